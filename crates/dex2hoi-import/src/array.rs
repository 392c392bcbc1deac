//! numpy element types (`dtype` type strings such as `<f8`, `|b1`, `<U5`, `|O`) and the decoding
//! of raw little- or big-endian bytes into [`ArrayData`]. The arrays, [`NdArray`] (always held
//! in C (row-major) order, Fortran-ordered elements reordered when one is built), are defined
//! with the Python values they nest in and hold ([`crate::value`]) and re-exported here.

use crate::error::{ImportError, Result};

pub use crate::value::{ArrayData, NdArray, element_count};

/// The kind of a numpy element type (the letter of its type string).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DTypeKind {
    /// `f`: IEEE float (2, 4 or 8 bytes).
    Float,
    /// `i`: signed integer (1, 2, 4 or 8 bytes).
    Int,
    /// `u`: unsigned integer (1, 2, 4 or 8 bytes).
    UInt,
    /// `b` (`?`): boolean, one byte.
    Bool,
    /// `U`: fixed-length UTF-32 text; the size counts characters.
    Unicode,
    /// `S`: fixed-length bytes.
    Bytes,
    /// `O`: Python objects (pickled).
    Object,
}

/// A numpy element type: kind, size and byte order.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct DType {
    /// The kind.
    pub kind: DTypeKind,
    /// Bytes per element, or characters for [`DTypeKind::Unicode`] (0 for objects).
    pub size: usize,
    /// Big-endian storage (`>`); little-endian and byte-free types are `false`.
    pub big_endian: bool,
}

impl DType {
    /// Parses a numpy type string (`<f8`, `>i4`, `|b1`, `?`, `<U5`, `|S3`, `|O`, `O8`); the
    /// byte order prefix is optional (`=` and none mean little-endian, the only native order
    /// numpy is run on in practice). Structured and other types are refused.
    pub fn parse(type_string: &str, source_name: &str) -> Result<Self> {
        let refuse = || {
            ImportError::format(
                source_name,
                "array type",
                "a numeric, boolean, text or object numpy type (f, i, u, b, U, S, O)",
                format!("`{type_string}`"),
            )
        };
        let (big_endian, rest) = match type_string.as_bytes().first() {
            Some(b'>') => (true, &type_string[1..]),
            Some(b'<' | b'|' | b'=') => (false, &type_string[1..]),
            _ => (false, type_string),
        };
        if rest == "?" {
            return Ok(Self { kind: DTypeKind::Bool, size: 1, big_endian: false });
        }
        let mut chars = rest.chars();
        let letter = chars.next().ok_or_else(refuse)?;
        let digits = chars.as_str();
        let size: usize =
            if digits.is_empty() { 0 } else { digits.parse().map_err(|_| refuse())? };
        let kind = match letter {
            'f' if matches!(size, 2 | 4 | 8) => DTypeKind::Float,
            'i' if matches!(size, 1 | 2 | 4 | 8) => DTypeKind::Int,
            'u' if matches!(size, 1 | 2 | 4 | 8) => DTypeKind::UInt,
            'b' if size == 1 => DTypeKind::Bool,
            // A width of at least one character: zero-width strings would let a header's
            // element count ask for any number of elements with no bytes behind them.
            'U' if size >= 1 && size.checked_mul(4).is_some() => DTypeKind::Unicode,
            'S' if size >= 1 => DTypeKind::Bytes,
            'O' => return Ok(Self { kind: DTypeKind::Object, size: 0, big_endian: false }),
            _ => return Err(refuse()),
        };
        Ok(Self { kind, size, big_endian })
    }

    /// Bytes one element occupies in raw storage.
    pub fn item_bytes(&self) -> usize {
        match self.kind {
            DTypeKind::Unicode => self.size * 4,
            _ => self.size,
        }
    }

    /// The type string numpy would write (`<f8`, `|b1`, `|O`).
    pub fn type_string(&self) -> String {
        let letter = match self.kind {
            DTypeKind::Float => 'f',
            DTypeKind::Int => 'i',
            DTypeKind::UInt => 'u',
            DTypeKind::Bool => 'b',
            DTypeKind::Unicode => 'U',
            DTypeKind::Bytes => 'S',
            DTypeKind::Object => return "|O".into(),
        };
        let order = if matches!(self.kind, DTypeKind::Bool | DTypeKind::Bytes) || self.size == 1 {
            '|'
        } else if self.big_endian {
            '>'
        } else {
            '<'
        };
        format!("{order}{letter}{}", self.size)
    }
}

/// IEEE half precision to `f64` (numpy's `f2`).
fn half_to_f64(bits: u16) -> f64 {
    let sign = if bits & 0x8000 != 0 { -1.0 } else { 1.0 };
    let exponent = i32::from((bits >> 10) & 0x1f);
    let mantissa = f64::from(bits & 0x3ff);
    match exponent {
        0 => sign * mantissa * 2f64.powi(-24),
        31 if mantissa == 0.0 => sign * f64::INFINITY,
        31 => f64::NAN,
        _ => sign * (1.0 + mantissa / 1024.0) * 2f64.powi(exponent - 15),
    }
}

