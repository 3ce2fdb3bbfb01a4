//! The face landmark model with attention (`face_landmark_with_attention.tflite`, spec
//! TRACKING.md sections 8 and 10): a BlazeBlock backbone regresses the 468-point mesh and a
//! face flag from the 192x192 crop; three attention branches then sample the backbone's 48x48
//! features around the lips and each eye (a rotated rectangle placed from the mesh itself,
//! resampled to 16x16 by a bilinear affine sampler) and regress 80 lip points, 71 points per
//! eye and 5 per iris, mapped back into the crop. MediaPipe runs the three geometric steps as
//! custom TFLite ops; they are written out here from their definitions.

use candle_core::Result;
use candle_nn::VarBuilder;

use crate::kernels::Act;
use crate::layers::{prelu, BlazeBlock, Conv2d, Pad};
use crate::tensor::Nhwc;

/// Mesh points the lip branch is placed on and refines (x, y only), in the branch's output
/// order.
pub const LIPS: [usize; 80] = [
    61, 146, 91, 181, 84, 17, 314, 405, 321, 375, 291, 185, 40, 39, 37, 0, 267, 269, 270, 409, 78,
    95, 88, 178, 87, 14, 317, 402, 318, 324, 308, 191, 80, 81, 82, 13, 312, 311, 310, 415, 76, 77,
    90, 180, 85, 16, 315, 404, 320, 307, 306, 184, 74, 73, 72, 11, 302, 303, 304, 408, 62, 96, 89,
    179, 86, 15, 316, 403, 319, 325, 292, 183, 42, 41, 38, 12, 268, 271, 272, 407,
];

/// Mesh points of the first eye (corners 33 and 133: the subject's right eye, image left) and
/// its brow.
pub const LEFT_EYE: [usize; 71] = [
    33, 7, 163, 144, 145, 153, 154, 155, 133, 246, 161, 160, 159, 158, 157, 173, 130, 25, 110, 24,
    23, 22, 26, 112, 243, 247, 30, 29, 27, 28, 56, 190, 226, 31, 228, 229, 230, 231, 232, 233, 244,
    113, 225, 224, 223, 222, 221, 189, 35, 124, 46, 53, 52, 65, 143, 111, 117, 118, 119, 120, 121,
    128, 245, 156, 70, 63, 105, 66, 107, 55, 193,
];

/// Mesh points of the second eye (corners 362 and 263) and its brow.
pub const RIGHT_EYE: [usize; 71] = [
    263, 249, 390, 373, 374, 380, 381, 382, 362, 466, 388, 387, 386, 385, 384, 398, 359, 255, 339,
    254, 253, 252, 256, 341, 463, 467, 260, 259, 257, 258, 286, 414, 446, 261, 448, 449, 450, 451,
    452, 453, 464, 342, 445, 444, 443, 442, 441, 413, 265, 353, 276, 283, 282, 295, 372, 340, 346,
    347, 348, 349, 350, 357, 465, 383, 300, 293, 334, 296, 336, 285, 417,
];

/// The mesh points that orient each branch's rectangle: (lips, first eye, second eye).
pub const ROTATION_POINTS: [(usize, usize); 3] = [(61, 291), (33, 133), (362, 263)];
/// Each branch's rectangle is 1.5 times the bounding box of its points.
pub const BRANCH_SCALE: f32 = 1.5;
/// Branch feature maps are 16x16.
pub const BRANCH_SIZE: usize = 16;
/// The mesh (192-px units) is scaled by this to the 48x48 feature map the branches sample.
pub const MESH_TO_FEATURES: f32 = 0.25;
/// Element-wise factors applied to a branch's 4x4 matrix before its points are mapped back
/// (the translation to 192-px units).
pub const LANDMARK_MATRIX_FACTORS: [f32; 16] = [
    1., 1., 4., 4., 1., 1., 4., 4., 0.25, 0.25, 1., 1., 0.25, 0.25, 1., 1.,
];

/// The raw outputs, in 192-px crop units.
#[derive(Debug, Clone)]
pub struct MeshOutputs {
    /// 468 x (x, y, z).
    pub mesh: Vec<f32>,
    /// 80 x (x, y).
    pub lips: Vec<f32>,
    /// 71 x (x, y) each.
    pub left_eye: Vec<f32>,
    pub right_eye: Vec<f32>,
    /// 5 x (x, y) each.
    pub left_iris: Vec<f32>,
    pub right_iris: Vec<f32>,
    /// Face presence logit.
    pub face_flag: f32,
}

