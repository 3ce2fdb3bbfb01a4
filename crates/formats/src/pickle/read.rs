//! A data-only interpreter for Python pickles (protocols 0 to 5), enough for `torch.save`
//! checkpoints and whatever config objects they carry.
//!
//! Nothing in the stream is imported or called. Classes and functions (GLOBAL, STACK_GLOBAL,
//! INST) are recorded by name; calling them (REDUCE, NEWOBJ, NEWOBJ_EX, OBJ, INST) records an
//! [`Object`] holding the callable and its arguments; BUILD records the state on it; SETITEM(S),
//! APPEND(S) and ADDITEMS on such an object store the items on it, so a dict subclass, an
//! `OrderedDict` or a list subclass stays walkable without knowing its class.
//!
//! Values live in an arena and the stack and memo hold indices into it. This gives Python's
//! reference semantics, which matter: the pickler memoizes a dict before filling it, so a later
//! GET must see the items added after the PUT (shared sub-configs, tied weights, cycles).
//!
//! Every read is bounds-checked and every growth is capped ([`Limits`]), so a truncated or
//! hostile stream ends in a [`PickleError`], never a panic or an unbounded allocation. Nothing
//! here recurses over the value tree; consumers that walk it must bound their own depth (the
//! tree may contain cycles).

use std::collections::HashMap;
use std::fmt;

/// Index of a value in [`Pickle`]'s arena.
pub type Id = usize;

/// One unpickled value.
#[derive(Debug, Clone, PartialEq)]
pub enum Value {
    None,
    Bool(bool),
    Int(i64),
    /// An integer outside `i64`, in decimal (only for display; nothing needs its value).
    BigInt(String),
    Float(f64),
    /// Text. Python 2 byte strings (STRING, BINSTRING, SHORT_BINSTRING) land here too, decoded
    /// as UTF-8 like `torch.load` does; undecodable bytes become U+FFFD.
    Str(String),
    /// `bytes` and `bytearray`.
    Bytes(Vec<u8>),
    List(Vec<Id>),
    Tuple(Vec<Id>),
    /// Entries in insertion order. A repeated key is kept twice; readers give the later one
    /// precedence, as Python's dict assignment does.
    Dict(Vec<(Id, Id)>),
    Set(Vec<Id>),
    FrozenSet(Vec<Id>),
    /// A class or function named by the stream, never resolved.
    Global(Box<Global>),
    /// The result of calling something from the stream, recorded instead of performed.
    Object(Box<Object>),
    /// PERSID / BINPERSID: a reference to data outside the pickle (torch: a storage).
    PersistentId(Id),
}

#[derive(Debug, Clone, PartialEq)]
pub struct Global {
    pub module: String,
    pub name: String,
}

#[derive(Debug, Clone, PartialEq)]
pub struct Object {
    /// What was called: usually a [`Value::Global`]; for REDUCE possibly another object (a
    /// `functools.partial`, say).
    pub callable: Id,
    /// The positional arguments (a [`Value::Tuple`]).
    pub args: Id,
    /// NEWOBJ_EX keyword arguments (a [`Value::Dict`]).
    pub kwargs: Option<Id>,
    /// The last BUILD state: for plain objects the `__dict__` (a dict), for `__slots__` objects
    /// a `(dict or None, slots dict)` tuple, or anything a `__setstate__` accepts.
    pub state: Option<Id>,
    /// SETITEM(S) on the object: the items of a dict subclass / `OrderedDict`.
    pub items: Vec<(Id, Id)>,
    /// APPEND(S) and ADDITEMS on the object: the items of a list or set subclass.
    pub elems: Vec<Id>,
}

/// A parsed pickle: the arena and the value STOP returned.
#[derive(Debug, Clone)]
pub struct Pickle {
    nodes: Vec<Value>,
    root: Id,
}

impl Pickle {
    pub fn root(&self) -> Id {
        self.root
    }

    /// The value of an id taken from this pickle (ids from elsewhere read as `None`).
    pub fn get(&self, id: Id) -> &Value {
        self.nodes.get(id).unwrap_or(&Value::None)
    }

    /// `(module, name)` if `id` is a global.
    pub fn global(&self, id: Id) -> Option<(&str, &str)> {
        match self.get(id) {
            Value::Global(g) => Some((g.module.as_str(), g.name.as_str())),
            _ => None,
        }
    }

    /// A short, bounded rendering for error messages.
    pub fn describe(&self, id: Id) -> String {
        let mut out = String::new();
        self.describe_into(id, 2, &mut out);
        out
    }

    fn describe_into(&self, id: Id, depth: usize, out: &mut String) {
        use std::fmt::Write;
        const MAX_SHOWN: usize = 4;
        let seq = |p: &Self, out: &mut String, open: &str, close: &str, ids: &[Id]| {
            out.push_str(open);
            if depth == 0 && !ids.is_empty() {
                let _ = write!(out, "{} items", ids.len());
            } else {
                for (i, &c) in ids.iter().take(MAX_SHOWN).enumerate() {
                    if i > 0 {
                        out.push_str(", ");
                    }
                    p.describe_into(c, depth.saturating_sub(1), out);
                }
                if ids.len() > MAX_SHOWN {
                    let _ = write!(out, ", ... ({} items)", ids.len());
                }
            }
            out.push_str(close);
        };
        match self.get(id) {
            Value::None => out.push_str("None"),
            Value::Bool(b) => out.push_str(if *b { "True" } else { "False" }),
            Value::Int(i) => {
                let _ = write!(out, "{i}");
            }
            Value::BigInt(s) => out.push_str(s),
            Value::Float(f) => {
                let _ = write!(out, "{f:?}");
            }
            Value::Str(s) => {
                let short: String = s.chars().take(40).collect();
                let _ = write!(out, "{short:?}");
                if short.len() < s.len() {
                    out.push_str("...");
                }
            }
            Value::Bytes(b) => {
                let _ = write!(out, "<{} bytes>", b.len());
            }
            Value::List(v) => seq(self, out, "[", "]", v),
            Value::Tuple(v) => seq(self, out, "(", ")", v),
            Value::Set(v) => seq(self, out, "set(", ")", v),
            Value::FrozenSet(v) => seq(self, out, "frozenset(", ")", v),
            Value::Dict(e) => {
                let _ = write!(out, "<dict of {} items>", e.len());
            }
            Value::Global(g) => {
                let _ = write!(out, "{}.{}", g.module, g.name);
            }
            Value::Object(o) => {
                out.push('<');
                match self.global(o.callable) {
                    Some((m, n)) => {
                        let _ = write!(out, "{m}.{n}");
                    }
                    None => out.push_str("object"),
                }
                out.push_str(" object>");
            }
            Value::PersistentId(p) => {
                out.push_str("persistent_id(");
                self.describe_into(*p, depth.saturating_sub(1), out);
                out.push(')');
            }
        }
    }
}