/// Decodes `count` elements of raw storage. Object arrays are not raw storage (they are
/// pickled) and are refused here.
pub fn decode_raw(
    dtype: DType,
    bytes: &[u8],
    count: usize,
    source_name: &str,
) -> Result<ArrayData> {
    let width = dtype.item_bytes();
    let needed = width.checked_mul(count).ok_or_else(|| {
        ImportError::format(source_name, "array size", "a size that fits memory", count)
    })?;
    if bytes.len() < needed {
        return Err(ImportError::format(
            source_name,
            "array data",
            format!("{needed} bytes for {count} elements of {}", dtype.type_string()),
            format!("{} bytes (the file is truncated)", bytes.len()),
        ));
    }
    let bytes = &bytes[..needed];
    // Each element as 8 bytes in little-endian order, zero- or sign-extended later.
    let word = |chunk: &[u8]| -> [u8; 8] {
        let mut out = [0u8; 8];
        if dtype.big_endian {
            for (k, b) in chunk.iter().rev().enumerate() {
                out[k] = *b;
            }
        } else {
            out[..chunk.len()].copy_from_slice(chunk);
        }
        out
    };
    let data = match dtype.kind {
        DTypeKind::Float => ArrayData::Float(
            bytes
                .chunks_exact(width)
                .map(|c| {
                    let w = word(c);
                    match width {
                        2 => half_to_f64(u16::from_le_bytes([w[0], w[1]])),
                        4 => f64::from(f32::from_le_bytes([w[0], w[1], w[2], w[3]])),
                        _ => f64::from_le_bytes(w),
                    }
                })
                .collect(),
        ),
        DTypeKind::Int => ArrayData::Int(
            bytes
                .chunks_exact(width)
                .map(|c| {
                    let raw = i64::from_le_bytes(word(c));
                    let shift = 64 - 8 * width as u32;
                    // Sign-extend from the element's width.
                    (raw << shift) >> shift
                })
                .collect(),
        ),
        DTypeKind::UInt => {
            let values: Vec<u64> =
                bytes.chunks_exact(width).map(|c| u64::from_le_bytes(word(c))).collect();
            if let Some(big) = values.iter().find(|v| **v > i64::MAX as u64) {
                return Err(ImportError::format(
                    source_name,
                    "unsigned value",
                    "values below 2^63",
                    big,
                ));
            }
            ArrayData::Int(values.into_iter().map(|v| v as i64).collect())
        }
        DTypeKind::Bool => ArrayData::Bool(bytes.iter().map(|b| *b != 0).collect()),
        DTypeKind::Bytes => ArrayData::Bytes(
            bytes
                .chunks(width.max(1))
                .take(count)
                .map(|c| {
                    let end = c.iter().rposition(|b| *b != 0).map_or(0, |p| p + 1);
                    c[..end].to_vec()
                })
                .collect(),
        ),
        DTypeKind::Unicode => {
            let mut strings = Vec::with_capacity(count);
            for c in bytes.chunks(width.max(1)).take(count) {
                let mut text = String::new();
                for unit in c.chunks_exact(4) {
                    let w = word(unit);
                    let code = u32::from_le_bytes([w[0], w[1], w[2], w[3]]);
                    let ch = char::from_u32(code).ok_or_else(|| {
                        ImportError::format(source_name, "text element", "UTF-32 characters", code)
                    })?;
                    text.push(ch);
                }
                strings.push(text.trim_end_matches('\0').to_string());
            }
            ArrayData::Str(strings)
        }
        DTypeKind::Object => {
            return Err(ImportError::format(
                source_name,
                "array type",
                "raw (non-object) storage",
                "an object array",
            ));
        }
    };
    Ok(data)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn type_strings_parse_and_print() {
        for (text, kind, size, big) in [
            ("<f8", DTypeKind::Float, 8, false),
            (">i4", DTypeKind::Int, 4, true),
            ("|b1", DTypeKind::Bool, 1, false),
            ("?", DTypeKind::Bool, 1, false),
            ("<U5", DTypeKind::Unicode, 5, false),
            ("u2", DTypeKind::UInt, 2, false),
        ] {
            let dtype = DType::parse(text, "t").unwrap();
            assert_eq!((dtype.kind, dtype.size, dtype.big_endian), (kind, size, big), "{text}");
        }
        assert_eq!(DType::parse("|O", "t").unwrap().kind, DTypeKind::Object);
        assert_eq!(DType::parse("<f4", "t").unwrap().type_string(), "<f4");
        // Zero-width strings (which would decode any element count from no bytes) and widths
        // whose byte size overflows are refused.
        for bad in ["<c16", "V8", "<f3", "", "<M8[ns]", "<U0", "<U", "|S0", "<U4611686018427387904"]
        {
            assert!(DType::parse(bad, "t").is_err(), "{bad}");
        }
    }

    #[test]
    fn raw_values_decode_in_both_byte_orders() {
        let little = DType::parse("<i2", "t").unwrap();
        let big = DType::parse(">i2", "t").unwrap();
        assert_eq!(
            decode_raw(little, &[0xfe, 0xff, 3, 0], 2, "t").unwrap(),
            ArrayData::Int(vec![-2, 3])
        );
        assert_eq!(
            decode_raw(big, &[0xff, 0xfe, 0, 3], 2, "t").unwrap(),
            ArrayData::Int(vec![-2, 3])
        );
        let half = DType::parse("<f2", "t").unwrap();
        // 1.0 and -2.5 in half precision.
        assert_eq!(
            decode_raw(half, &[0x00, 0x3c, 0x00, 0xc1], 2, "t").unwrap(),
            ArrayData::Float(vec![1.0, -2.5])
        );
        let truncated = decode_raw(DType::parse("<f8", "t").unwrap(), &[0; 12], 2, "file.npy");
        let message = truncated.unwrap_err().to_string();
        assert!(message.contains("file.npy") && message.contains("truncated"), "{message}");
    }
}
