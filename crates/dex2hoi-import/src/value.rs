//! Python data as read from pickles and numpy files ([`Value`], numpy arrays among them as
//! [`NdArray`], whose object elements are values in turn), and [`Field`], a view of a value at a
//! key path inside a file that turns every "missing key", "wrong type" and "wrong shape" into an
//! error naming the file and the path (`mug_pass.npz[body].params.transl`).

use crate::error::{ImportError, Result};

/// A Python value built by the data-only unpickler or read from a numpy file.
#[derive(Debug, Clone, PartialEq)]
pub enum Value {
    /// `None`.
    None,
    /// `bool`.
    Bool(bool),
    /// `int` (within `i64`).
    Int(i64),
    /// `float`.
    Float(f64),
    /// `str`.
    Str(String),
    /// `bytes`, `bytearray` (and Python 2 `str`).
    Bytes(Vec<u8>),
    /// `list`.
    List(Vec<Value>),
    /// `tuple`.
    Tuple(Vec<Value>),
    /// `dict`, in insertion order.
    Dict(Vec<(Value, Value)>),
    /// `set` or `frozenset`.
    Set(Vec<Value>),
    /// A numpy array (a numpy scalar is a 0-d array).
    Array(NdArray),
}

impl Value {
    /// A short description of the value's type for messages.
    pub fn type_name(&self) -> String {
        match self {
            Self::None => "None".into(),
            Self::Bool(_) => "a bool".into(),
            Self::Int(_) => "an int".into(),
            Self::Float(_) => "a float".into(),
            Self::Str(_) => "a str".into(),
            Self::Bytes(_) => "bytes".into(),
            Self::List(v) => format!("a list of {}", v.len()),
            Self::Tuple(v) => format!("a tuple of {}", v.len()),
            Self::Dict(_) => "a dict".into(),
            Self::Set(_) => "a set".into(),
            Self::Array(a) => format!("a {} array of shape {:?}", a.data.kind_name(), a.shape),
        }
    }

    /// The text of a dict key (`str`, or Python 2 byte strings read as Latin-1).
    fn key_text(&self) -> Option<String> {
        match self {
            Self::Str(s) => Some(s.clone()),
            Self::Bytes(b) => Some(b.iter().map(|&c| char::from(c)).collect()),
            _ => None,
        }
    }

    /// numpy's `.item()` of a 0-d object array (GRAB's top-level entries); other values as
    /// they are.
    pub fn item(&self) -> &Value {
        match self {
            Self::Array(NdArray { shape, data: ArrayData::Object(items) })
                if shape.is_empty() && items.len() == 1 =>
            {
                items[0].item()
            }
            other => other,
        }
    }
}

/// The elements of an array, in C order.
#[derive(Debug, Clone, PartialEq)]
pub enum ArrayData {
    /// Floats of any size, widened to `f64`.
    Float(Vec<f64>),
    /// Integers of any size and sign that fit `i64`.
    Int(Vec<i64>),
    /// Booleans.
    Bool(Vec<bool>),
    /// Text elements (trailing NULs removed, as numpy does).
    Str(Vec<String>),
    /// Byte-string elements (trailing NULs removed).
    Bytes(Vec<Vec<u8>>),
    /// Python objects.
    Object(Vec<Value>),
}

impl ArrayData {
    /// Number of elements.
    pub fn len(&self) -> usize {
        match self {
            Self::Float(v) => v.len(),
            Self::Int(v) => v.len(),
            Self::Bool(v) => v.len(),
            Self::Str(v) => v.len(),
            Self::Bytes(v) => v.len(),
            Self::Object(v) => v.len(),
        }
    }

    /// `true` when there are no elements.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// A short name of the element kind for messages.
    pub fn kind_name(&self) -> &'static str {
        match self {
            Self::Float(_) => "float",
            Self::Int(_) => "integer",
            Self::Bool(_) => "boolean",
            Self::Str(_) => "text",
            Self::Bytes(_) => "bytes",
            Self::Object(_) => "object",
        }
    }

    /// Reorders the elements by `order` (`new[i] = old[order[i]]`).
    fn permuted(self, order: &[usize]) -> Self {
        fn pick<T: Clone>(values: Vec<T>, order: &[usize]) -> Vec<T> {
            order.iter().map(|&i| values[i].clone()).collect()
        }
        match self {
            Self::Float(v) => Self::Float(pick(v, order)),
            Self::Int(v) => Self::Int(pick(v, order)),
            Self::Bool(v) => Self::Bool(pick(v, order)),
            Self::Str(v) => Self::Str(pick(v, order)),
            Self::Bytes(v) => Self::Bytes(pick(v, order)),
            Self::Object(v) => Self::Object(pick(v, order)),
        }
    }
}

/// An n-dimensional numpy array in C order.
#[derive(Debug, Clone, PartialEq)]
pub struct NdArray {
    /// The shape (empty for a 0-d array).
    pub shape: Vec<usize>,
    /// The elements.
    pub data: ArrayData,
}