/// Where and why a stream was refused.
#[derive(Debug, Clone, PartialEq)]
pub struct PickleError {
    /// Byte offset of the opcode being run.
    pub offset: usize,
    pub message: String,
}

impl fmt::Display for PickleError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "at byte {}: {}", self.offset, self.message)
    }
}

impl std::error::Error for PickleError {}

/// Caps against hostile streams. The defaults are orders of magnitude above what a release
/// checkpoint needs (about ten values per tensor, mark nesting below 10).
#[derive(Debug, Clone, Copy)]
pub struct Limits {
    /// Values created (the arena size).
    pub max_values: usize,
    /// Memo entries.
    pub max_memo: usize,
    /// Open MARKs at once (the nesting of tuples/lists/dicts being built).
    pub max_marks: usize,
    /// Stack length.
    pub max_stack: usize,
    /// Items stored in containers, all together (DUP + APPEND can grow a list without new
    /// values).
    pub max_items: usize,
    /// Bytes of a LONG1 / LONG4 integer that does not fit `i64` (converted to decimal).
    pub max_bigint_bytes: usize,
    /// Digits of a text INT / LONG.
    pub max_int_digits: usize,
}

impl Default for Limits {
    fn default() -> Self {
        Self {
            max_values: 1 << 21,
            max_memo: 1 << 21,
            max_marks: 4096,
            max_stack: 1 << 21,
            max_items: 1 << 23,
            max_bigint_bytes: 1024,
            max_int_digits: 4096,
        }
    }
}

/// Parses a pickle with the default limits.
pub fn parse(data: &[u8]) -> Result<Pickle, PickleError> {
    parse_with_limits(data, Limits::default())
}

/// Parses with caller-chosen caps: data pickles far larger than a checkpoint's (a tracked
/// dataset's `optim.pkl`) need caps that grow with the input.
pub fn parse_with_limits(data: &[u8], limits: Limits) -> Result<Pickle, PickleError> {
    let mut m = Machine {
        data,
        pos: 0,
        op_pos: 0,
        nodes: Vec::new(),
        stack: Vec::new(),
        marks: Vec::new(),
        memo: HashMap::new(),
        items: 0,
        limits,
    };
    let root = m.run()?;
    Ok(Pickle {
        nodes: m.nodes,
        root,
    })
}

mod op {
    pub const MARK: u8 = b'(';
    pub const STOP: u8 = b'.';
    pub const POP: u8 = b'0';
    pub const POP_MARK: u8 = b'1';
    pub const DUP: u8 = b'2';
    pub const FLOAT: u8 = b'F';
    pub const INT: u8 = b'I';
    pub const BININT: u8 = b'J';
    pub const BININT1: u8 = b'K';
    pub const LONG: u8 = b'L';
    pub const BININT2: u8 = b'M';
    pub const NONE: u8 = b'N';
    pub const PERSID: u8 = b'P';
    pub const BINPERSID: u8 = b'Q';
    pub const REDUCE: u8 = b'R';
    pub const STRING: u8 = b'S';
    pub const BINSTRING: u8 = b'T';
    pub const SHORT_BINSTRING: u8 = b'U';
    pub const UNICODE: u8 = b'V';
    pub const BINUNICODE: u8 = b'X';
    pub const APPEND: u8 = b'a';
    pub const BUILD: u8 = b'b';
    pub const GLOBAL: u8 = b'c';
    pub const DICT: u8 = b'd';
    pub const EMPTY_DICT: u8 = b'}';
    pub const APPENDS: u8 = b'e';
    pub const GET: u8 = b'g';
    pub const BINGET: u8 = b'h';
    pub const INST: u8 = b'i';
    pub const LONG_BINGET: u8 = b'j';
    pub const LIST: u8 = b'l';
    pub const EMPTY_LIST: u8 = b']';
    pub const OBJ: u8 = b'o';
    pub const PUT: u8 = b'p';
    pub const BINPUT: u8 = b'q';
    pub const LONG_BINPUT: u8 = b'r';
    pub const SETITEM: u8 = b's';
    pub const TUPLE: u8 = b't';
    pub const EMPTY_TUPLE: u8 = b')';
    pub const SETITEMS: u8 = b'u';
    pub const BINFLOAT: u8 = b'G';
    // Protocol 2.
    pub const PROTO: u8 = 0x80;
    pub const NEWOBJ: u8 = 0x81;
    pub const EXT1: u8 = 0x82;
    pub const EXT2: u8 = 0x83;
    pub const EXT4: u8 = 0x84;
    pub const TUPLE1: u8 = 0x85;
    pub const TUPLE2: u8 = 0x86;
    pub const TUPLE3: u8 = 0x87;
    pub const NEWTRUE: u8 = 0x88;
    pub const NEWFALSE: u8 = 0x89;
    pub const LONG1: u8 = 0x8a;
    pub const LONG4: u8 = 0x8b;
    // Protocol 3.
    pub const BINBYTES: u8 = b'B';
    pub const SHORT_BINBYTES: u8 = b'C';
    // Protocol 4.
    pub const SHORT_BINUNICODE: u8 = 0x8c;
    pub const BINUNICODE8: u8 = 0x8d;
    pub const BINBYTES8: u8 = 0x8e;
    pub const EMPTY_SET: u8 = 0x8f;
    pub const ADDITEMS: u8 = 0x90;
    pub const FROZENSET: u8 = 0x91;
    pub const NEWOBJ_EX: u8 = 0x92;
    pub const STACK_GLOBAL: u8 = 0x93;
    pub const MEMOIZE: u8 = 0x94;
    pub const FRAME: u8 = 0x95;
    // Protocol 5.
    pub const BYTEARRAY8: u8 = 0x96;
    pub const NEXT_BUFFER: u8 = 0x97;
    pub const READONLY_BUFFER: u8 = 0x98;
}

const HIGHEST_PROTOCOL: u8 = 5;

type R<T> = Result<T, PickleError>;

struct Machine<'a> {
    data: &'a [u8],
    pos: usize,
    op_pos: usize,
    nodes: Vec<Value>,
    stack: Vec<Id>,
    /// Stack lengths at each open MARK; values below the innermost are out of reach, as in
    /// CPython.
    marks: Vec<usize>,
    memo: HashMap<u64, Id>,
    items: usize,
    limits: Limits,
}