fn dw_name(i: usize) -> String {
    if i == 0 {
        "depthwise_conv2d".into()
    } else {
        format!("depthwise_conv2d_{i}")
    }
}

fn prelu_name(i: usize) -> String {
    if i == 0 {
        "p_re_lu".into()
    } else {
        format!("p_re_lu_{i}")
    }
}

/// A PReLU BlazeBlock named by its depthwise index and its pointwise (= PReLU) index.
fn block(
    vb: &VarBuilder,
    dw: usize,
    pw: usize,
    cin: usize,
    cout: usize,
    stride: usize,
) -> Result<BlazeBlock> {
    let act = prelu(vb, &prelu_name(pw), cout)?;
    BlazeBlock::new(
        vb,
        (&dw_name(dw), &format!("conv2d_{pw}")),
        cin,
        cout,
        stride,
        act,
    )
}

/// Blocks in sequence from a borrowed input (`blocks` is non-empty).
fn run(blocks: &[BlazeBlock], x: &Nhwc) -> Nhwc {
    let h = blocks[0].forward(x);
    blocks[1..].iter().fold(h, |h, b| b.forward(&h))
}

/// A branch's first part: 16x16x32 down to 4x4x128 in six blocks.
#[derive(Debug, Clone)]
struct Stem {
    blocks: Vec<BlazeBlock>,
}

impl Stem {
    fn new(vb: &VarBuilder, dw: usize, pw: usize) -> Result<Self> {
        let shape = [
            (32, 32, 1),
            (32, 32, 1),
            (32, 64, 2),
            (64, 64, 1),
            (64, 64, 1),
            (64, 128, 2),
        ];
        let blocks = shape
            .iter()
            .enumerate()
            .map(|(i, &(ci, co, s))| block(vb, dw + i, pw + i, ci, co, s))
            .collect::<Result<_>>()?;
        Ok(Stem { blocks })
    }
}

/// A branch's head: 4x4x128 through five blocks to 2x2, a 1x1 to 32 channels, one block,
/// and a 2x2 stride-2 convolution to the points.
#[derive(Debug, Clone)]
struct Tail {
    blocks: Vec<BlazeBlock>,
    reduce: Conv2d,
    reduce_act: Act,
    last: BlazeBlock,
    head: Conv2d,
}

impl Tail {
    fn new(vb: &VarBuilder, dw: usize, pw: usize, head: &str, outputs: usize) -> Result<Self> {
        let strides = [1, 1, 2, 1, 1];
        let blocks = strides
            .iter()
            .enumerate()
            .map(|(i, &s)| block(vb, dw + i, pw + i, 128, 128, s))
            .collect::<Result<_>>()?;
        let r = pw + 5;
        Ok(Tail {
            blocks,
            reduce: Conv2d::pointwise(vb, &format!("conv2d_{r}"), 128, 32)?,
            reduce_act: prelu(vb, &prelu_name(r), 32)?,
            last: block(vb, dw + 5, r + 1, 32, 32, 1)?,
            head: Conv2d::new(vb, head, 32, outputs, 2, 2, Pad::Valid)?,
        })
    }

    fn forward(&self, x: &Nhwc) -> Vec<f32> {
        let h = run(&self.blocks, x);
        let h = self.reduce.forward(&h, &self.reduce_act);
        let h = self.last.forward(&h);
        self.head.forward(&h, &Act::None).into_vec()
    }
}

/// The 478-point face landmark network.
#[derive(Debug, Clone)]
pub struct AttentionMeshNet {
    stem: Conv2d,
    stem_act: Act,
    blocks: Vec<BlazeBlock>,
    reduce: Conv2d,
    reduce_act: Act,
    last: BlazeBlock,
    mesh: Conv2d,
    flag: Conv2d,
    lips: (Stem, Tail),
    left: (Stem, Tail, Tail),
    right: (Stem, Tail, Tail),
}

