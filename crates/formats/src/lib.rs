//! The file formats gagavatar reads and writes, on the ground floor of the workspace: every
//! other crate reads user files through here, so the parsers are hardened (and fuzzed) in one
//! place.
//!
//! - [`image`]: photos decoded by their content, not their name, with EXIF orientation applied,
//!   a size cap, and downscaling of huge photos right after decoding.
//! - [`atomic`]: outputs written under a temporary sibling name and renamed into place, so a
//!   crash never leaves a half-written file or directory.

pub mod atomic;
pub mod error;
pub mod image;

pub use error::FormatError;
