//! The file formats gagavatar reads and writes, on the ground floor of the workspace: every
//! other crate reads user files through here, so the parsers are hardened (and fuzzed, see
//! `fuzz/`) in one place. This crate knows bytes and generic values (tensors, plain Python
//! data, images); what a FLAME asset or a tracked record *means* is decided above it.
//!
//! - [`pickle`]: Python pickles read as data (never run) and written ([`pickle::read`],
//!   [`pickle::plain`], [`pickle::write`]); [`numpy`]: the arrays inside them.
//! - [`torch_zip`]: `torch.save` checkpoints, read and written.
//! - [`safetensors`]: safetensors files, read into tensor maps and written atomically.
//! - [`tensor`]: the generic tensor values those readers return.
//! - [`lmdb`]: a bounds-checked LMDB reader and writer (the release's `img_lmdb/`).
//! - [`ply`]: PLY point clouds (3DGS scenes).
//! - [`onnx`]: ONNX model files (a user's ArcFace for `eval --arcface`), the protobuf decoded
//!   by hand into nodes, attributes and initializers.
//! - [`sniff`]: what a file is, from its first bytes, for error messages.
//! - [`image`]: photos decoded by their content, not their name, with EXIF orientation applied,
//!   a size cap, and downscaling of huge photos right after decoding.
//! - [`atomic`]: outputs written under a temporary sibling name and renamed into place, so a
//!   crash never leaves a half-written file or directory.

pub mod atomic;
pub mod error;
pub mod image;
pub mod lmdb;
pub mod numpy;
pub mod onnx;
pub mod pickle;
pub mod ply;
pub mod safetensors;
pub mod sniff;
pub mod tensor;
pub mod torch_zip;

pub use error::FormatError;