impl<'a> Machine<'a> {
    fn err<T>(&self, message: impl Into<String>) -> R<T> {
        Err(PickleError {
            offset: self.op_pos,
            message: message.into(),
        })
    }

    // ---- reading ------------------------------------------------------------------------

    fn take(&mut self, n: u64) -> R<&'a [u8]> {
        let left = self.data.len() - self.pos;
        if n > left as u64 {
            return self.err(format!("truncated: needs {n} more bytes, {left} are left"));
        }
        let n = n as usize;
        let s = &self.data[self.pos..self.pos + n];
        self.pos += n;
        Ok(s)
    }

    fn byte(&mut self) -> R<u8> {
        Ok(self.take(1)?[0])
    }

    fn array<const N: usize>(&mut self) -> R<[u8; N]> {
        let s = self.take(N as u64)?;
        let mut a = [0u8; N];
        a.copy_from_slice(s);
        Ok(a)
    }

    fn u16(&mut self) -> R<u16> {
        Ok(u16::from_le_bytes(self.array()?))
    }

    fn u32(&mut self) -> R<u32> {
        Ok(u32::from_le_bytes(self.array()?))
    }

    fn i32(&mut self) -> R<i32> {
        Ok(i32::from_le_bytes(self.array()?))
    }

    fn u64(&mut self) -> R<u64> {
        Ok(u64::from_le_bytes(self.array()?))
    }

    /// A newline-terminated argument of the text opcodes, without the newline.
    fn line(&mut self) -> R<&'a [u8]> {
        let rest = &self.data[self.pos..];
        match rest.iter().position(|&b| b == b'\n') {
            Some(n) => {
                self.pos += n + 1;
                Ok(&rest[..n])
            }
            None => self.err("truncated: a text argument has no terminating newline"),
        }
    }

    fn line_str(&mut self) -> R<&'a str> {
        let l = self.line()?;
        match std::str::from_utf8(l) {
            Ok(s) => Ok(s),
            Err(_) => self.err("a text argument is not UTF-8"),
        }
    }

    // ---- stack --------------------------------------------------------------------------

    fn new_value(&mut self, v: Value) -> R<Id> {
        if self.nodes.len() >= self.limits.max_values {
            return self.err(format!(
                "more than {} values: refusing a pickle this large",
                self.limits.max_values
            ));
        }
        self.nodes.push(v);
        Ok(self.nodes.len() - 1)
    }

    fn push(&mut self, id: Id) -> R<()> {
        if self.stack.len() >= self.limits.max_stack {
            return self.err(format!(
                "stack deeper than {} entries",
                self.limits.max_stack
            ));
        }
        self.stack.push(id);
        Ok(())
    }

    fn push_new(&mut self, v: Value) -> R<()> {
        let id = self.new_value(v)?;
        self.push(id)
    }

    fn fence(&self) -> usize {
        self.marks.last().copied().unwrap_or(0)
    }

    fn pop(&mut self) -> R<Id> {
        if self.stack.len() <= self.fence() {
            return self.err(if self.marks.is_empty() {
                "stack underflow"
            } else {
                "stack underflow: the value needed is behind a MARK"
            });
        }
        match self.stack.pop() {
            Some(id) => Ok(id),
            None => self.err("stack underflow"),
        }
    }

    fn top(&self) -> R<Id> {
        if self.stack.len() <= self.fence() {
            return self.err("stack underflow: no value to act on");
        }
        match self.stack.last() {
            Some(&id) => Ok(id),
            None => self.err("stack underflow"),
        }
    }

    fn pop_mark(&mut self) -> R<Vec<Id>> {
        let Some(mark) = self.marks.pop() else {
            return self.err("no MARK to pop to");
        };
        if mark > self.stack.len() {
            return self.err("MARK beyond the stack");
        }
        Ok(self.stack.split_off(mark))
    }

    fn count_items(&mut self, n: usize) -> R<()> {
        self.items = self.items.saturating_add(n);
        if self.items > self.limits.max_items {
            return self.err(format!(
                "more than {} container items: refusing a pickle this large",
                self.limits.max_items
            ));
        }
        Ok(())
    }

    fn kind(&self, id: Id) -> &'static str {
        match self.nodes.get(id) {
            Some(Value::None) | None => "None",
            Some(Value::Bool(_)) => "bool",
            Some(Value::Int(_)) | Some(Value::BigInt(_)) => "int",
            Some(Value::Float(_)) => "float",
            Some(Value::Str(_)) => "str",
            Some(Value::Bytes(_)) => "bytes",
            Some(Value::List(_)) => "list",
            Some(Value::Tuple(_)) => "tuple",
            Some(Value::Dict(_)) => "dict",
            Some(Value::Set(_)) => "set",
            Some(Value::FrozenSet(_)) => "frozenset",
            Some(Value::Global(_)) => "global",
            Some(Value::Object(_)) => "object",
            Some(Value::PersistentId(_)) => "persistent id",
        }
    }

    // ---- memo ---------------------------------------------------------------------------

    fn memo_put(&mut self, index: u64) -> R<()> {
        let id = self.top()?;
        if !self.memo.contains_key(&index) && self.memo.len() >= self.limits.max_memo {
            return self.err(format!("more than {} memo entries", self.limits.max_memo));
        }
        self.memo.insert(index, id);
        Ok(())
    }

    fn memo_get(&mut self, index: u64) -> R<()> {
        match self.memo.get(&index) {
            Some(&id) => self.push(id),
            None => self.err(format!("memo entry {index} was never stored")),
        }
    }

    fn text_index(&mut self) -> R<u64> {
        let l = self.line_str()?;
        match l.trim().parse::<u64>() {
            Ok(i) => Ok(i),
            Err(_) => self.err(format!("bad memo index {l:?}")),
        }
    }

    // ---- containers ---------------------------------------------------------------------

    fn pairs(&self, flat: Vec<Id>, what: &str) -> R<Vec<(Id, Id)>> {
        if !flat.len().is_multiple_of(2) {
            return self.err(format!("odd number of items for {what}"));
        }
        Ok(flat.chunks_exact(2).map(|c| (c[0], c[1])).collect())
    }

    fn set_items(&mut self, target: Id, entries: Vec<(Id, Id)>) -> R<()> {
        self.count_items(entries.len())?;
        let kind = self.kind(target);
        match self.nodes.get_mut(target) {
            Some(Value::Dict(d)) => d.extend(entries),
            Some(Value::Object(o)) => o.items.extend(entries),
            _ => return self.err(format!("SETITEM(S) on a {kind}, not a dict-like object")),
        }
        Ok(())
    }

    fn append_items(&mut self, target: Id, elems: Vec<Id>, set_op: bool) -> R<()> {
        self.count_items(elems.len())?;
        let kind = self.kind(target);
        match (self.nodes.get_mut(target), set_op) {
            (Some(Value::List(l)), false) => l.extend(elems),
            (Some(Value::Set(s)), true) => s.extend(elems),
            (Some(Value::Object(o)), _) => o.elems.extend(elems),
            (_, false) => {
                return self.err(format!("APPEND(S) on a {kind}, not a list-like object"))
            }
            (_, true) => return self.err(format!("ADDITEMS on a {kind}, not a set-like object")),
        }
        Ok(())
    }

    fn tuple_of(&mut self, elems: Vec<Id>) -> R<()> {
        self.count_items(elems.len())?;
        self.push_new(Value::Tuple(elems))
    }

    fn pop_n(&mut self, n: usize) -> R<Vec<Id>> {
        let mut v = Vec::with_capacity(n);
        for _ in 0..n {
            v.push(self.pop()?);
        }
        v.reverse();
        Ok(v)
    }

    fn object(&mut self, callable: Id, args: Id, kwargs: Option<Id>) -> R<()> {
        self.push_new(Value::Object(Box::new(Object {
            callable,
            args,
            kwargs,
            state: None,
            items: Vec::new(),
            elems: Vec::new(),
        })))
    }

    fn expect_tuple(&self, id: Id, what: &str) -> R<()> {
        match self.nodes.get(id) {
            Some(Value::Tuple(_)) => Ok(()),
            _ => self.err(format!(
                "{what} arguments must be a tuple, got a {}",
                self.kind(id)
            )),
        }
    }

    /// A class is named by a global, or made by a call (protocols below 4 spell a nested
    /// class `Outer.Inner` as the REDUCE `getattr(Outer, "Inner")`).
    fn expect_class(&self, id: Id, what: &str) -> R<()> {
        match self.nodes.get(id) {
            Some(Value::Global(_)) | Some(Value::Object(_)) => Ok(()),
            _ => self.err(format!("{what} needs a class, got a {}", self.kind(id))),
        }
    }

    fn global(&mut self, module: String, name: String) -> R<Id> {
        self.new_value(Value::Global(Box::new(Global { module, name })))
    }

    // ---- numbers and strings ------------------------------------------------------------

    /// Decimal text of INT / LONG (Python writes plain decimal; `L` suffix stripped already).
    fn text_int(&self, s: &str) -> R<Value> {
        let t = s.trim();
        let (neg, digits) = match t.as_bytes().first() {
            Some(b'-') => (true, &t[1..]),
            Some(b'+') => (false, &t[1..]),
            _ => (false, t),
        };
        if digits.is_empty() || !digits.bytes().all(|b| b.is_ascii_digit()) {
            return self.err(format!("bad integer {s:?}"));
        }
        if digits.len() > self.limits.max_int_digits {
            return self.err(format!("integer of {} digits", digits.len()));
        }
        if let Ok(v) = t.parse::<i64>() {
            return Ok(Value::Int(v));
        }
        let digits = digits.trim_start_matches('0');
        Ok(Value::BigInt(format!(
            "{}{}",
            if neg { "-" } else { "" },
            digits
        )))
    }

    /// LONG1 / LONG4: little-endian two's complement.
    fn binary_int(&self, bytes: &[u8]) -> R<Value> {
        if bytes.is_empty() {
            return Ok(Value::Int(0));
        }
        let negative = bytes[bytes.len() - 1] & 0x80 != 0;
        let ext = if negative { 0xff } else { 0x00 };
        // Drop redundant sign-extension bytes, then see whether it fits i64.
        let mut n = bytes.len();
        while n > 1 && bytes[n - 1] == ext && (bytes[n - 2] & 0x80 != 0) == negative {
            n -= 1;
        }
        if n <= 8 {
            let mut buf = [ext; 8];
            buf[..n].copy_from_slice(&bytes[..n]);
            return Ok(Value::Int(i64::from_le_bytes(buf)));
        }
        if n > self.limits.max_bigint_bytes {
            return self.err(format!("integer of {n} bytes"));
        }
        Ok(Value::BigInt(decimal_of_twos_complement(&bytes[..n])))
    }

    fn text_float(&self, s: &str) -> R<f64> {
        match s.trim().parse::<f64>() {
            Ok(v) => Ok(v),
            Err(_) => self.err(format!("bad float {s:?}")),
        }
    }

    // ---- the loop -----------------------------------------------------------------------

    fn run(&mut self) -> R<Id> {
        loop {
            self.op_pos = self.pos;
            if self.pos >= self.data.len() {
                return self.err("truncated: the pickle ends before STOP");
            }
            let code = self.byte()?;
            if let Some(root) = self.step(code)? {
                return Ok(root);
            }
        }
    }

    /// Runs one opcode; `Some(value)` at STOP.
    fn step(&mut self, code: u8) -> R<Option<Id>> {
        use op::*;
        match code {
            PROTO => {
                let v = self.byte()?;
                if v > HIGHEST_PROTOCOL {
                    return self.err(format!("unsupported pickle protocol {v}"));
                }
            }
            FRAME => {
                // Frames only batch reads; the opcodes inside are ordinary.
                let len = self.u64()?;
                let left = (self.data.len() - self.pos) as u64;
                if len > left {
                    return self.err(format!("truncated: a frame of {len} bytes, {left} left"));
                }
            }
            STOP => return self.pop().map(Some),

            MARK => {
                if self.marks.len() >= self.limits.max_marks {
                    return self.err(format!("more than {} nested MARKs", self.limits.max_marks));
                }
                self.marks.push(self.stack.len());
            }
            POP => {
                // CPython: with nothing above the innermost MARK, POP removes the MARK.
                if self.stack.len() > self.fence() {
                    self.pop()?;
                } else if self.marks.pop().is_none() {
                    return self.err("stack underflow");
                }
            }
            POP_MARK => {
                self.pop_mark()?;
            }
            DUP => {
                let id = self.top()?;
                self.push(id)?;
            }

            NONE => self.push_new(Value::None)?,
            NEWTRUE => self.push_new(Value::Bool(true))?,
            NEWFALSE => self.push_new(Value::Bool(false))?,
            INT => {
                let l = self.line_str()?;
                let v = match l {
                    "00" => Value::Bool(false),
                    "01" => Value::Bool(true),
                    _ => self.text_int(l)?,
                };
                self.push_new(v)?;
            }
            LONG => {
                let l = self.line_str()?;
                let v = self.text_int(l.strip_suffix('L').unwrap_or(l))?;
                self.push_new(v)?;
            }
            BININT => {
                let v = self.i32()?;
                self.push_new(Value::Int(v.into()))?;
            }
            BININT1 => {
                let v = self.byte()?;
                self.push_new(Value::Int(v.into()))?;
            }
            BININT2 => {
                let v = self.u16()?;
                self.push_new(Value::Int(v.into()))?;
            }
            LONG1 => {
                let n = self.byte()?;
                let b = self.take(n.into())?;
                let v = self.binary_int(b)?;
                self.push_new(v)?;
            }
            LONG4 => {
                let n = self.i32()?;
                if n < 0 {
                    return self.err("LONG4 with a negative length");
                }
                let b = self.take(n as u64)?;
                let v = self.binary_int(b)?;
                self.push_new(v)?;
            }
            FLOAT => {
                let l = self.line_str()?;
                let v = self.text_float(l)?;
                self.push_new(Value::Float(v))?;
            }
            BINFLOAT => {
                let v = f64::from_be_bytes(self.array()?);
                self.push_new(Value::Float(v))?;
            }

            STRING => {
                let l = self.line()?;
                let s = match unquote_python_string(l) {
                    Ok(s) => s,
                    Err(e) => return self.err(e),
                };
                self.push_new(Value::Str(s))?;
            }
            BINSTRING => {
                let n = self.i32()?;
                if n < 0 {
                    return self.err("BINSTRING with a negative length");
                }
                let b = self.take(n as u64)?;
                self.push_new(Value::Str(String::from_utf8_lossy(b).into_owned()))?;
            }
            SHORT_BINSTRING => {
                let n = self.byte()?;
                let b = self.take(n.into())?;
                self.push_new(Value::Str(String::from_utf8_lossy(b).into_owned()))?;
            }
            UNICODE => {
                let l = self.line()?;
                let s = match raw_unicode_escape(l) {
                    Ok(s) => s,
                    Err(e) => return self.err(e),
                };
                self.push_new(Value::Str(s))?;
            }
            BINUNICODE | SHORT_BINUNICODE | BINUNICODE8 => {
                let n = match code {
                    BINUNICODE => self.u32()?.into(),
                    SHORT_BINUNICODE => self.byte()?.into(),
                    _ => self.u64()?,
                };
                let b = self.take(n)?;
                self.push_new(Value::Str(String::from_utf8_lossy(b).into_owned()))?;
            }
            BINBYTES | SHORT_BINBYTES | BINBYTES8 | BYTEARRAY8 => {
                let n = match code {
                    BINBYTES => self.u32()?.into(),
                    SHORT_BINBYTES => self.byte()?.into(),
                    _ => self.u64()?,
                };
                let b = self.take(n)?;
                self.push_new(Value::Bytes(b.to_vec()))?;
            }
            NEXT_BUFFER => return self.err("out-of-band buffers (NEXT_BUFFER) are not supported"),
            READONLY_BUFFER => {
                // Only changes a buffer's mutability: nothing to record.
                self.top()?;
            }

            EMPTY_TUPLE => self.push_new(Value::Tuple(Vec::new()))?,
            TUPLE1 | TUPLE2 | TUPLE3 => {
                let n = usize::from(code - TUPLE1) + 1;
                let v = self.pop_n(n)?;
                self.tuple_of(v)?;
            }
            TUPLE => {
                let v = self.pop_mark()?;
                self.tuple_of(v)?;
            }
            EMPTY_LIST => self.push_new(Value::List(Vec::new()))?,
            LIST => {
                let v = self.pop_mark()?;
                self.count_items(v.len())?;
                self.push_new(Value::List(v))?;
            }
            EMPTY_DICT => self.push_new(Value::Dict(Vec::new()))?,
            DICT => {
                let flat = self.pop_mark()?;
                let entries = self.pairs(flat, "DICT")?;
                self.count_items(entries.len())?;
                self.push_new(Value::Dict(entries))?;
            }
            EMPTY_SET => self.push_new(Value::Set(Vec::new()))?,
            FROZENSET => {
                let v = self.pop_mark()?;
                self.count_items(v.len())?;
                self.push_new(Value::FrozenSet(v))?;
            }
            APPEND => {
                let v = self.pop()?;
                let target = self.top()?;
                self.append_items(target, vec![v], false)?;
            }
            APPENDS => {
                let v = self.pop_mark()?;
                let target = self.top()?;
                self.append_items(target, v, false)?;
            }
            ADDITEMS => {
                let v = self.pop_mark()?;
                let target = self.top()?;
                self.append_items(target, v, true)?;
            }
            SETITEM => {
                let v = self.pop()?;
                let k = self.pop()?;
                let target = self.top()?;
                self.set_items(target, vec![(k, v)])?;
            }
            SETITEMS => {
                let flat = self.pop_mark()?;
                let entries = self.pairs(flat, "SETITEMS")?;
                let target = self.top()?;
                self.set_items(target, entries)?;
            }

            GLOBAL => {
                let module = self.line_str()?.to_owned();
                let name = self.line_str()?.to_owned();
                let id = self.global(module, name)?;
                self.push(id)?;
            }
            STACK_GLOBAL => {
                let name = self.pop()?;
                let module = self.pop()?;
                let (Some(Value::Str(m)), Some(Value::Str(n))) =
                    (self.nodes.get(module), self.nodes.get(name))
                else {
                    return self.err("STACK_GLOBAL needs two strings");
                };
                let (m, n) = (m.clone(), n.clone());
                let id = self.global(m, n)?;
                self.push(id)?;
            }
            INST => {
                let module = self.line_str()?.to_owned();
                let name = self.line_str()?.to_owned();
                let args = self.pop_mark()?;
                let class = self.global(module, name)?;
                self.count_items(args.len())?;
                let args = self.new_value(Value::Tuple(args))?;
                self.object(class, args, None)?;
            }
            OBJ => {
                let mut v = self.pop_mark()?;
                if v.is_empty() {
                    return self.err("OBJ without a class");
                }
                let class = v.remove(0);
                self.expect_class(class, "OBJ")?;
                self.count_items(v.len())?;
                let args = self.new_value(Value::Tuple(v))?;
                self.object(class, args, None)?;
            }
            REDUCE => {
                let args = self.pop()?;
                let callable = self.pop()?;
                self.expect_tuple(args, "REDUCE")?;
                match self.nodes.get(callable) {
                    Some(Value::Global(_)) | Some(Value::Object(_)) => {}
                    _ => {
                        return self.err(format!(
                            "REDUCE calls a {}, which is not callable",
                            self.kind(callable)
                        ))
                    }
                }
                self.object(callable, args, None)?;
            }
            NEWOBJ => {
                let args = self.pop()?;
                let class = self.pop()?;
                self.expect_tuple(args, "NEWOBJ")?;
                self.expect_class(class, "NEWOBJ")?;
                self.object(class, args, None)?;
            }
            NEWOBJ_EX => {
                let kwargs = self.pop()?;
                let args = self.pop()?;
                let class = self.pop()?;
                self.expect_tuple(args, "NEWOBJ_EX")?;
                self.expect_class(class, "NEWOBJ_EX")?;
                if !matches!(self.nodes.get(kwargs), Some(Value::Dict(_))) {
                    return self.err("NEWOBJ_EX keyword arguments must be a dict");
                }
                self.object(class, args, Some(kwargs))?;
            }
            BUILD => {
                let state = self.pop()?;
                let target = self.top()?;
                let kind = self.kind(target);
                match self.nodes.get_mut(target) {
                    Some(Value::Object(o)) => o.state = Some(state),
                    _ => return self.err(format!("BUILD on a {kind}, not an object")),
                }
            }

            PERSID => {
                let l = self.line()?;
                let pid = self.new_value(Value::Str(String::from_utf8_lossy(l).into_owned()))?;
                self.push_new(Value::PersistentId(pid))?;
            }
            BINPERSID => {
                let pid = self.pop()?;
                self.push_new(Value::PersistentId(pid))?;
            }

            PUT => {
                let i = self.text_index()?;
                self.memo_put(i)?;
            }
            BINPUT => {
                let i = self.byte()?;
                self.memo_put(i.into())?;
            }
            LONG_BINPUT => {
                let i = self.u32()?;
                self.memo_put(i.into())?;
            }
            MEMOIZE => {
                let i = self.memo.len() as u64;
                self.memo_put(i)?;
            }
            GET => {
                let i = self.text_index()?;
                self.memo_get(i)?;
            }
            BINGET => {
                let i = self.byte()?;
                self.memo_get(i.into())?;
            }
            LONG_BINGET => {
                let i = self.u32()?;
                self.memo_get(i.into())?;
            }

            EXT1 | EXT2 | EXT4 => {
                let code = match code {
                    EXT1 => u32::from(self.byte()?),
                    EXT2 => u32::from(self.u16()?),
                    _ => self.u32()?,
                };
                return self.err(format!(
                    "extension registry code {code} (EXT opcodes) is not supported"
                ));
            }
            other => {
                return self.err(format!(
                    "unknown opcode 0x{other:02x}{}",
                    if other.is_ascii_graphic() {
                        format!(" ('{}')", other as char)
                    } else {
                        String::new()
                    }
                ))
            }
        }
        Ok(None)
    }
}

