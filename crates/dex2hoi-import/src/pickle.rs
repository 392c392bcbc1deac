//! A bounded, data-only reader of Python pickles (protocols 2-5): enough for numpy's own
//! pickles of arrays (object arrays in `.npy` files, GRAB's dicts of ndarrays, HIMO's pose
//! dicts) and for plain Python containers (HUMOTO's lists of dicts of lists).
//!
//! Pickles are programs: `GLOBAL` names any Python callable and `REDUCE` calls it. This reader
//! never calls anything. It knows a fixed list of numpy reconstruction functions and emulates
//! what they build from their arguments (shape, dtype, order, raw bytes); every other global,
//! `REDUCE` target, `BUILD` target, extension code, persistent id or out-of-band buffer is
//! refused with an error that names the byte offset and the class. Nesting depth, the number of
//! objects and the size of what is built are bounded.
//!
//! Python objects live in an arena while the program runs, because pickles share them through
//! the memo and mutate them after memoising (an empty list is memoised, then appended to). The
//! result copies what the arena shares, so a few bytes of references to references can stand
//! for an exponentially large result (a "billion laughs": 123 bytes of nested `MARK`, `LIST`
//! and `DUP` asked for gigabytes). The result's size in memory is therefore counted while it
//! is built and bounded in proportion to the pickle's own size ([`PickleLimits`]).

use std::collections::HashMap;

use crate::array::{DType, DTypeKind, decode_raw};
use crate::error::{ImportError, Result};
use crate::value::{ArrayData, NdArray, Value, element_count};

/// Limits of the reader.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PickleLimits {
    /// The most objects the program may create (each int, float, list... counts one), and the
    /// most the result may hold.
    pub max_objects: usize,
    /// The deepest nesting of containers in the result.
    pub max_depth: usize,
    /// The most bytes the result may take in memory for each byte of the pickle, beyond
    /// [`PickleLimits::result_floor_bytes`] (see [`result_bytes`] for what counts).
    pub result_bytes_per_input_byte: usize,
    /// Bytes any pickle's result may take, however small the pickle.
    pub result_floor_bytes: usize,
}

impl Default for PickleLimits {
    /// HUMOTO's longest sequences are a few million small objects; 50 million objects is a
    /// few GB of memory at most. A pickle's result takes at most 64 bytes of memory per byte
    /// of the pickle plus 16 MiB: a real file takes far less, because everything in its result
    /// is written out in it once (a float is 9 bytes in the file and 32 in memory; a numpy
    /// array's elements at most twice their size in the file, widened to 64 bits), and only
    /// repeated dictionary keys are shared. The published HUMOTO pickle takes under 8 bytes a
    /// byte (`tests/realdata.rs` holds it to a quarter of the limit), numpy's pickles of GRAB's
    /// and HIMO's arrays about 2.
    fn default() -> Self {
        Self {
            max_objects: 50_000_000,
            max_depth: 100,
            result_bytes_per_input_byte: 64,
            result_floor_bytes: 16 << 20,
        }
    }
}

impl PickleLimits {
    /// The most bytes the result of a pickle of `input_bytes` bytes may take in memory.
    pub fn result_limit(&self, input_bytes: usize) -> usize {
        input_bytes
            .saturating_mul(self.result_bytes_per_input_byte)
            .saturating_add(self.result_floor_bytes)
    }
}

/// What a value takes in memory, as the reader counts it against
/// [`PickleLimits::result_bytes_per_input_byte`]: the value itself, plus its text, bytes or
/// array elements (an object array's elements are counted as values of their own).
pub fn result_bytes(value: &Value) -> usize {
    let own = size_of::<Value>();
    own + match value {
        Value::Str(text) => text.len(),
        Value::Bytes(bytes) => bytes.len(),
        Value::Array(array) => match &array.data {
            ArrayData::Float(v) => v.len() * 8,
            ArrayData::Int(v) => v.len() * 8,
            ArrayData::Bool(v) => v.len(),
            ArrayData::Str(v) => v.iter().map(|t| t.len() + size_of::<String>()).sum(),
            ArrayData::Bytes(v) => v.iter().map(|b| b.len() + size_of::<Vec<u8>>()).sum(),
            ArrayData::Object(v) => v.iter().map(result_bytes).sum(),
        },
        Value::List(items) | Value::Tuple(items) | Value::Set(items) => {
            items.iter().map(result_bytes).sum()
        }
        Value::Dict(pairs) => pairs.iter().map(|(k, v)| result_bytes(k) + result_bytes(v)).sum(),
        Value::None | Value::Bool(_) | Value::Int(_) | Value::Float(_) => 0,
    }
}

/// What is left of the limits while the result is built.
struct Budget {
    objects: usize,
    bytes: usize,
}