impl NdArray {
    /// Builds an array, checking that the element count matches the shape, and reorders
    /// Fortran-ordered elements into C order.
    pub fn new(
        shape: Vec<usize>,
        data: ArrayData,
        fortran_order: bool,
        source_name: &str,
    ) -> Result<Self> {
        let count = element_count(&shape, source_name)?;
        if data.len() != count {
            return Err(ImportError::format(
                source_name,
                "element count",
                format!("{count} elements for shape {shape:?}"),
                data.len(),
            ));
        }
        let data = if fortran_order && shape.len() > 1 {
            data.permuted(&fortran_to_c_order(&shape))
        } else {
            data
        };
        Ok(Self { shape, data })
    }

    /// Number of elements.
    pub fn len(&self) -> usize {
        self.data.len()
    }

    /// `true` when the array has no elements.
    pub fn is_empty(&self) -> bool {
        self.data.is_empty()
    }
}

/// The product of a shape's dimensions, refusing overflow.
pub fn element_count(shape: &[usize], source_name: &str) -> Result<usize> {
    shape.iter().try_fold(1usize, |n, &d| n.checked_mul(d)).ok_or_else(|| {
        ImportError::format(
            source_name,
            "shape",
            "an element count that fits memory",
            format!("{shape:?}"),
        )
    })
}

/// For each C-order position, the position of the same element in Fortran (column-major) order.
fn fortran_to_c_order(shape: &[usize]) -> Vec<usize> {
    let count: usize = shape.iter().product();
    let mut order = Vec::with_capacity(count);
    let mut index = vec![0usize; shape.len()];
    for _ in 0..count {
        let mut position = 0;
        let mut stride = 1;
        for (axis, &i) in index.iter().enumerate() {
            position += i * stride;
            stride *= shape[axis];
        }
        order.push(position);
        for axis in (0..shape.len()).rev() {
            index[axis] += 1;
            if index[axis] < shape[axis] {
                break;
            }
            index[axis] = 0;
        }
    }
    order
}

/// A value at a key path inside a file.
#[derive(Debug, Clone)]
pub struct Field<'a> {
    source_name: &'a str,
    path: String,
    value: &'a Value,
}

impl<'a> Field<'a> {
    /// The root of a file's content; `source_name` is the file (and entry) for messages,
    /// `path` the key path of `value` inside it (empty for the whole file).
    pub fn root(source_name: &'a str, path: &str, value: &'a Value) -> Self {
        Self { source_name, path: path.to_string(), value: value.item() }
    }