/// Decimal of a little-endian two's complement integer (already size-capped by the caller).
fn decimal_of_twos_complement(bytes: &[u8]) -> String {
    let negative = bytes.last().is_some_and(|b| b & 0x80 != 0);
    let mut mag: Vec<u8> = bytes.to_vec();
    if negative {
        // Magnitude = two's complement negation: invert, add one.
        let mut carry = true;
        for b in mag.iter_mut() {
            let (v, c) = (!*b).overflowing_add(u8::from(carry));
            *b = v;
            carry = c;
        }
    }
    // Base-2^32 limbs, most significant first, divided by 10^9 repeatedly.
    let mut limbs: Vec<u32> = mag
        .chunks(4)
        .rev()
        .map(|c| {
            let mut a = [0u8; 4];
            a[..c.len()].copy_from_slice(c);
            u32::from_le_bytes(a)
        })
        .collect();
    let mut groups: Vec<u32> = Vec::new();
    while limbs.iter().any(|&l| l != 0) {
        let mut rem: u64 = 0;
        for l in limbs.iter_mut() {
            let cur = (rem << 32) | u64::from(*l);
            *l = (cur / 1_000_000_000) as u32;
            rem = cur % 1_000_000_000;
        }
        groups.push(rem as u32);
        while limbs.first() == Some(&0) {
            limbs.remove(0);
        }
    }
    let mut s = String::from(if negative { "-" } else { "" });
    match groups.split_last() {
        None => s.push('0'),
        Some((first, rest)) => {
            s.push_str(&first.to_string());
            for g in rest.iter().rev() {
                s.push_str(&format!("{g:09}"));
            }
        }
    }
    s
}