/// (input, output channels, stride) of the backbone's 17 blocks; block 2's output (48x48x32)
/// is what the branches sample.
const BACKBONE: [(usize, usize, usize); 17] = [
    (16, 16, 1),
    (16, 16, 1),
    (16, 32, 2),
    (32, 32, 1),
    (32, 32, 1),
    (32, 64, 2),
    (64, 64, 1),
    (64, 64, 1),
    (64, 128, 2),
    (128, 128, 1),
    (128, 128, 1),
    (128, 128, 2),
    (128, 128, 1),
    (128, 128, 1),
    (128, 128, 2),
    (128, 128, 1),
    (128, 128, 1),
];
const FEATURE_TAP: usize = 2;

impl AttentionMeshNet {
    pub const INPUT: usize = 192;

    pub fn new(vb: VarBuilder) -> Result<Self> {
        let blocks = BACKBONE
            .iter()
            .enumerate()
            .map(|(i, &(ci, co, s))| block(&vb, i, i + 1, ci, co, s))
            .collect::<Result<_>>()?;
        Ok(AttentionMeshNet {
            stem: Conv2d::new(&vb, "conv2d", 3, 16, 3, 2, Pad::Same)?,
            stem_act: prelu(&vb, "p_re_lu", 16)?,
            blocks,
            reduce: Conv2d::pointwise(&vb, "conv2d_18", 128, 32)?,
            reduce_act: prelu(&vb, "p_re_lu_18", 32)?,
            last: block(&vb, 17, 19, 32, 32, 1)?,
            mesh: Conv2d::new(&vb, "output_mesh", 32, 1404, 3, 3, Pad::Valid)?,
            flag: Conv2d::new(&vb, "conv_faceflag", 32, 1, 3, 3, Pad::Valid)?,
            lips: (
                Stem::new(&vb, 18, 20)?,
                Tail::new(&vb, 24, 26, "conv_lips", 160)?,
            ),
            left: (
                Stem::new(&vb, 30, 33)?,
                Tail::new(&vb, 36, 39, "conv_left_eye", 142)?,
                Tail::new(&vb, 42, 46, "conv_left_iris", 10)?,
            ),
            right: (
                Stem::new(&vb, 48, 53)?,
                Tail::new(&vb, 54, 59, "conv_right_eye", 142)?,
                Tail::new(&vb, 60, 66, "conv_right_iris", 10)?,
            ),
        })
    }

    /// `x`: the 192x192x3 crop in [0, 1].
    pub fn forward(&self, x: &Nhwc) -> MeshOutputs {
        assert_eq!((x.h, x.w, x.c), (192, 192, 3), "landmark model input");
        let stem = self.stem.forward(x, &self.stem_act);
        let features = run(&self.blocks[..=FEATURE_TAP], &stem);
        drop(stem);
        let h = run(&self.blocks[FEATURE_TAP + 1..], &features);
        let h = self.reduce.forward(&h, &self.reduce_act);
        let h = self.last.forward(&h);
        let mesh = self.mesh.forward(&h, &Act::None).into_vec();
        let face_flag = self.flag.forward(&h, &Act::None).data[0];

        let scaled: Vec<f32> = mesh.iter().map(|v| v * MESH_TO_FEATURES).collect();
        let m_lips = landmarks_to_matrix(&scaled, ROTATION_POINTS[0], &LIPS);
        let m_left = landmarks_to_matrix(&scaled, ROTATION_POINTS[1], &LEFT_EYE);
        let m_right = landmarks_to_matrix(&scaled, ROTATION_POINTS[2], &RIGHT_EYE);
        // The branches are independent: with two threads, phase 1 runs the whole lip branch
        // beside both eye stems, phase 2 the four eye and iris heads (about equal work each).
        use std::sync::Mutex;
        let sample =
            |m: &[f32; 16]| transform_tensor_bilinear(&features, m, BRANCH_SIZE, BRANCH_SIZE);
        let lips = Mutex::new(Vec::new());
        let stems: [Mutex<Option<Nhwc>>; 2] = [Mutex::new(None), Mutex::new(None)];
        let eyes = [&self.left, &self.right];
        let mats = [&m_left, &m_right];
        crate::pool::run(3, &|i| match i {
            0 => {
                let f = run(&self.lips.0.blocks, &sample(&m_lips));
                let out = transform_landmarks(&self.lips.1.forward(&f), &m_lips);
                if let Ok(mut l) = lips.lock() {
                    *l = out;
                }
            }
            _ => {
                let f = run(&eyes[i - 1].0.blocks, &sample(mats[i - 1]));
                if let Ok(mut s) = stems[i - 1].lock() {
                    *s = Some(f);
                }
            }
        });
        let stems = stems.map(|s| s.into_inner().ok().flatten());
        let heads: [Mutex<Vec<f32>>; 4] = Default::default();
        crate::pool::run(4, &|i| {
            let (e, iris) = (i / 2, i % 2 == 1);
            if let Some(f) = &stems[e] {
                let tail = if iris { &eyes[e].2 } else { &eyes[e].1 };
                let out = transform_landmarks(&tail.forward(f), mats[e]);
                if let Ok(mut h) = heads[i].lock() {
                    *h = out;
                }
            }
        });
        let [left_eye, left_iris, right_eye, right_iris] =
            heads.map(|h| h.into_inner().unwrap_or_default());
        let lips = lips.into_inner().unwrap_or_default();
        MeshOutputs {
            mesh,
            lips,
            left_eye,
            right_eye,
            left_iris,
            right_iris,
            face_flag,
        }
    }
}

