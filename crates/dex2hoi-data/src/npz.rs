//! numpy archives (`.npz`) written without Python: `.npy` members (format version 1.0: magic,
//! header dictionary padded to 64 bytes, little-endian C-order data) deflated into a zip with a
//! fixed timestamp, so the same arrays always give the same bytes. Strings are numpy unicode
//! arrays (`<U..`), which numpy reads without `allow_pickle`.

use std::io::{Cursor, Write};

use zip::write::FileOptions;
use zip::{CompressionMethod, DateTime, ZipWriter};

use crate::error::{DataError, Result};

/// The values of one array.
#[derive(Debug, Clone, PartialEq)]
pub enum Values {
    /// `<f4`.
    F32(Vec<f32>),
    /// `<i8`.
    I64(Vec<i64>),
    /// `<U..`, as wide as the longest string.
    Text(Vec<String>),
}

/// One named array of an archive.
#[derive(Debug, Clone, PartialEq)]
pub struct NpyArray {
    /// The member name without `.npy`.
    pub name: String,
    /// The shape (`[]` for a scalar).
    pub shape: Vec<usize>,
    /// The values, C order.
    pub values: Values,
}

impl NpyArray {
    /// A `float32` array.
    pub fn f32(name: impl Into<String>, shape: &[usize], values: Vec<f32>) -> Self {
        Self { name: name.into(), shape: shape.to_vec(), values: Values::F32(values) }
    }

    /// An `int64` array.
    pub fn i64(name: impl Into<String>, shape: &[usize], values: Vec<i64>) -> Self {
        Self { name: name.into(), shape: shape.to_vec(), values: Values::I64(values) }
    }

    /// A unicode string array.
    pub fn text(name: impl Into<String>, shape: &[usize], values: Vec<String>) -> Self {
        Self { name: name.into(), shape: shape.to_vec(), values: Values::Text(values) }
    }

    /// The `.npy` bytes: magic, version 1.0, header, data.
    pub fn npy_bytes(&self) -> Vec<u8> {
        let descr = match &self.values {
            Values::F32(_) => "<f4".to_string(),
            Values::I64(_) => "<i8".to_string(),
            // numpy needs at least one character per element ('<U0' does not round-trip).
            Values::Text(texts) => {
                format!("<U{}", texts.iter().map(|t| t.chars().count()).max().unwrap_or(0).max(1))
            }
        };
        let shape = match self.shape.as_slice() {
            [] => "()".to_string(),
            [n] => format!("({n},)"),
            dims => {
                format!("({})", dims.iter().map(|d| d.to_string()).collect::<Vec<_>>().join(", "))
            }
        };
        let mut header =
            format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape}, }}");
        // Magic (6) + version (2) + header length (2) + header + '\n', padded to 64 bytes.
        let unpadded = 10 + header.len() + 1;
        header.push_str(&" ".repeat(unpadded.next_multiple_of(64) - unpadded));
        header.push('\n');
        let mut bytes = b"\x93NUMPY\x01\x00".to_vec();
        let header_length = u16::try_from(header.len()).unwrap_or(u16::MAX);
        bytes.extend_from_slice(&header_length.to_le_bytes());
        bytes.extend_from_slice(header.as_bytes());
        match &self.values {
            Values::F32(values) => values.iter().for_each(|v| bytes.extend(v.to_le_bytes())),
            Values::I64(values) => values.iter().for_each(|v| bytes.extend(v.to_le_bytes())),
            Values::Text(texts) => {
                let width = descr[2..].parse::<usize>().unwrap_or(1);
                for text in texts {
                    let mut chars = text.chars().map(u32::from).collect::<Vec<_>>();
                    chars.resize(width, 0);
                    chars.iter().for_each(|c| bytes.extend(c.to_le_bytes()));
                }
            }
        }
        bytes
    }
}

/// The bytes of an `.npz` archive of the arrays, refusing an array whose values do not fill
/// its shape.
pub fn encode_npz(arrays: &[NpyArray]) -> Result<Vec<u8>> {
    let zip_error = |e: zip::result::ZipError| {
        DataError::invalid("npz archive", "an archive written in memory", e)
    };
    let io_error =
        |e: std::io::Error| DataError::invalid("npz archive", "an archive written in memory", e);
    let options = FileOptions::default()
        .compression_method(CompressionMethod::Deflated)
        .last_modified_time(DateTime::default());
    let mut zip = ZipWriter::new(Cursor::new(Vec::new()));
    for array in arrays {
        let count = match &array.values {
            Values::F32(v) => v.len(),
            Values::I64(v) => v.len(),
            Values::Text(v) => v.len(),
        };
        let expected: usize = array.shape.iter().product();
        if count != expected {
            return Err(DataError::invalid(
                &array.name,
                format!("{expected} values for shape {:?}", array.shape),
                count,
            ));
        }
        zip.start_file(format!("{}.npy", array.name), options).map_err(zip_error)?;
        zip.write_all(&array.npy_bytes()).map_err(io_error)?;
    }
    Ok(zip.finish().map_err(zip_error)?.into_inner())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn npy_header_is_padded_to_64_bytes_and_ends_with_a_newline() {
        for array in [
            NpyArray::f32("a", &[2, 3], vec![0.0; 6]),
            NpyArray::f32("b", &[], vec![1.5]),
            NpyArray::text("c", &[2], vec!["ab".into(), "".into()]),
            NpyArray::i64("d", &[0], vec![]),
        ] {
            let bytes = array.npy_bytes();
            let header_length = u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
            assert_eq!((10 + header_length) % 64, 0);
            assert_eq!(bytes[10 + header_length - 1], b'\n');
        }
    }

    #[test]
    fn an_array_that_does_not_fill_its_shape_is_refused() {
        let error = encode_npz(&[NpyArray::f32("short", &[2, 2], vec![1.0; 3])]).unwrap_err();
        assert!(error.to_string().contains("short"), "{error}");
    }

    #[test]
    fn npy_bytes_read_back_with_npyz() {
        let array = NpyArray::f32("a", &[2, 3], vec![1.0, 2.0, 3.0, 4.0, 5.0, 6.5]);
        let bytes = array.npy_bytes();
        let file = npyz::NpyFile::new(&bytes[..]).expect("a valid npy file");
        assert_eq!(file.shape(), &[2, 3]);
        assert_eq!(file.into_vec::<f32>().expect("f32 data"), vec![1.0, 2.0, 3.0, 4.0, 5.0, 6.5]);
        let text = NpyArray::text("t", &[2], vec!["héllo".into(), "a".into()]);
        let bytes = text.npy_bytes();
        let file = npyz::NpyFile::new(&bytes[..]).expect("a valid npy file");
        assert_eq!(file.dtype().descr(), "'<U5'");
        assert_eq!(file.into_vec::<String>().expect("strings"), vec!["héllo", "a"]);
    }
}
