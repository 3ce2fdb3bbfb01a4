//! FLAME head model (spec section 9). Work in progress.