/// The argument of STRING: a Python 2 `repr` of a byte string, quoted, with backslash escapes.
fn unquote_python_string(line: &[u8]) -> Result<String, String> {
    let (first, last) = match (line.first(), line.last()) {
        (Some(&f), Some(&l)) if line.len() >= 2 => (f, l),
        _ => return Err("STRING argument is not quoted".into()),
    };
    if first != last || (first != b'\'' && first != b'"') {
        return Err("STRING argument is not quoted".into());
    }
    let body = &line[1..line.len() - 1];
    let mut out = Vec::with_capacity(body.len());
    let mut i = 0;
    while i < body.len() {
        let b = body[i];
        i += 1;
        if b != b'\\' {
            out.push(b);
            continue;
        }
        let Some(&e) = body.get(i) else {
            return Err("STRING ends with a lone backslash".into());
        };
        i += 1;
        match e {
            b'\\' | b'\'' | b'"' => out.push(e),
            b'a' => out.push(7),
            b'b' => out.push(8),
            b'f' => out.push(12),
            b'n' => out.push(b'\n'),
            b'r' => out.push(b'\r'),
            b't' => out.push(b'\t'),
            b'v' => out.push(11),
            b'\n' => {}
            b'x' => {
                let hex = body
                    .get(i..i + 2)
                    .and_then(|h| std::str::from_utf8(h).ok())
                    .and_then(|h| u8::from_str_radix(h, 16).ok());
                match hex {
                    Some(v) => out.push(v),
                    None => return Err("invalid \\x escape in STRING".into()),
                }
                i += 2;
            }
            b'0'..=b'7' => {
                let mut v = u32::from(e - b'0');
                for _ in 0..2 {
                    match body.get(i) {
                        Some(&d @ b'0'..=b'7') => {
                            v = v * 8 + u32::from(d - b'0');
                            i += 1;
                        }
                        _ => break,
                    }
                }
                out.push((v & 0xff) as u8);
            }
            other => {
                out.push(b'\\');
                out.push(other);
            }
        }
    }
    Ok(String::from_utf8_lossy(&out).into_owned())
}

