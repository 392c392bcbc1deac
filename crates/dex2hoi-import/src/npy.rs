//! numpy's `.npy` and `.npz` files, read natively: the header (versions 1-3), raw arrays of
//! the types in [`crate::array`], and object arrays, whose data is a pickle read by the
//! data-only [`crate::pickle`] reader (GRAB's 0-d object arrays of dicts, HIMO's pose dicts).
//!
//! `.npz` archives (stored or deflated zip files, as `np.savez` and `np.savez_compressed`
//! write them) are opened through `npyz`'s zip layer; each entry is read whole and parsed here.

use std::io::Read;
use std::path::{Path, PathBuf};

use crate::array::{DType, DTypeKind, decode_raw};
use crate::error::{ImportError, Result};
use crate::pickle::read_pickle;
use crate::value::{NdArray, Value, element_count};

/// The largest archive entry read (decompressed), 1 GiB: the largest arrays of the real GRAB,
/// HUMOTO and HIMO files are tens of MB, so this leaves a wide margin while a zip bomb fails
/// before it fills the memory of a small machine.
pub const MAX_ENTRY_BYTES: u64 = 1 << 30;

/// The most bytes one compressed byte of an entry can stand for: deflate's limit (a 258-byte
/// match in at best two bits, about 1032 to 1), the only compression `np.savez_compressed`
/// uses. An entry declaring more than its compressed size times this is a lie or another
/// method, and is refused before anything is read: a small file cannot claim gigabytes.
pub const MAX_EXPANSION: u64 = 1032;

/// The most an archive entry's declared size reserves before its data is read.
const PREALLOCATE_BYTES: u64 = 64 << 20;

/// The parsed header of an `.npy` file.
#[derive(Debug, Clone, PartialEq, Eq)]
struct Header {
    dtype_text: String,
    fortran_order: bool,
    shape: Vec<usize>,
}

/// Reads an `.npy` file. Object arrays come back as arrays of [`Value`]s; a 0-d object array
/// (what `np.save(path, some_dict)` writes) is one element (see [`Value::item`]).
pub fn read_npy(path: &Path) -> Result<Value> {
    let bytes = std::fs::read(path).map_err(ImportError::io(path))?;
    parse_npy(&bytes, &path.display().to_string())
}

/// Parses the bytes of an `.npy` file; `source_name` names it in errors.
pub fn parse_npy(bytes: &[u8], source_name: &str) -> Result<Value> {
    let malformed = |what: &str, expected: &str, got: String| {
        ImportError::format(source_name, what, expected, got)
    };
    if bytes.len() < 10 || &bytes[..6] != b"\x93NUMPY" {
        return Err(malformed(
            "magic",
            "a numpy file starting with \\x93NUMPY",
            format!("{} bytes starting {:?}", bytes.len(), &bytes[..bytes.len().min(6)]),
        ));
    }
    let major = bytes[6];
    let (length, start) = match major {
        1 => (usize::from(u16::from_le_bytes([bytes[8], bytes[9]])), 10),
        2 | 3 if bytes.len() >= 12 => {
            (u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize, 12)
        }
        _ => return Err(malformed("version", "1, 2 or 3", format!("{major}.{}", bytes[7]))),
    };
    let end = start + length;
    if bytes.len() < end {
        return Err(malformed(
            "header",
            &format!("{length} header bytes"),
            format!("{} (the file is truncated)", bytes.len() - start),
        ));
    }
    let text = std::str::from_utf8(&bytes[start..end])
        .map_err(|_| malformed("header", "UTF-8 text", "other bytes".into()))?;
    let header = parse_header(text, source_name)?;
    let dtype = DType::parse(&header.dtype_text, source_name)?;
    let data = &bytes[end..];
    let count = element_count(&header.shape, source_name)?;
    if dtype.kind == DTypeKind::Object {
        let (value, _) = read_pickle(data, source_name)?;
        return match value {
            Value::Array(array) if array.shape == header.shape => Ok(Value::Array(array)),
            other => Err(malformed(
                "pickled object array",
                &format!("an array of shape {:?}", header.shape),
                other.type_name(),
            )),
        };
    }
    let values = decode_raw(dtype, data, count, source_name)?;
    Ok(Value::Array(NdArray::new(header.shape, values, header.fortran_order, source_name)?))
}

