//! The part of Python's pickle format that a dictionary of numpy arrays uses (protocol 2 and
//! 3, as `pickle.dump` of nested dicts of `np.ndarray` writes it), read without Python: a
//! small stack machine that builds [`Value`]s and turns numpy's reconstruction calls into
//! arrays. Anything else is refused by opcode.

use std::collections::BTreeMap;

/// What a pickle held.
#[derive(Debug, Clone, PartialEq)]
pub enum Value {
    None,
    Bool(bool),
    Int(i64),
    Str(String),
    Bytes(Vec<u8>),
    Tuple(Vec<Value>),
    Dict(BTreeMap<String, Value>),
    /// A little-endian float32 numpy array in C order.
    Array {
        shape: Vec<usize>,
        data: Vec<f32>,
    },
    /// A global (`module name`) not yet applied.
    Global(String),
    /// `numpy.dtype(...)` applied: its type string (`f4`).
    Dtype(String),
    /// `numpy.core.multiarray._reconstruct(ndarray, ...)`: an array awaiting its state.
    EmptyArray,
}

/// Reads a pickle of nested dictionaries of float32 arrays.
pub fn load(data: &[u8]) -> Result<Value, String> {
    let mut machine = Machine {
        data,
        at: 0,
        stack: Vec::new(),
        marks: Vec::new(),
        memo: BTreeMap::new(),
    };
    machine.run()
}

struct Machine<'a> {
    data: &'a [u8],
    at: usize,
    stack: Vec<Value>,
    marks: Vec<usize>,
    memo: BTreeMap<u32, Value>,
}

impl Machine<'_> {
    fn take(&mut self, n: usize) -> Result<&[u8], String> {
        let end = self.at.checked_add(n).filter(|&end| end <= self.data.len());
        let end =
            end.ok_or_else(|| format!("the pickle ends inside an argument at {}", self.at))?;
        let bytes = &self.data[self.at..end];
        self.at = end;
        Ok(bytes)
    }

    fn u32_le(&mut self) -> Result<u32, String> {
        Ok(u32::from_le_bytes(
            self.take(4)?.try_into().expect("4 bytes"),
        ))
    }

    fn line(&mut self) -> Result<String, String> {
        let rest = &self.data[self.at..];
        let end = rest
            .iter()
            .position(|&b| b == b'\n')
            .ok_or("an unterminated line")?;
        let text = String::from_utf8_lossy(&rest[..end]).into_owned();
        self.at += end + 1;
        Ok(text)
    }

    fn pop(&mut self) -> Result<Value, String> {
        self.stack
            .pop()
            .ok_or_else(|| "the pickle's stack ran empty".to_string())
    }

    fn pop_mark(&mut self) -> Result<Vec<Value>, String> {
        let mark = self.marks.pop().ok_or("a MARK is missing")?;
        if mark > self.stack.len() {
            return Err("a MARK above the stack".into());
        }
        Ok(self.stack.split_off(mark))
    }

    fn top_dict(&mut self) -> Result<&mut BTreeMap<String, Value>, String> {
        match self.stack.last_mut() {
            Some(Value::Dict(dict)) => Ok(dict),
            _ => Err("items set on something that is not a dict".into()),
        }
    }

    fn run(&mut self) -> Result<Value, String> {
        loop {
            let opcode = self.take(1)?[0];
            match opcode {
                0x80 => {
                    self.take(1)?; // PROTO n
                }
                b'}' => self.stack.push(Value::Dict(BTreeMap::new())),
                b'(' => self.marks.push(self.stack.len()),
                b'q' => {
                    let key = u32::from(self.take(1)?[0]);
                    self.memoize(key)?;
                }
                b'r' => {
                    let key = self.u32_le()?;
                    self.memoize(key)?;
                }
                b'h' => {
                    let key = u32::from(self.take(1)?[0]);
                    self.recall(key)?;
                }
                b'j' => {
                    let key = self.u32_le()?;
                    self.recall(key)?;
                }
                b'X' => {
                    let n = self.u32_le()? as usize;
                    let text =
                        String::from_utf8(self.take(n)?.to_vec()).map_err(|e| e.to_string())?;
                    self.stack.push(Value::Str(text));
                }
                b'C' => {
                    let n = usize::from(self.take(1)?[0]);
                    let bytes = self.take(n)?.to_vec();
                    self.stack.push(Value::Bytes(bytes));
                }
                b'B' => {
                    let n = self.u32_le()? as usize;
                    let bytes = self.take(n)?.to_vec();
                    self.stack.push(Value::Bytes(bytes));
                }
                b'K' => {
                    let v = self.take(1)?[0];
                    self.stack.push(Value::Int(i64::from(v)));
                }
                b'M' => {
                    let v = u16::from_le_bytes(self.take(2)?.try_into().expect("2 bytes"));
                    self.stack.push(Value::Int(i64::from(v)));
                }
                b'J' => {
                    let v = i32::from_le_bytes(self.take(4)?.try_into().expect("4 bytes"));
                    self.stack.push(Value::Int(i64::from(v)));
                }
                b'N' => self.stack.push(Value::None),
                0x88 => self.stack.push(Value::Bool(true)),
                0x89 => self.stack.push(Value::Bool(false)),
                b')' => self.stack.push(Value::Tuple(Vec::new())),
                b't' => {
                    let items = self.pop_mark()?;
                    self.stack.push(Value::Tuple(items));
                }
                0x85..=0x87 => {
                    let n = usize::from(opcode - 0x84);
                    if self.stack.len() < n {
                        return Err("a tuple of more items than the stack holds".into());
                    }
                    let items = self.stack.split_off(self.stack.len() - n);
                    self.stack.push(Value::Tuple(items));
                }
                b'c' => {
                    let module = self.line()?;
                    let name = self.line()?;
                    self.stack.push(Value::Global(format!("{module} {name}")));
                }
                b'R' => {
                    let args = self.pop()?;
                    let callable = self.pop()?;
                    let value = reduce(callable, args)?;
                    self.stack.push(value);
                }
                b'b' => {
                    let state = self.pop()?;
                    let object = self.pop()?;
                    self.stack.push(build(object, state)?);
                }
                b's' => {
                    let value = self.pop()?;
                    let key = self.pop()?;
                    let Value::Str(key) = key else {
                        return Err("a dict key that is not a string".into());
                    };
                    self.top_dict()?.insert(key, value);
                }
                b'u' => {
                    let items = self.pop_mark()?;
                    if items.len() % 2 != 0 {
                        return Err("SETITEMS with an odd count".into());
                    }
                    let mut pairs = Vec::new();
                    let mut items = items.into_iter();
                    while let (Some(key), Some(value)) = (items.next(), items.next()) {
                        let Value::Str(key) = key else {
                            return Err("a dict key that is not a string".into());
                        };
                        pairs.push((key, value));
                    }
                    self.top_dict()?.extend(pairs);
                }
                b'.' => return self.pop(),
                other => {
                    return Err(format!(
                        "unsupported pickle opcode 0x{other:02x} at {}",
                        self.at - 1
                    ));
                }
            }
        }
    }

    fn memoize(&mut self, key: u32) -> Result<(), String> {
        let top = self.stack.last().ok_or("a memo of an empty stack")?.clone();
        self.memo.insert(key, top);
        Ok(())
    }

    fn recall(&mut self, key: u32) -> Result<(), String> {
        let value = self
            .memo
            .get(&key)
            .ok_or_else(|| format!("memo {key} is unset"))?;
        self.stack.push(value.clone());
        Ok(())
    }
}