/// A row-major 3x3 f32 product, summed in index order (as the custom op's `Mat3`).
fn mat3_vec(m: &[f32; 9], v: [f32; 3]) -> [f32; 3] {
    std::array::from_fn(|r| {
        let mut s = 0.0f32;
        for (k, vk) in v.iter().enumerate() {
            s += m[r * 3 + k] * vk;
        }
        s
    })
}

/// `a * b` for row-major 4x4 f32 matrices, summed in index order (the custom op's `Mat4`).
fn mat4_mul(a: &[f32; 16], b: &[f32; 16]) -> [f32; 16] {
    std::array::from_fn(|i| {
        let (r, c) = (i / 4, i % 4);
        let mut s = 0.0f32;
        for k in 0..4 {
            s += a[r * 4 + k] * b[k * 4 + c];
        }
        s
    })
}

/// The `Landmarks2TransformMatrix` (v2) custom op: the 4x4 matrix that maps the 16x16 branch
/// grid onto the feature map, for a rectangle aligned with the line between the two
/// `rotation` points and 1.5 times the bounding box of `subset` in that frame. `landmarks`:
/// 468 x (x, y, z) in feature-map units.
pub fn landmarks_to_matrix(
    landmarks: &[f32],
    rotation: (usize, usize),
    subset: &[usize],
) -> [f32; 16] {
    let p = |i: usize| (landmarks[i * 3], landmarks[i * 3 + 1]);
    let (l, r) = (p(rotation.0), p(rotation.1));
    let rot = 0.0f32 - (r.1 - l.1).atan2(r.0 - l.0);
    let (c, s) = (rot.cos(), rot.sin());
    let t_rot = [c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0];
    let (ci, si) = ((-rot).cos(), (-rot).sin());
    let t_inv = [ci, -si, 0.0, si, ci, 0.0, 0.0, 0.0, 1.0];
    let rotated: Vec<[f32; 3]> = subset
        .iter()
        .map(|&i| mat3_vec(&t_rot, [p(i).0, p(i).1, 1.0]))
        .collect();
    let (mut max, mut min) = (rotated[0], rotated[0]);
    for q in &rotated[1..] {
        if max[0] < q[0] {
            max[0] = q[0];
        }
        if max[1] < q[1] {
            max[1] = q[1];
        }
        if min[0] > q[0] {
            min[0] = q[0];
        }
        if min[1] > q[1] {
            min[1] = q[1];
        }
    }
    let (cw, ch) = (max[0] - min[0], max[1] - min[1]);
    let mut centre = min;
    centre[0] += max[0];
    centre[1] += max[1];
    centre[0] /= 2.0;
    centre[1] /= 2.0;
    let centre = mat3_vec(&t_inv, centre);
    let out = BRANCH_SIZE as f32;
    let identity = [
        1., 0., 0., 0., 0., 1., 0., 0., 0., 0., 1., 0., 0., 0., 0., 1.,
    ];
    let shift = [
        1., 0., 0., centre[0], 0., 1., 0., centre[1], 0., 0., 1., 0., 0., 0., 0., 1.,
    ];
    let rr = -rot;
    let rotate = [
        rr.cos(),
        -rr.sin(),
        0.,
        0.,
        rr.sin(),
        rr.cos(),
        0.,
        0.,
        0.,
        0.,
        1.,
        0.,
        0.,
        0.,
        0.,
        1.,
    ];
    let (sx, sy) = (BRANCH_SCALE * cw / out, BRANCH_SCALE * ch / out);
    let scale = [
        sx, 0., 0., 0., 0., sy, 0., 0., 0., 0., 1., 0., 0., 0., 0., 1.,
    ];
    let half = -(out / 2.0);
    let shift2 = [
        1., 0., 0., half, 0., 1., 0., half, 0., 0., 1., 0., 0., 0., 0., 1.,
    ];
    let t = mat4_mul(&identity, &shift);
    let t = mat4_mul(&t, &rotate);
    let t = mat4_mul(&t, &scale);
    mat4_mul(&t, &shift2)
}