/// The callables a pickle may name: numpy's array, dtype and scalar reconstruction and the
/// byte-string helper of protocol 2. Nothing else.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Global {
    /// `numpy.core.multiarray._reconstruct` (`numpy._core` in numpy 2): an empty array,
    /// filled by `BUILD`.
    Reconstruct,
    /// `numpy.ndarray`: the class argument of `_reconstruct`.
    NdarrayClass,
    /// `numpy.dtype`.
    DTypeClass,
    /// `numpy.core.multiarray.scalar`: a numpy scalar from a dtype and its bytes.
    Scalar,
    /// `numpy.core.numeric._frombuffer`: an array from in-band bytes (protocol 5).
    FromBuffer,
    /// `_codecs.encode(text, 'latin1')`: how protocol 2 stores `bytes`.
    CodecsEncode,
}

impl Global {
    fn find(module: &str, name: &str) -> Option<Self> {
        let numpy_core = |m: &str, sub: &str| {
            m == format!("numpy.core.{sub}") || m == format!("numpy._core.{sub}")
        };
        match name {
            "_reconstruct" if numpy_core(module, "multiarray") => Some(Self::Reconstruct),
            "scalar" if numpy_core(module, "multiarray") => Some(Self::Scalar),
            "_frombuffer" if numpy_core(module, "numeric") => Some(Self::FromBuffer),
            "ndarray" if module == "numpy" => Some(Self::NdarrayClass),
            "dtype" if module == "numpy" => Some(Self::DTypeClass),
            "encode" if module == "_codecs" => Some(Self::CodecsEncode),
            _ => None,
        }
    }
}

/// An object under construction.
#[derive(Debug, Clone)]
enum Node {
    Value(Value),
    List(Vec<usize>),
    Tuple(Vec<usize>),
    Dict(Vec<(usize, usize)>),
    Set(Vec<usize>),
    Global(Global),
    DType(DType),
    /// The result of `_reconstruct`, waiting for its `BUILD` state.
    EmptyArray,
    /// An object array: shape and element objects (C order after `BUILD`).
    ObjectArray(Vec<usize>, Vec<usize>),
}

#[derive(Debug, Clone, Copy)]
enum Slot {
    Mark,
    Object(usize),
}

struct Machine<'a> {
    data: &'a [u8],
    position: usize,
    opcode_at: usize,
    source_name: &'a str,
    limits: PickleLimits,
    arena: Vec<Node>,
    stack: Vec<Slot>,
    memo: HashMap<u32, usize>,
}

/// Reads one pickle from `data` (which may continue after the `STOP` opcode) and returns the
/// value and the number of bytes used. `source_name` names the file in errors.
pub fn read_pickle(data: &[u8], source_name: &str) -> Result<(Value, usize)> {
    read_pickle_with_limits(data, source_name, PickleLimits::default())
}

/// [`read_pickle`] with explicit limits.
pub fn read_pickle_with_limits(
    data: &[u8],
    source_name: &str,
    limits: PickleLimits,
) -> Result<(Value, usize)> {
    let mut machine = Machine {
        data,
        position: 0,
        opcode_at: 0,
        source_name,
        limits,
        arena: Vec::new(),
        stack: Vec::new(),
        memo: HashMap::new(),
    };
    let root = machine.run()?;
    let mut budget = Budget { objects: limits.max_objects, bytes: limits.result_limit(data.len()) };
    let value = machine.materialise(root, 0, &mut budget)?;
    Ok((value, machine.position))
}