/// The argument of UNICODE: `raw-unicode-escape`, i.e. Latin-1 bytes plus `\uXXXX` and
/// `\UXXXXXXXX` escapes.
fn raw_unicode_escape(line: &[u8]) -> Result<String, String> {
    let mut units: Vec<u32> = Vec::with_capacity(line.len());
    let mut i = 0;
    while i < line.len() {
        let b = line[i];
        let width = match (b, line.get(i + 1)) {
            (b'\\', Some(b'u')) => 4,
            (b'\\', Some(b'U')) => 8,
            _ => 0,
        };
        if width == 0 {
            units.push(b.into());
            i += 1;
            continue;
        }
        let cp = line
            .get(i + 2..i + 2 + width)
            .and_then(|h| std::str::from_utf8(h).ok())
            .filter(|h| h.bytes().all(|c| c.is_ascii_hexdigit()))
            .and_then(|h| u32::from_str_radix(h, 16).ok());
        match cp {
            Some(cp) if cp <= 0x10ffff => units.push(cp),
            _ => return Err("truncated or invalid \\u escape in UNICODE".into()),
        }
        i += 2 + width;
    }
    // Pair surrogates (a \ud83d\ude42 spelling); lone ones cannot be Rust chars.
    let mut s = String::with_capacity(units.len());
    let mut k = 0;
    while k < units.len() {
        let u = units[k];
        if (0xd800..0xdc00).contains(&u) {
            if let Some(&lo) = units.get(k + 1) {
                if (0xdc00..0xe000).contains(&lo) {
                    let cp = 0x10000 + ((u - 0xd800) << 10) + (lo - 0xdc00);
                    s.push(char::from_u32(cp).unwrap_or(char::REPLACEMENT_CHARACTER));
                    k += 2;
                    continue;
                }
            }
        }
        s.push(char::from_u32(u).unwrap_or(char::REPLACEMENT_CHARACTER));
        k += 1;
    }
    Ok(s)
}