/// A tiny reader of the Python dict literal of a numpy header:
/// `{'descr': '<f8', 'fortran_order': False, 'shape': (3, 4), }`.
fn parse_header(text: &str, source_name: &str) -> Result<Header> {
    let malformed = |got: &str| {
        ImportError::format(
            source_name,
            "header",
            "a dict with 'descr' (a type string), 'fortran_order' and 'shape'",
            got,
        )
    };
    let field = |key: &str| -> Result<&str> {
        let quoted = format!("'{key}':");
        let at = text.find(&quoted).ok_or_else(|| malformed(text.trim()))?;
        Ok(text[at + quoted.len()..].trim_start())
    };
    let descr = field("descr")?;
    let dtype_text = match descr.strip_prefix('\'') {
        Some(rest) => rest.split('\'').next().unwrap_or_default().to_string(),
        None => {
            return Err(ImportError::format(
                source_name,
                "array type",
                "a plain numpy type (structured arrays are not read)",
                descr.split('}').next().unwrap_or(descr).trim(),
            ));
        }
    };
    let fortran = field("fortran_order")?;
    let fortran_order = if fortran.starts_with("True") {
        true
    } else if fortran.starts_with("False") {
        false
    } else {
        return Err(malformed(text.trim()));
    };
    let shape_text = field("shape")?;
    let inner = shape_text
        .strip_prefix('(')
        .and_then(|s| s.split(')').next())
        .ok_or_else(|| malformed(text.trim()))?;
    let shape = inner
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| s.trim_end_matches('L').parse::<usize>().map_err(|_| malformed(text.trim())))
        .collect::<Result<Vec<_>>>()?;
    Ok(Header { dtype_text, fortran_order, shape })
}

/// An open `.npz` archive.
pub struct Npz {
    path: PathBuf,
    /// The archive's size on disk: no entry's compressed data can be larger.
    file_bytes: u64,
    archive: npyz::npz::NpzArchive<std::io::BufReader<std::fs::File>>,
}

impl std::fmt::Debug for Npz {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Npz").field("path", &self.path).finish_non_exhaustive()
    }
}

impl Npz {
    /// Opens an archive.
    pub fn open(path: &Path) -> Result<Self> {
        let archive = npyz::npz::NpzArchive::open(path).map_err(|source| {
            if source.kind() == std::io::ErrorKind::NotFound {
                ImportError::Io { path: path.to_path_buf(), source }
            } else {
                ImportError::format(path.display(), "archive", "an .npz (zip) archive", source)
            }
        })?;
        let file_bytes = std::fs::metadata(path).map_err(ImportError::io(path))?.len();
        Ok(Self { path: path.to_path_buf(), file_bytes, archive })
    }

    /// The file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The array names in the archive (entry names without `.npy`).
    pub fn names(&self) -> Vec<String> {
        self.archive.array_names().map(String::from).collect()
    }

    /// Whether the archive holds an array of that name.
    pub fn contains(&self, name: &str) -> bool {
        self.archive.array_names().any(|n| n == name)
    }

