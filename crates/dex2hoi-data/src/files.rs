//! Files written whole or not at all: every file dex2hoi writes goes through
//! [`write_atomically`], so an interrupted write never leaves a partial file under the final
//! name.

use std::path::{Path, PathBuf};

use crate::error::{DataError, Result};

/// Maps an I/O error on `path` to a [`DataError::Io`] saying what was being done.
pub(crate) fn io_error<'a>(
    path: &'a Path,
    action: &'static str,
) -> impl FnOnce(std::io::Error) -> DataError + 'a {
    move |source| DataError::Io { path: path.to_path_buf(), action, source }
}

/// Writes a file atomically: a temporary file beside it, then a rename.
pub fn write_atomically(path: &Path, bytes: &[u8]) -> Result<()> {
    let temporary = temporary_path(path);
    std::fs::write(&temporary, bytes).map_err(io_error(&temporary, "writing"))?;
    std::fs::rename(&temporary, path).map_err(io_error(path, "renaming into place"))
}

/// The name a file is written under before it is renamed into place (unique per process).
pub(crate) fn temporary_path(path: &Path) -> PathBuf {
    let mut name = path.file_name().map(|n| n.to_os_string()).unwrap_or_default();
    name.push(format!(".tmp-{}", std::process::id()));
    path.with_file_name(name)
}