    /// The underlying value (0-d object arrays unwrapped).
    pub fn value(&self) -> &'a Value {
        self.value
    }

    /// The key path of this field.
    pub fn path(&self) -> &str {
        &self.path
    }

    /// The file this field comes from.
    pub fn source_name(&self) -> &'a str {
        self.source_name
    }

    fn wrong_type(&self, expected: &str) -> ImportError {
        ImportError::format(
            self.source_name,
            format!("`{}`", self.path),
            expected,
            self.value.type_name(),
        )
    }

    fn child_path(&self, key: &str) -> String {
        if self.path.is_empty() { key.to_string() } else { format!("{}.{key}", self.path) }
    }

    /// A child field for a value inside this one, named `key` in messages.
    pub fn child(&self, value: &'a Value, key: &str) -> Field<'a> {
        Field { source_name: self.source_name, path: self.child_path(key), value: value.item() }
    }

    /// The entry `key` of a dict; `expected` says what it should hold, for the error when it
    /// is missing.
    pub fn get(&self, key: &str, expected: &str) -> Result<Field<'a>> {
        let Value::Dict(entries) = self.value else {
            return Err(self.wrong_type("a dict"));
        };
        let value = entries
            .iter()
            .find(|(k, _)| k.key_text().as_deref() == Some(key))
            .map(|(_, v)| v)
            .ok_or_else(|| {
                ImportError::missing(self.source_name, self.child_path(key), expected)
            })?;
        Ok(self.child(value, key))
    }

    /// Whether this is a dict with the key.
    pub fn has(&self, key: &str) -> bool {
        matches!(self.value, Value::Dict(entries)
            if entries.iter().any(|(k, _)| k.key_text().as_deref() == Some(key)))
    }

    /// The entries of a dict with text keys, in order.
    pub fn entries(&self) -> Result<Vec<(String, Field<'a>)>> {
        let Value::Dict(entries) = self.value else {
            return Err(self.wrong_type("a dict"));
        };
        entries
            .iter()
            .map(|(k, v)| {
                let key = k.key_text().ok_or_else(|| {
                    ImportError::format(
                        self.source_name,
                        format!("keys of `{}`", self.path),
                        "text keys",
                        k.type_name(),
                    )
                })?;
                let child = self.child(v, &key);
                Ok((key, child))
            })
            .collect()
    }

    /// The items of a list or tuple (or the elements of a 1-d object array), named
    /// `path[i]` in messages.
    pub fn items(&self) -> Result<Vec<Field<'a>>> {
        let values = match self.value {
            Value::List(v) | Value::Tuple(v) => v,
            Value::Array(NdArray { shape, data: ArrayData::Object(v) }) if shape.len() == 1 => v,
            _ => return Err(self.wrong_type("a list")),
        };
        Ok(values
            .iter()
            .enumerate()
            .map(|(i, v)| Field {
                source_name: self.source_name,
                path: format!("{}[{i}]", self.path),
                value: v.item(),
            })
            .collect())
    }

    /// Text: a `str`, Latin-1 bytes, or a one-element text array.
    pub fn text(&self) -> Result<String> {
        match self.value {
            Value::Str(_) | Value::Bytes(_) => {
                self.value.key_text().ok_or_else(|| self.wrong_type("text"))
            }
            Value::Array(NdArray { data: ArrayData::Str(v), .. }) if v.len() == 1 => {
                Ok(v[0].clone())
            }
            Value::Array(NdArray { data: ArrayData::Bytes(v), .. }) if v.len() == 1 => {
                Ok(v[0].iter().map(|&c| char::from(c)).collect())
            }
            _ => Err(self.wrong_type("text")),
        }
    }

    /// A single number: an int, a float, a bool or a one-element numeric array.
    pub fn number(&self) -> Result<f64> {
        let (values, _) = self.numbers_any_shape()?;
        if values.len() != 1 {
            return Err(self.wrong_type("a single number"));
        }
        Ok(values[0])
    }

    /// Numbers of any shape: a numeric (or boolean) array, an object array of numbers, or
    /// nested lists/tuples of numbers with a rectangular shape. Values must be finite.
    pub fn numbers_any_shape(&self) -> Result<(Vec<f64>, Vec<usize>)> {
        let nested = |items: &'a [Value], outer: &[usize]| -> Result<(Vec<f64>, Vec<usize>)> {
            let mut values = Vec::new();
            let mut inner: Option<Vec<usize>> = None;
            for (i, item) in items.iter().enumerate() {
                let child = Field {
                    source_name: self.source_name,
                    path: format!("{}[{i}]", self.path),
                    value: item.item(),
                };
                let (v, s) = child.numbers_any_shape()?;
                if inner.as_ref().is_some_and(|i| *i != s) {
                    return Err(self.wrong_type("numbers (nested lists of equal lengths)"));
                }
                inner = Some(s);
                values.extend(v);
            }
            let mut shape = outer.to_vec();
            shape.extend(inner.unwrap_or_default());
            Ok((values, shape))
        };
        let (values, shape) = match self.value {
            Value::Array(NdArray { shape, data }) => match data {
                ArrayData::Float(v) => (v.clone(), shape.clone()),
                ArrayData::Int(v) => (v.iter().map(|&x| x as f64).collect(), shape.clone()),
                ArrayData::Bool(v) => {
                    (v.iter().map(|&x| f64::from(u8::from(x))).collect(), shape.clone())
                }
                ArrayData::Object(items) => nested(items, shape)?,
                _ => return Err(self.wrong_type("a numeric array")),
            },
            Value::Int(i) => (vec![*i as f64], vec![]),
            Value::Float(f) => (vec![*f], vec![]),
            Value::Bool(b) => (vec![f64::from(u8::from(*b))], vec![]),
            Value::List(items) | Value::Tuple(items) => nested(items, &[items.len()])?,
            _ => return Err(self.wrong_type("numbers")),
        };
        if let Some(index) = values.iter().position(|v| !v.is_finite()) {
            return Err(ImportError::NonFinite {
                source_name: self.source_name.into(),
                key: self.path.clone(),
                index,
            });
        }
        Ok((values, shape))
    }

    /// Numbers with a required shape: `None` matches any size along that axis.
    pub fn numbers(&self, shape: &[Option<usize>]) -> Result<(Vec<f64>, Vec<usize>)> {
        let (values, got) = self.numbers_any_shape()?;
        let fits = got.len() == shape.len()
            && got.iter().zip(shape).all(|(g, s)| s.is_none_or(|s| s == *g));
        if !fits {
            return Err(ImportError::Shape {
                source_name: self.source_name.into(),
                key: self.path.clone(),
                expected: shape_words(shape),
                got,
            });
        }
        Ok((values, got))
    }
}

/// `(T, 3)` for `[None, Some(3)]`.
pub fn shape_words(shape: &[Option<usize>]) -> String {
    let parts: Vec<String> =
        shape.iter().map(|d| d.map_or_else(|| "T".to_string(), |d| d.to_string())).collect();
    if parts.len() == 1 { format!("({},)", parts[0]) } else { format!("({})", parts.join(", ")) }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fortran_order_becomes_c_order() {
        // numpy: np.arange(6).reshape(2, 3, order='F') stores 0..6 column-major.
        let data = ArrayData::Int((0..6).collect());
        let array = NdArray::new(vec![2, 3], data, true, "t").unwrap();
        assert_eq!(array.data, ArrayData::Int(vec![0, 2, 4, 1, 3, 5]));
        assert!(NdArray::new(vec![2, 2], ArrayData::Int(vec![1]), false, "t").is_err());
    }
}