/// A call: only numpy's array and dtype reconstruction.
fn reduce(callable: Value, args: Value) -> Result<Value, String> {
    let Value::Global(name) = callable else {
        return Err("a call of something that is not a global".into());
    };
    let Value::Tuple(args) = args else {
        return Err(format!("{name} called without an argument tuple"));
    };
    match name.as_str() {
        "numpy.core.multiarray _reconstruct" | "numpy._core.multiarray _reconstruct" => {
            Ok(Value::EmptyArray)
        }
        "numpy dtype" => match args.first() {
            Some(Value::Str(kind)) => Ok(Value::Dtype(kind.clone())),
            _ => Err("numpy.dtype without a type string".into()),
        },
        other => Err(format!(
            "the pickle calls {other}, which a weights file has no need of"
        )),
    }
}

/// `__setstate__`: a dtype's state is checked for little-endian order, an array's gives its
/// shape, dtype and bytes.
fn build(object: Value, state: Value) -> Result<Value, String> {
    let Value::Tuple(state) = state else {
        return Err("a state that is not a tuple".into());
    };
    match object {
        Value::Dtype(kind) => match state.get(1) {
            Some(Value::Str(order)) if order == "<" || order == "|" => Ok(Value::Dtype(kind)),
            _ => Err(format!("dtype {kind} is not little-endian")),
        },
        Value::EmptyArray => {
            // (version, shape, dtype, is_fortran, raw bytes)
            let [
                _,
                Value::Tuple(shape),
                Value::Dtype(kind),
                Value::Bool(fortran),
                Value::Bytes(raw),
            ] = &state[..]
            else {
                return Err(
                    "an array state other than numpy's (version, shape, dtype, order, bytes)"
                        .into(),
                );
            };
            if kind != "f4" || *fortran {
                return Err(format!(
                    "an array of {kind} (fortran order {fortran}); only C-order f4 is read"
                ));
            }
            let shape = shape
                .iter()
                .map(|d| match d {
                    Value::Int(n) if *n >= 0 => Ok(*n as usize),
                    _ => Err("a bad array dimension".to_string()),
                })
                .collect::<Result<Vec<usize>, String>>()?;
            let count: usize = shape.iter().product();
            if raw.len() != count * 4 {
                return Err(format!(
                    "an array of shape {shape:?} with {} bytes",
                    raw.len()
                ));
            }
            let data = raw
                .chunks_exact(4)
                .map(|b| f32::from_le_bytes(b.try_into().expect("4 bytes")))
                .collect();
            Ok(Value::Array { shape, data })
        }
        _ => Err("a state set on something other than an array or a dtype".into()),
    }
}
