//! Synthetic head datasets for training GAGAvatar without tracked photos: FLAME heads (the
//! synthetic asset or the licensed one) with procedural identities, random expressions, jaw and
//! eye poses and release-style cameras, rendered by a small CPU rasterizer and written in the
//! release layout (`img_lmdb/`, `optim.pkl`, `dataset.json`) with records that are exact for the
//! images.
//!
//! * [`rasterizer`]: z-buffered triangles, perspective-correct barycentrics, supersampling.
//! * [`appearance`]: per-identity skin, hair, eyes, lips, patterns; face-anchored texture.
//! * [`sample`]: seeded shape codes, expressions, poses and cameras.
//! * [`dataset`]: the generator and the dataset writer.

pub mod appearance;
pub mod dataset;
pub mod error;
pub mod rasterizer;
pub mod sample;

pub use appearance::{Appearance, HeadAnchors, Material, Pattern};
pub use dataset::{
    frame_name, project, DatasetSummary, Generator, NoProgress, Progress, RenderedFrame,
    SynthConfig, WriteOptions, FLAME_BLOCK, MAX_SIZE, MIN_SIZE,
};
pub use error::{Result, SynthError};
pub use rasterizer::{to_rgb8, GBuffer, Rasterizer, NO_FACE};
pub use sample::{FrameSample, Rng, SampleConfig};