// The integration tests' helpers, shared rather than copied.
#[cfg(test)]
#[path = "../../tests/common/mod.rs"]
mod test_common;

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::{json, Value as Json};
    use test_common::first_difference;

    fn golden(name: &str) -> std::path::PathBuf {
        std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("tests/golden")
            .join(name)
    }

    fn expected() -> Json {
        let path = golden("pickle_plain_expected.json");
        let text =
            std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        serde_json::from_str(&text).unwrap()
    }

    /// The canonical JSON of `tools/reference/pickle_fixtures.py::canon`.
    fn canon(p: &Pickle, id: Id, ancestors: &mut Vec<Id>) -> Json {
        if ancestors.contains(&id) {
            return json!({ "cycle": null });
        }
        assert!(ancestors.len() < 64, "runaway nesting");
        ancestors.push(id);
        let seq = |ids: &[Id], anc: &mut Vec<Id>| -> Vec<Json> {
            ids.iter().map(|&c| canon(p, c, anc)).collect()
        };
        let sorted = |mut v: Vec<Json>| {
            v.sort_by_key(|j| j.to_string());
            v
        };
        let out = match p.get(id) {
            Value::None => Json::Null,
            Value::Bool(b) => json!(b),
            Value::Int(i) => json!({ "int": i.to_string() }),
            Value::BigInt(s) => json!({ "int": s }),
            Value::Float(f) => json!({ "float": format!("{:016x}", f.to_bits()) }),
            Value::Str(s) => json!(s),
            Value::Bytes(b) => {
                let hex: String = b.iter().map(|x| format!("{x:02x}")).collect();
                json!({ "bytes": hex })
            }
            Value::List(v) => json!({ "list": seq(v, ancestors) }),
            Value::Tuple(v) => json!({ "tuple": seq(v, ancestors) }),
            Value::Set(v) => json!({ "set": sorted(seq(v, ancestors)) }),
            Value::FrozenSet(v) => json!({ "frozenset": sorted(seq(v, ancestors)) }),
            Value::Dict(e) => {
                let items: Vec<Json> = e
                    .iter()
                    .map(|&(k, v)| json!([canon(p, k, ancestors), canon(p, v, ancestors)]))
                    .collect();
                json!({ "dict": items })
            }
            Value::Global(g) => json!({ "global": [g.module, g.name] }),
            Value::PersistentId(pid) => json!({ "persid": canon(p, *pid, ancestors) }),
            Value::Object(o) => {
                let args = match p.get(o.args) {
                    Value::Tuple(a) => seq(a, ancestors),
                    other => panic!("object args are {other:?}"),
                };
                let kwargs = match o.kwargs.map(|k| p.get(k)) {
                    None => Json::Null,
                    Some(Value::Dict(e)) if e.is_empty() => Json::Null,
                    Some(Value::Dict(e)) => Json::Array(
                        e.iter()
                            .map(|&(k, v)| json!([canon(p, k, ancestors), canon(p, v, ancestors)]))
                            .collect(),
                    ),
                    Some(other) => panic!("kwargs are {other:?}"),
                };
                let items: Vec<Json> = o
                    .items
                    .iter()
                    .map(|&(k, v)| json!([canon(p, k, ancestors), canon(p, v, ancestors)]))
                    .collect();
                json!({
                    "object": canon(p, o.callable, ancestors),
                    "args": args,
                    "kwargs": kwargs,
                    "state": o.state.map_or(Json::Null, |s| canon(p, s, ancestors)),
                    "items": items,
                    "elems": seq(&o.elems, ancestors),
                })
            }
        };
        ancestors.pop();
        out
    }

    #[test]
    fn every_protocol_reads_like_cpython() {
        let exp = expected();
        let files = exp["files"].as_object().unwrap();
        assert_eq!(files.len(), 6, "protocols 0..=5");
        for (name, want) in files {
            let data = std::fs::read(golden(name)).unwrap();
            let p = parse(&data).unwrap_or_else(|e| panic!("{name}: {e}"));
            let got = canon(&p, p.root(), &mut Vec::new());
            if let Some(d) = first_difference(want, &got, name) {
                panic!("{d}");
            }
        }
    }

    #[test]
    fn handmade_streams_match_cpython() {
        let exp = expected();
        let cases = exp["handmade"].as_array().unwrap();
        let (mut ok, mut refused) = (0, 0);
        for case in cases {
            let name = case["name"].as_str().unwrap();
            let data = test_common::hex(case["hex"].as_str().unwrap());
            match (case.get("expected"), parse(&data)) {
                (Some(want), Ok(p)) => {
                    let got = canon(&p, p.root(), &mut Vec::new());
                    if let Some(d) = first_difference(want, &got, name) {
                        panic!("{d}");
                    }
                    ok += 1;
                }
                (Some(_), Err(e)) => panic!("{name}: CPython reads it, we refuse: {e}"),
                (None, Ok(p)) => panic!(
                    "{name}: CPython refuses it ({}), we read {}",
                    case["error"],
                    p.describe(p.root())
                ),
                (None, Err(_)) => refused += 1,
            }
        }
        assert!(ok >= 10 && refused >= 15, "{ok} read, {refused} refused");
    }

    #[test]
    fn errors_name_the_offset_and_cause() {
        let e = parse(b"\x80\x02\xff.").unwrap_err();
        assert_eq!(e.offset, 2);
        assert!(e.message.contains("unknown opcode 0xff"), "{e}");
        let e = parse(b"\x80\x02\x82\x01.").unwrap_err();
        assert!(e.message.contains("extension registry"), "{e}");
        let e = parse(b"\x80\x02K\x01").unwrap_err();
        assert!(e.message.contains("before STOP"), "{e}");
        let e = parse(b"X\xff\xff\xff\x7fab.").unwrap_err();
        assert!(e.message.contains("truncated"), "{e}");
        let e = parse(b"\x80\x02c__main__\nConfig\n)b.").unwrap_err();
        assert!(e.message.contains("BUILD on a global"), "{e}");
    }

    /// Every prefix of a real stream, and many corruptions of it, end in a value or an error.
    #[test]
    fn truncated_and_corrupted_streams_never_panic() {
        for name in [
            "pickle_plain_p2.pkl",
            "pickle_plain_p4.pkl",
            "pickle_plain_p0.pkl",
        ] {
            let data = std::fs::read(golden(name)).unwrap();
            for cut in 0..data.len() {
                assert!(
                    parse(&data[..cut]).is_err(),
                    "{name}: the first {cut} bytes parsed"
                );
            }
            // A fixed xorshift sequence of single-byte corruptions.
            let mut state: u64 = 0x9e37_79b9_7f4a_7c15;
            for _ in 0..3000 {
                state ^= state << 13;
                state ^= state >> 7;
                state ^= state << 17;
                let mut bad = data.clone();
                let pos = (state % data.len() as u64) as usize;
                bad[pos] = (state >> 32) as u8;
                let _ = parse(&bad);
            }
        }
    }

    #[test]
    fn limits_stop_hostile_streams() {
        let small = Limits {
            max_values: 100,
            max_memo: 10,
            max_marks: 8,
            max_stack: 50,
            max_items: 200,
            ..Limits::default()
        };
        let round = [b"(".to_vec(), b"h\x00".repeat(30), b"e".to_vec()].concat();
        let cases: Vec<(&str, Vec<u8>, &str)> = vec![
            (
                "values",
                [b"]0".repeat(150), b"N.".to_vec()].concat(),
                "values",
            ),
            ("marks", [b"(".repeat(20), b"N.".to_vec()].concat(), "MARK"),
            (
                "memo",
                (0..20u8)
                    .flat_map(|i| [b'N', b'q', i])
                    .chain(*b".")
                    .collect(),
                "memo",
            ),
            (
                "stack",
                [b"N".to_vec(), b"2".repeat(60), b".".to_vec()].concat(),
                "stack",
            ),
            (
                "items",
                [b"Nq\x00]".to_vec(), round.repeat(10), b".".to_vec()].concat(),
                "container items",
            ),
        ];
        for (what, data, needle) in cases {
            let e = parse_with_limits(&data, small).expect_err(what);
            assert!(e.message.contains(needle), "{what}: {e}");
        }
        // A huge declared length is refused before anything is allocated.
        let e = parse(b"\x8e\xff\xff\xff\xff\xff\xff\xff\x7f.").unwrap_err();
        assert!(e.message.contains("truncated"), "{e}");
        // An integer of 2000 bytes is refused; 1000 bytes is read.
        let mut long = vec![op::LONG4];
        long.extend_from_slice(&2000i32.to_le_bytes());
        long.extend([0x11; 2000]);
        long.push(b'.');
        assert!(parse(&long).unwrap_err().message.contains("2000 bytes"));
        let mut long = vec![op::LONG4];
        long.extend_from_slice(&1000i32.to_le_bytes());
        long.extend([0x11; 1000]);
        long.push(b'.');
        assert!(matches!(parse(&long).unwrap().get(0), Value::BigInt(_)));
    }

    #[test]
    fn references_and_cycles_are_shared_not_copied() {
        // d = {}; d["self"] = d; [d, d]
        let p = parse(b"\x80\x02]q\x00(}q\x01X\x04\x00\x00\x00selfq\x02h\x01sh\x01e.").unwrap();
        let Value::List(l) = p.get(p.root()) else {
            panic!("{:?}", p.get(p.root()))
        };
        assert_eq!(l.len(), 2);
        assert_eq!(l[0], l[1], "one dict, referenced twice");
        let Value::Dict(e) = p.get(l[0]) else {
            panic!()
        };
        assert_eq!(e.len(), 1);
        assert_eq!(e[0].1, l[0], "the dict contains itself");
        assert!(p.describe(p.root()).starts_with("[<dict of 1 items>"));
    }

    #[test]
    fn big_integers_convert_exactly() {
        for (bytes, want) in [
            (vec![], "0"),
            (vec![0xff], "-1"),
            (vec![0x00, 0x80], "-32768"),
            (vec![0, 0, 0, 0, 0, 0, 0, 0, 1], "18446744073709551616"),
            (vec![0, 0, 0, 0, 0, 0, 0, 0x80], "-9223372036854775808"),
            (
                vec![0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0x7f, 0x00],
                "9223372036854775807",
            ),
            (
                vec![0xfb, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xfe],
                "-18446744073709551621",
            ),
        ] {
            let mut data = vec![op::LONG1, bytes.len() as u8];
            data.extend(&bytes);
            data.push(b'.');
            let p = parse(&data).unwrap();
            let got = match p.get(p.root()) {
                Value::Int(i) => i.to_string(),
                Value::BigInt(s) => s.clone(),
                other => panic!("{other:?}"),
            };
            assert_eq!(got, want, "bytes {bytes:02x?}");
        }
    }
}