    /// Reads one array; `expected` says what it should hold, for the error when it is missing.
    pub fn read(&mut self, name: &str, expected: &str) -> Result<Value> {
        let source_name = format!("{}[{name}]", self.path.display());
        let entry_name = npyz::npz::file_name_from_array_name(name);
        let path = self.path.clone();
        let mut entry = match self.archive.zip_archive().by_name(&entry_name) {
            Ok(entry) => entry,
            Err(_) => return Err(ImportError::missing(path.display(), name, expected)),
        };
        // What the entry may hold: what it declares, if its compressed data fits in the file,
        // deflate could expand that data so far, and the cap allows.
        let compressed = entry.compressed_size();
        let limit = MAX_ENTRY_BYTES.min(compressed.saturating_mul(MAX_EXPANSION));
        if compressed > self.file_bytes || entry.size() > limit {
            return Err(ImportError::format(
                &source_name,
                "entry size",
                format!(
                    "at most {limit} bytes ({MAX_EXPANSION} times its {compressed} compressed \
                     bytes in a file of {}, at most {MAX_ENTRY_BYTES})",
                    self.file_bytes
                ),
                entry.size(),
            ));
        }
        // The declared size is not trusted for the allocation (a lie would reserve gigabytes;
        // found by the `npy` fuzz target): reading grows the buffer as data comes, and stops
        // past the declared size.
        let declared = entry.size();
        let mut bytes = Vec::with_capacity(declared.min(PREALLOCATE_BYTES) as usize);
        (&mut entry)
            .take(declared + 1)
            .read_to_end(&mut bytes)
            .map_err(|e| ImportError::format(&source_name, "entry data", "a readable entry", e))?;
        if bytes.len() as u64 > declared {
            return Err(ImportError::format(
                &source_name,
                "entry data",
                format!("the {declared} bytes the entry declares"),
                "more",
            ));
        }
        parse_npy(&bytes, &source_name)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::value::ArrayData;

    fn npy(header: &str, data: &[u8]) -> Vec<u8> {
        let mut header = header.to_string();
        while !(10 + header.len() + 1).is_multiple_of(64) {
            header.push(' ');
        }
        header.push('\n');
        let mut bytes = b"\x93NUMPY\x01\x00".to_vec();
        bytes.extend((header.len() as u16).to_le_bytes());
        bytes.extend(header.as_bytes());
        bytes.extend(data);
        bytes
    }

    #[test]
    fn headers_parse() {
        let h = parse_header("{'descr': '<f8', 'fortran_order': False, 'shape': (3, 4), }", "t")
            .unwrap();
        assert_eq!(h, Header { dtype_text: "<f8".into(), fortran_order: false, shape: vec![3, 4] });
        let h = parse_header("{'descr': '|O', 'fortran_order': True, 'shape': (), }", "t").unwrap();
        assert!(h.shape.is_empty() && h.fortran_order);
        let h =
            parse_header("{'descr': '<i8', 'fortran_order': False, 'shape': (5,), }", "t").unwrap();
        assert_eq!(h.shape, vec![5]);
        let structured = "{'descr': [('a', '<f4')], 'fortran_order': False, 'shape': (2,), }";
        assert!(parse_header(structured, "t").unwrap_err().to_string().contains("structured"));
    }

    /// An entry whose declared size is more than deflate could make of its compressed bytes is
    /// refused before it is read (the reader used to reserve up to 64 MiB for it and would read
    /// up to 8 GiB).
    #[test]
    fn entries_declaring_more_than_they_can_hold_are_refused() {
        use npyz::WriterBuilder;
        let dir = std::env::temp_dir().join(format!("dex2hoi-npz-size-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("liar.npz");
        {
            let mut npz = npyz::npz::NpzWriter::create(&path).unwrap();
            let mut writer = npz
                .array::<f64>("a", Default::default())
                .unwrap()
                .default_dtype()
                .shape(&[4])
                .begin_nd()
                .unwrap();
            writer.extend([1.0, 2.0, 3.0, 4.0]).unwrap();
            writer.finish().unwrap();
        }
        assert!(Npz::open(&path).unwrap().read("a", "an array").is_ok());
        // 4 GiB declared in the central directory and the local header.
        let mut bytes = std::fs::read(&path).unwrap();
        let central = bytes.windows(4).rposition(|w| w == b"PK\x01\x02").unwrap();
        bytes[central + 24..central + 28].copy_from_slice(&0xFFFF_FFF0u32.to_le_bytes());
        bytes[22..26].copy_from_slice(&0xFFFF_FFF0u32.to_le_bytes());
        std::fs::write(&path, &bytes).unwrap();
        let error = Npz::open(&path).unwrap().read("a", "an array").unwrap_err().to_string();
        assert!(error.contains("liar.npz[a]") && error.contains("entry size"), "{error}");
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn raw_arrays_and_errors() {
        let data: Vec<u8> = [1.5f32, -2.0].iter().flat_map(|v| v.to_le_bytes()).collect();
        let bytes = npy("{'descr': '<f4', 'fortran_order': False, 'shape': (2,), }", &data);
        let Value::Array(a) = parse_npy(&bytes, "a.npy").unwrap() else { panic!() };
        assert_eq!((a.shape, a.data), (vec![2], ArrayData::Float(vec![1.5, -2.0])));
        let short = &bytes[..bytes.len() - 1];
        assert!(parse_npy(short, "a.npy").unwrap_err().to_string().contains("truncated"));
        assert!(parse_npy(b"not numpy", "b.npy").unwrap_err().to_string().contains("b.npy"));
    }
}
