//! Python pickles, read and written without a Python interpreter and without running anything.
//!
//! - [`read`]: the data-only interpreter (protocols 0 to 5) that turns a stream into a graph of
//!   values; classes are recorded by name, never imported or called.
//! - [`plain`]: plain data (dicts, lists, strings, numbers, bytes, numpy arrays) out of that
//!   graph, refusing everything else by name.
//! - [`write`]: plain data back out as a protocol 4 pickle that CPython + numpy load.

pub mod plain;
pub mod read;
pub mod write;

pub use plain::{parse_pickle, read_pickle, DictKey, PyValue};
pub use read::{parse, parse_with_limits, Limits, Pickle, PickleError, Value};
pub use write::to_pickle;