impl Machine<'_> {
    fn error(&self, message: impl Into<String>) -> ImportError {
        ImportError::Pickle {
            source_name: self.source_name.into(),
            offset: self.opcode_at,
            message: message.into(),
        }
    }

    fn take(&mut self, count: usize) -> Result<&[u8]> {
        let end = self.position.checked_add(count).filter(|&e| e <= self.data.len());
        let Some(end) = end else {
            return Err(self.error(format!(
                "needs {count} more bytes but the data ends (the file is truncated)"
            )));
        };
        let bytes = &self.data[self.position..end];
        self.position = end;
        Ok(bytes)
    }

    fn byte(&mut self) -> Result<u8> {
        Ok(self.take(1)?[0])
    }

    fn u16(&mut self) -> Result<u16> {
        let b = self.take(2)?;
        Ok(u16::from_le_bytes([b[0], b[1]]))
    }

    fn u32(&mut self) -> Result<u32> {
        let b = self.take(4)?;
        Ok(u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
    }

    fn u64(&mut self) -> Result<u64> {
        let b = self.take(8)?;
        Ok(u64::from_le_bytes(b.try_into().expect("eight bytes")))
    }

    fn length(&mut self, value: u64) -> Result<usize> {
        usize::try_from(value).map_err(|_| self.error("a length beyond memory"))
    }

    fn line(&mut self) -> Result<String> {
        let rest = &self.data[self.position..];
        let end = rest
            .iter()
            .position(|&b| b == b'\n')
            .ok_or_else(|| self.error("a text argument without its newline (truncated)"))?;
        let text = String::from_utf8_lossy(&rest[..end]).into_owned();
        self.position += end + 1;
        Ok(text)
    }

    fn new_node(&mut self, node: Node) -> Result<usize> {
        if self.arena.len() >= self.limits.max_objects {
            return Err(self.error(format!(
                "more than {} objects (the reader's limit)",
                self.limits.max_objects
            )));
        }
        self.arena.push(node);
        Ok(self.arena.len() - 1)
    }

    fn push(&mut self, node: Node) -> Result<()> {
        let index = self.new_node(node)?;
        self.stack.push(Slot::Object(index));
        Ok(())
    }

    fn pop(&mut self) -> Result<usize> {
        match self.stack.pop() {
            Some(Slot::Object(index)) => Ok(index),
            Some(Slot::Mark) => Err(self.error("an object expected on the stack, found a mark")),
            None => Err(self.error("an object expected on the stack, found it empty")),
        }
    }

    fn top(&self) -> Result<usize> {
        match self.stack.last() {
            Some(Slot::Object(index)) => Ok(*index),
            _ => Err(self.error("an object expected on top of the stack")),
        }
    }

    /// Pops everything down to the last mark (and the mark).
    fn pop_mark(&mut self) -> Result<Vec<usize>> {
        let mark = self
            .stack
            .iter()
            .rposition(|s| matches!(s, Slot::Mark))
            .ok_or_else(|| self.error("a mark expected on the stack"))?;
        let items = self.stack[mark + 1..]
            .iter()
            .map(|s| match s {
                Slot::Object(i) => *i,
                Slot::Mark => unreachable!("the last mark is at `mark`"),
            })
            .collect();
        self.stack.truncate(mark);
        Ok(items)
    }

    fn memo_get(&self, key: u32) -> Result<usize> {
        self.memo.get(&key).copied().ok_or_else(|| self.error(format!("memo key {key} is unset")))
    }

    fn memo_put(&mut self, key: u32) -> Result<()> {
        let top = self.top()?;
        self.memo.insert(key, top);
        Ok(())
    }

    fn text(&self, index: usize) -> Option<String> {
        match &self.arena[index] {
            Node::Value(Value::Str(s)) => Some(s.clone()),
            Node::Value(Value::Bytes(b)) => Some(b.iter().map(|&c| char::from(c)).collect()),
            _ => None,
        }
    }

    fn describe(&self, index: usize) -> String {
        match &self.arena[index] {
            Node::Value(v) => v.type_name(),
            Node::List(_) => "a list".into(),
            Node::Tuple(_) => "a tuple".into(),
            Node::Dict(_) => "a dict".into(),
            Node::Set(_) => "a set".into(),
            Node::Global(g) => format!("the callable {g:?}"),
            Node::DType(d) => format!("the dtype {}", d.type_string()),
            Node::EmptyArray | Node::ObjectArray(..) => "an array".into(),
        }
    }

    fn run(&mut self) -> Result<usize> {
        loop {
            self.opcode_at = self.position;
            let opcode = self.byte()?;
            match opcode {
                // PROTO: protocols 2-5 (numpy writes 3 and 4, Python's default is 4 or 5).
                0x80 => {
                    let protocol = self.byte()?;
                    if !(2..=5).contains(&protocol) {
                        return Err(self.error(format!(
                            "protocol {protocol} (this reader knows protocols 2 to 5)"
                        )));
                    }
                }
                // FRAME: a length hint only.
                0x95 => {
                    self.u64()?;
                }
                b'.' => return self.pop(),
                b'(' => self.stack.push(Slot::Mark),
                b'0' => {
                    self.stack.pop().ok_or_else(|| self.error("POP on an empty stack"))?;
                }
                b'1' => {
                    self.pop_mark()?;
                }
                b'2' => {
                    let top = self.top()?;
                    self.stack.push(Slot::Object(top));
                }
                b'N' => self.push(Node::Value(Value::None))?,
                0x88 => self.push(Node::Value(Value::Bool(true)))?,
                0x89 => self.push(Node::Value(Value::Bool(false)))?,
                b'J' => {
                    let b = self.take(4)?;
                    let v = i32::from_le_bytes([b[0], b[1], b[2], b[3]]);
                    self.push(Node::Value(Value::Int(i64::from(v))))?;
                }
                b'K' => {
                    let v = self.byte()?;
                    self.push(Node::Value(Value::Int(i64::from(v))))?;
                }
                b'M' => {
                    let v = self.u16()?;
                    self.push(Node::Value(Value::Int(i64::from(v))))?;
                }
                // LONG1 / LONG4: little-endian two's complement of any length; up to 8 bytes.
                0x8a | 0x8b => {
                    let count = if opcode == 0x8a {
                        u64::from(self.byte()?)
                    } else {
                        u64::from(self.u32()?)
                    };
                    let count = self.length(count)?;
                    let bytes = self.take(count)?.to_vec();
                    if bytes.len() > 8 {
                        return Err(
                            self.error(format!("an integer of {} bytes (at most 8)", bytes.len()))
                        );
                    }
                    let mut word = [0u8; 8];
                    word[..bytes.len()].copy_from_slice(&bytes);
                    let mut value = i64::from_le_bytes(word);
                    let negative = bytes.last().is_some_and(|last| last & 0x80 != 0);
                    if negative && bytes.len() < 8 {
                        value -= 1i64 << (8 * bytes.len());
                    }
                    self.push(Node::Value(Value::Int(value)))?;
                }
                b'G' => {
                    let b = self.take(8)?;
                    let v = f64::from_be_bytes(b.try_into().expect("eight bytes"));
                    self.push(Node::Value(Value::Float(v)))?;
                }
                // Text INT / FLOAT / LONG of protocol 0 (also written for bools by protocol 0).
                b'I' | b'L' | b'F' => {
                    let line = self.line()?;
                    let text = line.trim_end_matches('L');
                    let value = match (opcode, text) {
                        (b'I', "01") => Value::Bool(true),
                        (b'I', "00") => Value::Bool(false),
                        (b'F', t) => {
                            Value::Float(t.parse().map_err(|_| self.error(format!("float `{t}`")))?)
                        }
                        (_, t) => {
                            Value::Int(t.parse().map_err(|_| self.error(format!("integer `{t}`")))?)
                        }
                    };
                    self.push(Node::Value(value))?;
                }
                // BINUNICODE, SHORT_BINUNICODE, BINUNICODE8.
                b'X' | 0x8c | 0x8d => {
                    let count = match opcode {
                        b'X' => u64::from(self.u32()?),
                        0x8c => u64::from(self.byte()?),
                        _ => self.u64()?,
                    };
                    let count = self.length(count)?;
                    let bytes = self.take(count)?.to_vec();
                    let text = String::from_utf8(bytes)
                        .map_err(|_| self.error("text that is not UTF-8"))?;
                    self.push(Node::Value(Value::Str(text)))?;
                }
                // BINBYTES, SHORT_BINBYTES, BINBYTES8, BYTEARRAY8, and Python 2's BINSTRING and
                // SHORT_BINSTRING (bytes; numpy reads them with encoding='latin1').
                b'B' | b'C' | 0x8e | 0x96 | b'T' | b'U' => {
                    let count = match opcode {
                        b'B' | b'T' => u64::from(self.u32()?),
                        b'C' | b'U' => u64::from(self.byte()?),
                        _ => self.u64()?,
                    };
                    let count = self.length(count)?;
                    let bytes = self.take(count)?.to_vec();
                    self.push(Node::Value(Value::Bytes(bytes)))?;
                }
                b']' => self.push(Node::List(Vec::new()))?,
                b')' => self.push(Node::Tuple(Vec::new()))?,
                b'}' => self.push(Node::Dict(Vec::new()))?,
                0x8f => self.push(Node::Set(Vec::new()))?,
                b'l' => {
                    let items = self.pop_mark()?;
                    self.push(Node::List(items))?;
                }
                b't' => {
                    let items = self.pop_mark()?;
                    self.push(Node::Tuple(items))?;
                }
                0x85..=0x87 => {
                    let count = usize::from(opcode - 0x84);
                    let mut items = Vec::with_capacity(count);
                    for _ in 0..count {
                        items.push(self.pop()?);
                    }
                    items.reverse();
                    self.push(Node::Tuple(items))?;
                }
                b'd' => {
                    let items = self.pop_mark()?;
                    if items.len() % 2 != 0 {
                        return Err(self.error("DICT with an odd number of items"));
                    }
                    let pairs = items.chunks_exact(2).map(|p| (p[0], p[1])).collect();
                    self.push(Node::Dict(pairs))?;
                }
                0x91 => {
                    let items = self.pop_mark()?;
                    self.push(Node::Set(items))?;
                }
                b'a' => {
                    let item = self.pop()?;
                    let list = self.top()?;
                    self.append(list, vec![item])?;
                }
                b'e' => {
                    let items = self.pop_mark()?;
                    let list = self.top()?;
                    self.append(list, items)?;
                }
                0x90 => {
                    let items = self.pop_mark()?;
                    let set = self.top()?;
                    match &mut self.arena[set] {
                        Node::Set(v) => v.extend(items),
                        _ => return Err(self.error("ADDITEMS on something that is not a set")),
                    }
                }
                b's' => {
                    let value = self.pop()?;
                    let key = self.pop()?;
                    let dict = self.top()?;
                    self.set_items(dict, vec![key, value])?;
                }
                b'u' => {
                    let items = self.pop_mark()?;
                    if items.len() % 2 != 0 {
                        return Err(self.error("SETITEMS with an odd number of items"));
                    }
                    let dict = self.top()?;
                    self.set_items(dict, items)?;
                }
                b'q' => {
                    let key = u32::from(self.byte()?);
                    self.memo_put(key)?;
                }
                b'r' => {
                    let key = self.u32()?;
                    self.memo_put(key)?;
                }
                0x94 => {
                    let key =
                        u32::try_from(self.memo.len()).map_err(|_| self.error("memo overflow"))?;
                    self.memo_put(key)?;
                }
                b'p' => {
                    let line = self.line()?;
                    let key = line.parse().map_err(|_| self.error(format!("memo key `{line}`")))?;
                    self.memo_put(key)?;
                }
                b'h' => {
                    let key = u32::from(self.byte()?);
                    let index = self.memo_get(key)?;
                    self.stack.push(Slot::Object(index));
                }
                b'j' => {
                    let key = self.u32()?;
                    let index = self.memo_get(key)?;
                    self.stack.push(Slot::Object(index));
                }
                b'g' => {
                    let line = self.line()?;
                    let key = line.parse().map_err(|_| self.error(format!("memo key `{line}`")))?;
                    let index = self.memo_get(key)?;
                    self.stack.push(Slot::Object(index));
                }
                b'c' => {
                    let module = self.line()?;
                    let name = self.line()?;
                    self.push_global(&module, &name)?;
                }
                0x93 => {
                    let name = self.pop()?;
                    let module = self.pop()?;
                    let (Some(module), Some(name)) = (self.text(module), self.text(name)) else {
                        return Err(self.error("STACK_GLOBAL without text module and name"));
                    };
                    self.push_global(&module, &name)?;
                }
                b'R' => {
                    let arguments = self.pop()?;
                    let callable = self.pop()?;
                    let node = self.reduce(callable, arguments)?;
                    self.push(node)?;
                }
                b'b' => {
                    let state = self.pop()?;
                    let target = self.top()?;
                    self.build(target, state)?;
                }
                0x81 | 0x92 | b'i' | b'o' => {
                    return Err(self.error(
                        "an instance of a Python class (NEWOBJ/INST/OBJ): only numpy arrays and \
                         plain containers are read",
                    ));
                }
                b'P' | b'Q' => return Err(self.error("a persistent id (refused)")),
                0x82..=0x84 => return Err(self.error("an extension-registry code (refused)")),
                0x97 | 0x98 => {
                    return Err(self.error("an out-of-band buffer (refused: not in the file)"));
                }
                other => {
                    return Err(self.error(format!("unknown or unsupported opcode 0x{other:02x}")));
                }
            }
        }
    }

    fn push_global(&mut self, module: &str, name: &str) -> Result<()> {
        let global = Global::find(module, name).ok_or_else(|| {
            self.error(format!(
                "refused global `{module}.{name}`: only numpy's array, dtype and scalar \
                 reconstruction are allowed (the reader never runs code)"
            ))
        })?;
        self.push(Node::Global(global))
    }

    fn append(&mut self, list: usize, items: Vec<usize>) -> Result<()> {
        match &mut self.arena[list] {
            Node::List(v) => {
                v.extend(items);
                Ok(())
            }
            _ => Err(self.error(format!("APPEND to {}", self.describe(list)))),
        }
    }

    fn set_items(&mut self, dict: usize, items: Vec<usize>) -> Result<()> {
        match &mut self.arena[dict] {
            Node::Dict(v) => {
                v.extend(items.chunks_exact(2).map(|p| (p[0], p[1])));
                Ok(())
            }
            _ => Err(self.error(format!("SETITEM on {}", self.describe(dict)))),
        }
    }

    fn tuple(&self, index: usize, what: &str) -> Result<Vec<usize>> {
        match &self.arena[index] {
            Node::Tuple(items) => Ok(items.clone()),
            _ => Err(self.error(format!("{what}: expected a tuple, got {}", self.describe(index)))),
        }
    }

    fn int(&self, index: usize, what: &str) -> Result<i64> {
        match &self.arena[index] {
            Node::Value(Value::Int(v)) => Ok(*v),
            Node::Value(Value::Bool(b)) => Ok(i64::from(*b)),
            _ => Err(self.error(format!("{what}: expected an int, got {}", self.describe(index)))),
        }
    }

    fn shape(&self, index: usize) -> Result<Vec<usize>> {
        self.tuple(index, "array shape")?
            .into_iter()
            .map(|d| {
                let d = self.int(d, "array dimension")?;
                usize::try_from(d).map_err(|_| self.error(format!("a negative dimension {d}")))
            })
            .collect()
    }

    fn dtype(&self, index: usize) -> Result<DType> {
        match &self.arena[index] {
            Node::DType(d) => Ok(*d),
            _ => Err(self.error(format!("expected a numpy dtype, got {}", self.describe(index)))),
        }
    }

    fn bytes(&self, index: usize) -> Result<&[u8]> {
        match &self.arena[index] {
            Node::Value(Value::Bytes(b)) => Ok(b),
            _ => Err(self.error(format!("expected bytes, got {}", self.describe(index)))),
        }
    }

    fn reduce(&mut self, callable: usize, arguments: usize) -> Result<Node> {
        let Node::Global(global) = self.arena[callable] else {
            return Err(self.error(format!(
                "REDUCE calls {}: only the allowed numpy callables may be called",
                self.describe(callable)
            )));
        };
        let args = self.tuple(arguments, "REDUCE arguments")?;
        match (global, args.as_slice()) {
            (Global::Reconstruct, [class, _shape, _kind]) => {
                if !matches!(self.arena[*class], Node::Global(Global::NdarrayClass)) {
                    return Err(self.error(format!(
                        "_reconstruct of {} (only numpy.ndarray)",
                        self.describe(*class)
                    )));
                }
                Ok(Node::EmptyArray)
            }
            (Global::DTypeClass, [type_string, ..]) => {
                let text = self
                    .text(*type_string)
                    .ok_or_else(|| self.error("numpy.dtype without a type string"))?;
                let dtype = DType::parse(&text, self.source_name)?;
                Ok(Node::DType(dtype))
            }
            (Global::Scalar, [dtype, data]) => {
                let dtype = self.dtype(*dtype)?;
                let raw = self.bytes(*data)?;
                let data = decode_raw(dtype, raw, 1, self.source_name)?;
                Ok(Node::Value(Value::Array(NdArray { shape: vec![], data })))
            }
            (Global::FromBuffer, [buffer, dtype, shape, order]) => {
                let dtype = self.dtype(*dtype)?;
                let shape = self.shape(*shape)?;
                let fortran = self.text(*order).as_deref() == Some("F");
                let count = element_count(&shape, self.source_name)?;
                let data = decode_raw(dtype, self.bytes(*buffer)?, count, self.source_name)?;
                Ok(Node::Value(Value::Array(NdArray::new(shape, data, fortran, self.source_name)?)))
            }
            (Global::CodecsEncode, [text, encoding]) => {
                let encoding = self.text(*encoding).unwrap_or_default();
                if !matches!(encoding.as_str(), "latin1" | "latin-1" | "iso-8859-1") {
                    return Err(self.error(format!("_codecs.encode with encoding `{encoding}`")));
                }
                let text =
                    self.text(*text).ok_or_else(|| self.error("_codecs.encode of non-text"))?;
                let bytes = text
                    .chars()
                    .map(|c| {
                        u8::try_from(u32::from(c))
                            .map_err(|_| self.error("a non-Latin-1 character"))
                    })
                    .collect::<Result<Vec<u8>>>()?;
                Ok(Node::Value(Value::Bytes(bytes)))
            }
            (global, args) => Err(self.error(format!(
                "{global:?} called with {} arguments, which numpy never writes",
                args.len()
            ))),
        }
    }

    fn build(&mut self, target: usize, state: usize) -> Result<()> {
        let state = self.tuple(state, "BUILD state")?;
        match self.arena[target] {
            // (version, byte order, subarray, names, fields, elsize, alignment, flags[, metadata])
            Node::DType(mut dtype) => {
                if state.len() < 5 {
                    return Err(self.error("a dtype state shorter than numpy writes"));
                }
                let order = self.text(state[1]).unwrap_or_default();
                dtype.big_endian = order == ">";
                for (k, what) in [(2, "subarray"), (3, "field names"), (4, "fields")] {
                    if !matches!(self.arena[state[k]], Node::Value(Value::None)) {
                        return Err(self.error(format!(
                            "a structured dtype (with {what}): only plain element types are read"
                        )));
                    }
                }
                self.arena[target] = Node::DType(dtype);
                Ok(())
            }
            // (version, shape, dtype, is_fortran, raw bytes or list of objects)
            Node::EmptyArray => {
                let [_version, shape, dtype, fortran, data] = state[..] else {
                    return Err(self.error(format!(
                        "an array state of {} items (numpy writes 5)",
                        state.len()
                    )));
                };
                let shape = self.shape(shape)?;
                let dtype = self.dtype(dtype)?;
                let fortran = self.int(fortran, "array order flag")? != 0;
                let count = element_count(&shape, self.source_name)?;
                let node = if dtype.kind == DTypeKind::Object {
                    let Node::List(items) = &self.arena[data] else {
                        return Err(self.error(format!(
                            "object array data: expected a list, got {}",
                            self.describe(data)
                        )));
                    };
                    if items.len() != count {
                        return Err(self.error(format!(
                            "an object array of shape {shape:?} with {} elements",
                            items.len()
                        )));
                    }
                    let mut items = items.clone();
                    if fortran && shape.len() > 1 {
                        // Reorder through a placeholder array of indices.
                        let indices = ArrayData::Int(items.iter().map(|&i| i as i64).collect());
                        let ArrayData::Int(order) =
                            NdArray::new(shape.clone(), indices, true, self.source_name)?.data
                        else {
                            unreachable!("an integer array stays an integer array")
                        };
                        items = order.into_iter().map(|i| i as usize).collect();
                    }
                    Node::ObjectArray(shape, items)
                } else {
                    let raw = self.bytes(data)?;
                    let values = decode_raw(dtype, raw, count, self.source_name)?;
                    Node::Value(Value::Array(NdArray::new(
                        shape,
                        values,
                        fortran,
                        self.source_name,
                    )?))
                };
                self.arena[target] = node;
                Ok(())
            }
            _ => Err(self.error(format!(
                "BUILD on {}: only numpy arrays and dtypes are built",
                self.describe(target)
            ))),
        }
    }

    /// Turns the arena object `index` into a [`Value`], within the depth limit and the budget
    /// of objects and bytes (shared objects are copied, so a pickle of many references to one
    /// big list cannot expand without bound). Each value is charged before it is built.
    fn materialise(&self, index: usize, depth: usize, budget: &mut Budget) -> Result<Value> {
        if depth > self.limits.max_depth {
            return Err(self.error(format!(
                "nesting deeper than {} levels (or a self-referencing container)",
                self.limits.max_depth
            )));
        }
        budget.objects = budget.objects.checked_sub(1).ok_or_else(|| {
            self.error(format!(
                "the result would hold more than {} objects (the reader's limit)",
                self.limits.max_objects
            ))
        })?;
        let charge = match &self.arena[index] {
            Node::Value(v) => result_bytes(v),
            _ => size_of::<Value>(),
        };
        budget.bytes = budget.bytes.checked_sub(charge).ok_or_else(|| {
            let limit = self.limits.result_limit(self.data.len());
            self.error(format!(
                "the result would take more than {} MiB of memory ({} bytes per byte of the \
                 file beyond {} MiB): its shared references expand far beyond what the file \
                 holds",
                limit >> 20,
                self.limits.result_bytes_per_input_byte,
                self.limits.result_floor_bytes >> 20
            ))
        })?;
        let many = |items: &[usize], budget: &mut Budget| -> Result<Vec<Value>> {
            items.iter().map(|&i| self.materialise(i, depth + 1, budget)).collect()
        };
        Ok(match &self.arena[index] {
            Node::Value(v) => v.clone(),
            Node::List(items) => Value::List(many(items, budget)?),
            Node::Tuple(items) => Value::Tuple(many(items, budget)?),
            Node::Set(items) => Value::Set(many(items, budget)?),
            Node::Dict(pairs) => Value::Dict(
                pairs
                    .iter()
                    .map(|&(k, v)| {
                        Ok((
                            self.materialise(k, depth + 1, budget)?,
                            self.materialise(v, depth + 1, budget)?,
                        ))
                    })
                    .collect::<Result<_>>()?,
            ),
            Node::ObjectArray(shape, items) => Value::Array(NdArray {
                shape: shape.clone(),
                data: ArrayData::Object(many(items, budget)?),
            }),
            Node::Global(_) | Node::DType(_) | Node::EmptyArray => {
                return Err(self
                    .error(format!("the result holds {} rather than data", self.describe(index))));
            }
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn read(bytes: &[u8]) -> Result<Value> {
        read_pickle(bytes, "test.pkl").map(|(v, _)| v)
    }

    #[test]
    fn plain_containers() {
        // pickle.dumps({'a': [1, 2.5, None, True], 'b': (b'xy', 'z')}, protocol=2)
        let bytes = b"\x80\x02}q\x00(X\x01\x00\x00\x00aq\x01]q\x02(K\x01G@\x04\x00\x00\x00\x00\x00\x00N\x88eX\x01\x00\x00\x00bq\x03c_codecs\nencode\nq\x04X\x02\x00\x00\x00xyq\x05X\x06\x00\x00\x00latin1q\x06\x86q\x07Rq\x08X\x01\x00\x00\x00zq\t\x86q\nu.";
        let value = read(bytes).unwrap();
        let expected = Value::Dict(vec![
            (
                Value::Str("a".into()),
                Value::List(vec![Value::Int(1), Value::Float(2.5), Value::None, Value::Bool(true)]),
            ),
            (
                Value::Str("b".into()),
                Value::Tuple(vec![Value::Bytes(b"xy".to_vec()), Value::Str("z".into())]),
            ),
        ]);
        assert_eq!(value, expected);
    }

    #[test]
    fn memo_shares_mutated_objects() {
        // l = [7]; pickle.dumps([l, l], protocol=4): the inner list is memoised empty, then
        // appended to, then read back from the memo, which must see the append.
        let bytes = b"\x80\x04\x95\x0c\x00\x00\x00\x00\x00\x00\x00]\x94(]\x94K\x07ah\x01e.";
        let value = read(bytes).unwrap();
        let inner = Value::List(vec![Value::Int(7)]);
        assert_eq!(value, Value::List(vec![inner.clone(), inner]));
    }

    #[test]
    fn long_integers_are_signed() {
        // LONG1 of -1 (one byte 0xff) and of 2^40.
        let bytes = b"\x80\x02\x8a\x01\xff\x8a\x06\x00\x00\x00\x00\x00\x01\x86.";
        assert_eq!(read(bytes).unwrap(), Value::Tuple(vec![Value::Int(-1), Value::Int(1 << 40)]));
    }

    #[test]
    fn unknown_globals_and_calls_are_refused() {
        // pickle.dumps(os.system) style: GLOBAL posix system, then REDUCE with ('ls',).
        let bytes = b"\x80\x02cposix\nsystem\nX\x02\x00\x00\x00ls\x85R.";
        let message = read(bytes).unwrap_err().to_string();
        assert!(message.contains("test.pkl"), "{message}");
        assert!(message.contains("refused global `posix.system`"), "{message}");
        // Instances of classes are refused too.
        let newobj = b"\x80\x02cnumpy\nndarray\n)\x81.";
        assert!(read(newobj).unwrap_err().to_string().contains("instance"));
    }

    #[test]
    fn truncated_and_malformed_programs_fail_cleanly() {
        let bytes = b"\x80\x04]\x94(K\x01K\x02e.";
        for end in 0..bytes.len() - 1 {
            let error = read(&bytes[..end]).unwrap_err().to_string();
            assert!(error.contains("test.pkl"), "{error}");
        }
        assert!(read(b"\x80\x02a.").is_err());
        assert!(read(b"\x80\x09N.").unwrap_err().to_string().contains("protocol 9"));
    }

    #[test]
    fn limits_hold() {
        // A list nested 200 deep.
        let mut bytes = b"\x80\x02".to_vec();
        for _ in 0..200 {
            bytes.extend(b"(");
        }
        bytes.extend(b"]");
        for _ in 0..200 {
            bytes.extend(b"l");
        }
        bytes.extend(b".");
        assert!(read(&bytes).unwrap_err().to_string().contains("nesting"));
        let small = PickleLimits { max_objects: 3, max_depth: 10, ..PickleLimits::default() };
        let many = b"\x80\x02(K\x01K\x02K\x03K\x04l.";
        assert!(read_pickle_with_limits(many, "t", small).is_err());
        // Self-reference: a list appended to itself.
        let cycle = b"\x80\x02]q\x00h\x00a.";
        assert!(read(cycle).is_err());
    }

    /// A list holding the same list twice, nested `levels` deep: `9 * levels + 5` bytes that
    /// stand for `2^levels` empty lists.
    fn doubling(levels: usize) -> Vec<u8> {
        // An empty list, memoised as 0.
        let mut bytes = b"\x80\x02]q\x00".to_vec();
        for _ in 0..levels {
            // POP it, MARK, memo 0 twice, LIST of the two, memoised as 0 in its place.
            bytes.extend(b"0(h\x00h\x00lq\x00");
        }
        bytes.extend(b".");
        bytes
    }

    #[test]
    fn shared_references_cannot_expand_beyond_the_budget() {
        // 2^10 copies fit any budget; 2^40 would take terabytes and are refused, quickly.
        assert!(read(&doubling(10)).is_ok());
        let started = std::time::Instant::now();
        let error = read(&doubling(40)).unwrap_err().to_string();
        assert!(error.contains("MiB of memory") && error.contains("test.pkl"), "{error}");
        assert!(started.elapsed().as_secs() < 10, "refused after {:?}", started.elapsed());
        // The budget grows with the file: a result of 2^17 values (about 4 MiB) is refused with
        // no floor and 8 bytes per input byte, accepted with the default limits.
        let tight = PickleLimits {
            result_bytes_per_input_byte: 8,
            result_floor_bytes: 0,
            ..PickleLimits::default()
        };
        assert!(read_pickle_with_limits(&doubling(17), "t", tight).is_err());
        assert!(read(&doubling(17)).is_ok());
    }

    /// `../shared/bad-inputs/pickle-bomb-123b.pkl`, the input the pickle fuzzer stopped at:
    /// nested `MARK`, `LIST` and `DUP` inside two dicts.
    const BOMB: &[u8] = include_bytes!("../tests/fixtures/pickle-bomb-123b.pkl");

    #[test]
    fn the_fuzzers_pickle_bomb_is_refused_quickly() {
        let started = std::time::Instant::now();
        let error = read(BOMB).unwrap_err().to_string();
        assert!(error.contains("MiB of memory"), "{error}");
        assert!(started.elapsed().as_secs() < 10, "refused after {:?}", started.elapsed());
    }
}
