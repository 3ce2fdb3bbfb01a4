//! The GAGAvatar pipeline as a library, between the model crates and the shells (CLI, Python,
//! server):
//!
//! ```no_run
//! use gagavatar_avatar::{Drive, Engine, EngineConfig};
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! let engine = Engine::open(&EngineConfig::new("assets/demo/weights.safetensors"))?;
//! let record = gagavatar_flame::TrackedFrame::from_json_file("assets/demo/source.json".as_ref())?;
//! let photo = image::open("assets/demo/source.png")?.to_rgb8();
//! let avatar = engine.avatar(&photo, &record)?;            // reconstruct once
//! let mut drive = avatar.cpu_drive();                        // or avatar.gpu_drive(..)
//! let codes = avatar.codes(&record, "the source record")?;
//! let frame = drive.render(&codes, &avatar.source_camera()?)?; // RGB u8, size x size
//! # let _ = frame; Ok(()) }
//! ```
//!
//! Tracking is here too: [`Engine::track`] turns a photo or a video into records and crops
//! (in a folder of the release's layout, or the content-addressed cache), and
//! [`Engine::track_photo`] a photo in memory into the record and crop [`Engine::avatar`] takes.
//!
//! Loading happens once ([`Engine::open`]); an [`Avatar`] is reconstructed once per source and
//! driven any number of times through a [`Drive`] ([`CpuDrive`] or [`GpuDrive`]). The library
//! prints nothing: warnings are returned ([`Engine::warnings`]), errors are typed
//! ([`AvatarError`]).

pub mod avatar;
pub mod cache;
pub mod convert;
pub mod drive;
pub mod engine;
mod error;
pub mod flame_source;
pub mod many;
pub mod monitor;
pub mod orbit;
pub mod tracking;

pub use avatar::Avatar;
pub use cache::{TrackTo, Tracked};
pub use convert::{image_tensor, to_rgb8, transforms_tensor};
pub use drive::{Camera, CpuDrive, Drive, DriveTimes, GpuDrive};
pub use engine::{
    flame_mismatch, load_flame, synthetic_fingerprint, Engine, EngineConfig, FlameSource,
    SYNTHETIC_FLAME,
};
pub use error::{one_line, AvatarError, Result};
pub use gagavatar_gpu::flame::FrameCodes;
pub use gagavatar_gpu::reconstruct::GpuReconstruct;
pub use gagavatar_ops::Precision;
pub use many::render_many;
pub use monitor::{CancelToken, Monitor, NoMonitor};
pub use tracking::{InputKind, LiveTracker, PhotoTrack, Tracker};
