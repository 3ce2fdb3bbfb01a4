//! The GAGAvatar release's tracked-data formats, read and written natively and safely
//! (spec sections 10-11):
//!
//! * [`pyobj`]: plain data (dicts, lists, strings, numbers, numpy arrays) out of Python pickles,
//!   nothing else (no class is imported or run); [`pickle_out`] writes it back.
//! * [`records`]: `optim.pkl` / `smoothed.pkl` frame records as [`TrackedFrame`]s.
//! * [`lmdb`]: a bounds-checked LMDB reader and writer for `img_lmdb/`.
//! * [`images`]: image values (PNG / JPEG bytes or a torch-saved tensor) to RGB.
//! * [`driver`]: driving sequences (tracked folder or JSON) and source records for reenactment.
//! * [`dataset`]: training datasets in the release layout or our folder layout.
//! * [`names`]: `<video>_<frame>` names and their natural order.

pub mod dataset;
pub mod driver;
pub mod error;
pub mod fsutil;
pub mod images;
pub mod lmdb;
pub mod names;
pub mod pickle_out;
pub mod pyobj;
pub mod records;

pub use dataset::{write_release_dataset, Dataset, DatasetSplits, FolderDataset, ReleaseDataset};
pub use driver::{read_source_record, DriverFrame, DriverSequence};
pub use error::{DataError, Result};
pub use gagavatar_flame::TrackedFrame;
pub use images::{decode_image, encode_png};
pub use lmdb::{write_lmdb, LmdbReader, LmdbStat};
pub use names::{frame_name_cmp, group_by_video, sort_frame_names, split_frame_name};
pub use pyobj::{read_pickle, NdArray, PyValue};
pub use records::{read_records, write_records};
