//! The GAGAvatar release's tracked-data formats, read and written natively and safely
//! (spec sections 10-11):
//!
//! The file formats themselves (pickles, numpy arrays, LMDB, images) are read and written by
//! `gagavatar-formats`; this crate knows what the release's files *mean*:
//!
//! * [`records`]: `optim.pkl` / `smoothed.pkl` frame records as [`TrackedFrame`]s.
//! * [`images`]: image values (PNG / JPEG bytes or a torch-saved tensor) to RGB.
//! * [`driver`]: driving sequences (tracked folder or JSON) and source records for reenactment.
//! * [`dataset`]: training datasets in the release layout or our folder layout.
//! * [`names`]: `<video>_<frame>` names and their natural order.

pub mod dataset;
pub mod driver;
pub mod error;
pub mod images;
pub mod names;
pub mod records;

pub use dataset::{write_release_dataset, Dataset, DatasetSplits, FolderDataset, ReleaseDataset};
pub use driver::{read_source_record, DriverFrame, DriverSequence};
pub use error::{DataError, Result};
pub use gagavatar_flame::TrackedFrame;
pub use gagavatar_formats::lmdb::{write_lmdb, LmdbReader, LmdbStat};
pub use gagavatar_formats::numpy::NdArray;
pub use gagavatar_formats::pickle::{read_pickle, PyValue};
pub use images::{decode_image, encode_png};
pub use names::{frame_name_cmp, group_by_video, sort_frame_names, split_frame_name};
pub use records::{read_records, write_records};
