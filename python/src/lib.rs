//! The Python package `gagavatar`: the pipeline library (`gagavatar-avatar`) with NumPy arrays in
//! and out. Built by maturin with the `python` feature (`pip install ./python`); without it this
//! crate is empty.

#[cfg(feature = "python")]
mod py;