/// `((a0 b0 + a1 b1) + a2 b2) + a3 b3`, the custom ops' float4 dot product.
fn dot4(a: [f32; 4], b: [f32; 4]) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + a[3] * b[3]
}

/// The `TransformTensorBilinear` (v2) custom op: samples `x` at the matrix-mapped positions
/// of an `oh x ow` grid (pixel centres, align-corners corrected), bilinear, zero where the
/// position leaves the map.
pub fn transform_tensor_bilinear(x: &Nhwc, m: &[f32; 16], oh: usize, ow: usize) -> Nhwc {
    let mut xt = [m[0], m[1], m[2], m[3]];
    let mut yt = [m[4], m[5], m[6], m[7]];
    xt[3] += xt[0] * 0.5 + xt[1] * 0.5 - 0.5;
    yt[3] += yt[0] * 0.5 + yt[1] * 0.5 - 0.5;
    let mut out = Nhwc::zeros(oh, ow, x.c);
    let (ih, iw) = (x.h as f32, x.w as f32);
    for oy in 0..oh {
        for ox in 0..ow {
            let coord = [ox as f32, oy as f32, 0.0, 1.0];
            let (tx, ty) = (dot4(xt, coord), dot4(yt, coord));
            if tx < 0.0 || tx > iw - 1.0 || ty < 0.0 || ty > ih - 1.0 {
                continue;
            }
            let (fx, fy) = (tx.floor(), ty.floor());
            let (x0, y0) = (fx as isize, fy as isize);
            let read = |yy: isize, xx: isize, c: usize| {
                if yy < 0 || xx < 0 || yy >= x.h as isize || xx >= x.w as isize {
                    0.0
                } else {
                    x.data[(yy as usize * x.w + xx as usize) * x.c + c]
                }
            };
            let (rc, lc) = (tx - fx, ty - fy);
            let o = &mut out.data[(oy * ow + ox) * x.c..(oy * ow + ox + 1) * x.c];
            for (c, v) in o.iter_mut().enumerate() {
                let q11 = read(y0, x0, c);
                let q21 = read(y0, x0 + 1, c);
                let q12 = read(y0 + 1, x0, c);
                let q22 = read(y0 + 1, x0 + 1, c);
                let upper = (1.0 - rc) * q11 + rc * q21;
                let lower = (1.0 - rc) * q12 + rc * q22;
                *v = lc * lower + (1.0 - lc) * upper;
            }
        }
    }
    out
}

/// The `TransformLandmarks` (v2) custom op on 2-D points, with the branch matrix scaled by
/// [`LANDMARK_MATRIX_FACTORS`] first (the graph's MUL): branch outputs to 192-px crop units.
pub fn transform_landmarks(points: &[f32], m: &[f32; 16]) -> Vec<f32> {
    let s: [f32; 16] = std::array::from_fn(|i| m[i] * LANDMARK_MATRIX_FACTORS[i]);
    let (xt, yt) = ([s[0], s[1], s[2], s[3]], [s[4], s[5], s[6], s[7]]);
    points
        .chunks_exact(2)
        .flat_map(|p| {
            let v = [p[0], p[1], 0.0, 1.0];
            [dot4(xt, v), dot4(yt, v)]
        })
        .collect()
}
