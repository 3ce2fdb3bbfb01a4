//! The GAGAvatar network (spec sections 3-8) in candle: each module is a struct whose parameter
//! names are the release checkpoint's keys.

pub mod config;
pub mod dino;
pub mod dpt;
pub mod error;
pub mod layers;

pub use config::ModelConfig;
pub use error::{NetError, Result};
pub mod checkpoint;
pub mod gs_generator;
pub mod model;
pub mod plane;
pub mod style_unet;
pub mod train;
