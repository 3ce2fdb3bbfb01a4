//! The GAGAvatar network (spec sections 3-8) in candle: each module is a struct whose parameter
//! names are the release checkpoint's keys.

pub mod config;
pub mod error;
pub mod layers;

pub use config::ModelConfig;
pub use error::{NetError, Result};
