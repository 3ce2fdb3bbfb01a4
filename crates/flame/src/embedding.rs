//! Where the landmarks sit on the surface: the asset's barycentric embeddings, as data. The
//! asset reads them and [`crate::landmarks`] evaluates them; keeping the data here lets the
//! asset sit below the model code that evaluates it.

/// Rows of the dynamic-contour table: yaw 0..39 degrees, then -1..-39.
pub const DYNAMIC_ROWS: usize = 79;

#[derive(Debug, Clone, PartialEq, Default)]
pub struct LandmarkEmbedding {
    pub static_faces: Vec<u32>,
    pub static_bary: Vec<[f32; 3]>,
    /// `[79, dynamic_count]` row-major.
    pub dynamic_faces: Vec<u32>,
    pub dynamic_bary: Vec<[f32; 3]>,
    pub dynamic_count: usize,
    pub full_faces: Vec<u32>,
    pub full_bary: Vec<[f32; 3]>,
}
