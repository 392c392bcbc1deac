//! File helpers of the run directory.

use std::io::Write;
use std::path::Path;

use dex2hoi_data::files::write_atomically;

use crate::error::{Result, TrainError};

/// Appends a line to a file (creating it).
pub(crate) fn append_line(path: &Path, line: &str) -> Result<()> {
    let mut file = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(path)
        .map_err(TrainError::io(path, "opening for appending"))?;
    writeln!(file, "{line}").map_err(TrainError::io(path, "appending"))
}

/// Writes a file atomically (a temporary file beside it, then a rename).
pub(crate) fn write_file(path: &Path, bytes: &[u8]) -> Result<()> {
    Ok(write_atomically(path, bytes)?)
}
