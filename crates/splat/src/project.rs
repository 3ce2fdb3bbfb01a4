//! Per-Gaussian preprocessing (spec section 7): view transform, covariance from the
//! unnormalised quaternion, EWA projection with the 1.3 tan(fov) clamp and the 0.3 dilation,
//! conic, screen radius and tile rectangle; and its exact backward.

use crate::camera::Camera;
use crate::lanes::{Lanes, WIDTH};
use crate::real::Real;
use rayon::prelude::*;
use std::mem::MaybeUninit;

pub const TILE: usize = 16;
/// Gaussians at or nearer than this view depth are culled (the release's frustum test).
pub const NEAR_CULL: f64 = 0.2;
/// The EWA Jacobian is evaluated with x/z and y/z clamped to this multiple of tan(fov/2).
pub const FOV_CLAMP: f64 = 1.3;
/// Low-pass dilation added to both diagonal entries of the 2D covariance.
pub const DILATION: f64 = 0.3;

/// Camera constants in the kernel's float type.
#[derive(Debug, Clone, Copy)]
pub struct CamK<T> {
    pub rot: [[T; 3]; 3],
    pub trans: [T; 3],
    pub focal: T,
    pub fx: T,
    pub fy: T,
    pub w: T,
    pub h: T,
    pub lim: T,
    pub width: usize,
    pub height: usize,
    pub grid_x: usize,
    pub grid_y: usize,
}

impl<T: Real> CamK<T> {
    pub fn new(cam: &Camera) -> Self {
        let (fx, fy) = cam.focal_px();
        let mut rot = [[T::ZERO; 3]; 3];
        for (i, row) in rot.iter_mut().enumerate() {
            for (j, v) in row.iter_mut().enumerate() {
                *v = T::lit(cam.rot[i][j]);
            }
        }
        Self {
            rot,
            trans: cam.trans.map(T::lit),
            focal: T::lit(cam.focal),
            fx: T::lit(fx),
            fy: T::lit(fy),
            w: T::lit(cam.width as f64),
            h: T::lit(cam.height as f64),
            // tan(fov/2) = 1 / focal on both axes.
            lim: T::lit(FOV_CLAMP / cam.focal),
            width: cam.width,
            height: cam.height,
            grid_x: cam.width.div_ceil(TILE),
            grid_y: cam.height.div_ceil(TILE),
        }
    }

    #[inline(always)]
    fn view(&self, p: [T; 3]) -> [T; 3] {
        let r = &self.rot;
        [
            r[0][0] * p[0] + r[0][1] * p[1] + r[0][2] * p[2] + self.trans[0],
            r[1][0] * p[0] + r[1][1] * p[1] + r[1][2] * p[2] + self.trans[1],
            r[2][0] * p[0] + r[2][1] * p[1] + r[2][2] * p[2] + self.trans[2],
        ]
    }
}

/// One projected Gaussian as the rasterizer reads it: 32 bytes in f32, aligned, so a read
/// never straddles two cache lines (its depth, only needed for sorting, lives apart).
#[derive(Debug, Clone, Copy, Default)]
#[repr(C, align(32))]
pub struct Splat2D<T> {
    /// Pixel-space centre.
    pub mx: T,
    pub my: T,
    /// The conic (inverse 2D covariance) A, B, C as the power uses it: -A/2, -B, -C/2
    /// (`power = dx (qa dx + qb dy) + qc dy^2` with d = mean - pixel; [`Splat2D::conic`]
    /// undoes the exact scaling).
    pub qa: T,
    pub qb: T,
    pub qc: T,
    pub opacity: T,
    /// Half-height of the rows the Gaussian can reach: `sqrt(cut * cov_yy)`, where `cut`
    /// bounds `A dx^2 + 2 B dx dy + C dy^2` inside which alpha can reach 1/255 (slightly
    /// inflated so rounding never excludes a pixel), and the ellipse `d^T Q d <= cut` reaches
    /// that far above and below its centre. Negative when the Gaussian can never reach 1/255.
    pub ey: T,
    /// Half-width of the columns it can reach, `sqrt(cut * cov_xx)` (negative likewise).
    pub ex: T,
}

impl<T: Real> Splat2D<T> {
    /// The conic entries A, B, C.
    #[inline(always)]
    pub fn conic(&self) -> (T, T, T) {
        let m2 = T::lit(-2.0);
        (m2 * self.qa, -self.qb, m2 * self.qc)
    }
}

/// Projected Gaussians. A culled Gaussian has `radius == 0` and an empty rect.
#[derive(Debug, Clone, Default)]
pub struct Projected<T> {
    pub g: Vec<Splat2D<T>>,
    /// View depth per Gaussian (0 when culled).
    pub depth: Vec<T>,
    pub radius: Vec<u32>,
    /// Tile rectangle [x0, x1) x [y0, y1).
    pub rect: Vec<[u16; 4]>,
}

/// The alpha >= 1/255 region is inflated by this factor (and [`CUT_PAD`]) before it bounds the
/// pixels visited, far more than f32 rounding of the conic quadratic can move its edge.
const CUT_INFLATE: f64 = 1.02;
const CUT_PAD: f64 = 0.05;

/// Quaternion (r, x, y, z) to the 3x3 matrix of spec section 7, without normalisation.
#[inline(always)]
pub fn quat_to_mat<T: Real>(q: [T; 4]) -> [[T; 3]; 3] {
    let [r, x, y, z] = q;
    let one = T::ONE;
    let two = T::lit(2.0);
    [
        [
            one - two * (y * y + z * z),
            two * (x * y - r * z),
            two * (x * z + r * y),
        ],
        [
            two * (x * y + r * z),
            one - two * (x * x + z * z),
            two * (y * z - r * x),
        ],
        [
            two * (x * z - r * y),
            two * (y * z + r * x),
            one - two * (x * x + y * y),
        ],
    ]
}

/// Everything the forward computes for one Gaussian that the backward needs again.
struct Geo<T> {
    t: [T; 3],
    rq: [[T; 3]; 3],
    /// M = Rq diag(s)
    m: [[T; 3]; 3],
    /// Sigma = M M^T
    sigma: [[T; 3]; 3],
    /// Clamped tan ratios and whether each was clamped (+1 / -1) or not (0).
    clamp: [i8; 2],
    /// P = J W (2x3)
    p: [[T; 3]; 2],
    a: T,
    b: T,
    c: T,
}

#[inline(always)]
fn geometry<T: Real>(cam: &CamK<T>, mean: [T; 3], scale: [T; 3], quat: [T; 4]) -> Option<Geo<T>> {
    let t = cam.view(mean);
    if !(t[2] > T::lit(NEAR_CULL)) {
        return None;
    }
    let rq = quat_to_mat(quat);
    let mut m = [[T::ZERO; 3]; 3];
    for i in 0..3 {
        for k in 0..3 {
            m[i][k] = rq[i][k] * scale[k];
        }
    }
    let mut sigma = [[T::ZERO; 3]; 3];
    for i in 0..3 {
        for k in 0..3 {
            sigma[i][k] = m[i][0] * m[k][0] + m[i][1] * m[k][1] + m[i][2] * m[k][2];
        }
    }
    let tz = t[2];
    let mut clamp = [0i8; 2];
    let mut tc = [T::ZERO; 2];
    for a in 0..2 {
        let r = t[a] / tz;
        let rc = if r < -cam.lim {
            clamp[a] = -1;
            -cam.lim
        } else if r > cam.lim {
            clamp[a] = 1;
            cam.lim
        } else {
            r
        };
        tc[a] = rc * tz;
    }
    let tz2 = tz * tz;
    let j = [
        [cam.fx / tz, T::ZERO, -(cam.fx * tc[0]) / tz2],
        [T::ZERO, cam.fy / tz, -(cam.fy * tc[1]) / tz2],
    ];
    let w = &cam.rot;
    let mut p = [[T::ZERO; 3]; 2];
    for i in 0..2 {
        for k in 0..3 {
            p[i][k] = j[i][0] * w[0][k] + j[i][1] * w[1][k] + j[i][2] * w[2][k];
        }
    }
    // cov2 = P Sigma P^T
    let mut ps = [[T::ZERO; 3]; 2];
    for i in 0..2 {
        for k in 0..3 {
            ps[i][k] = p[i][0] * sigma[0][k] + p[i][1] * sigma[1][k] + p[i][2] * sigma[2][k];
        }
    }
    let dot = |u: &[T; 3], v: &[T; 3]| u[0] * v[0] + u[1] * v[1] + u[2] * v[2];
    let a = dot(&ps[0], &p[0]) + T::lit(DILATION);
    let b = dot(&ps[0], &p[1]);
    let c = dot(&ps[1], &p[1]) + T::lit(DILATION);
    Some(Geo {
        t,
        rq,
        m,
        sigma,
        clamp,
        p,
        a,
        b,
        c,
    })
}

/// Pixel-space centre: `ndc = focal * x / z`, `pixel = ((ndc + 1) * size - 1) / 2`.
#[inline(always)]
fn mean2d<T: Real>(cam: &CamK<T>, t: &[T; 3]) -> (T, T) {
    let half = T::lit(0.5);
    let ndc_x = cam.focal * (t[0] / t[2]);
    let ndc_y = cam.focal * (t[1] / t[2]);
    (
        ((ndc_x + T::ONE) * cam.w - T::ONE) * half,
        ((ndc_y + T::ONE) * cam.h - T::ONE) * half,
    )
}

/// Raw inputs per Gaussian: mean (3), opacity (1), scale (3), quaternion (4). One
/// (Gaussian set, camera) pair's `geom` holds them as four blocks, `[means (3N) | opacities
/// (N) | scales (3N) | quaternions (4N)]`: packing the four input tensors that way is four
/// block copies, where interleaving them row by row cost 2 ms a frame.
pub const GEOM: usize = 11;

/// A view of `geom` (see [`GEOM`]) or of a range of its Gaussians.
#[derive(Clone, Copy, Debug)]
pub struct GeomIn<'a, T> {
    pub means: &'a [T],
    pub opacities: &'a [T],
    pub scales: &'a [T],
    pub rotations: &'a [T],
}

impl<'a, T: Copy> GeomIn<'a, T> {
    /// Splits `geom` into its four blocks (its length must be a multiple of [`GEOM`]).
    pub fn split(geom: &'a [T]) -> Self {
        let n = geom.len() / GEOM;
        let (means, rest) = geom.split_at(3 * n);
        let (opacities, rest) = rest.split_at(n);
        let (scales, rotations) = rest.split_at(3 * n);
        Self {
            means,
            opacities,
            scales,
            rotations: &rotations[..4 * n],
        }
    }

    pub fn len(&self) -> usize {
        self.opacities.len()
    }

    pub fn is_empty(&self) -> bool {
        self.opacities.is_empty()
    }

    /// Gaussians `lo..hi`.
    pub fn range(&self, lo: usize, hi: usize) -> Self {
        Self {
            means: &self.means[3 * lo..3 * hi],
            opacities: &self.opacities[lo..hi],
            scales: &self.scales[3 * lo..3 * hi],
            rotations: &self.rotations[4 * lo..4 * hi],
        }
    }

    /// Gaussian `i` as `[mean, opacity, scale, quaternion]`.
    #[inline(always)]
    pub fn row(&self, i: usize) -> [T; GEOM] {
        let (m, s, q) = (&self.means, &self.scales, &self.rotations);
        [
            m[3 * i],
            m[3 * i + 1],
            m[3 * i + 2],
            self.opacities[i],
            s[3 * i],
            s[3 * i + 1],
            s[3 * i + 2],
            q[4 * i],
            q[4 * i + 1],
            q[4 * i + 2],
            q[4 * i + 3],
        ]
    }
}

/// The mutable counterpart of [`GeomIn`], for gradients.
pub struct GeomOut<'a, T> {
    pub means: &'a mut [T],
    pub opacities: &'a mut [T],
    pub scales: &'a mut [T],
    pub rotations: &'a mut [T],
}

impl<'a, T: Copy> GeomOut<'a, T> {
    pub fn split(geom: &'a mut [T]) -> Self {
        let n = geom.len() / GEOM;
        let (means, rest) = geom.split_at_mut(3 * n);
        let (opacities, rest) = rest.split_at_mut(n);
        let (scales, rotations) = rest.split_at_mut(3 * n);
        Self {
            means,
            opacities,
            scales,
            rotations: &mut rotations[..4 * n],
        }
    }

    /// Writes Gaussian `i` from `[mean, opacity, scale, quaternion]`.
    #[inline(always)]
    pub fn put(&mut self, i: usize, v: [T; GEOM]) {
        self.means[3 * i..3 * i + 3].copy_from_slice(&v[0..3]);
        self.opacities[i] = v[3];
        self.scales[3 * i..3 * i + 3].copy_from_slice(&v[4..7]);
        self.rotations[4 * i..4 * i + 4].copy_from_slice(&v[7..11]);
    }
}

/// Projects all Gaussians in parallel. Results depend only on each Gaussian, so they are
/// identical for any thread count.
pub fn project<T: Real>(cam: &CamK<T>, geom: &[T]) -> Projected<T> {
    let geom = GeomIn::split(geom);
    let n = geom.len();
    // Every element is written below (each block writes all of its Gaussians), so the
    // outputs start uninitialised rather than being cleared first.
    let mut g: Vec<Splat2D<T>> = Vec::with_capacity(n);
    let mut depth: Vec<T> = Vec::with_capacity(n);
    let mut radius: Vec<u32> = Vec::with_capacity(n);
    let mut rect: Vec<[u16; 4]> = Vec::with_capacity(n);
    let avx2 = has_avx2();
    #[cfg(target_arch = "x86_64")]
    let cam32 = as_f32_cam(cam).filter(|_| has_avx512());
    g.spare_capacity_mut()[..n]
        .par_chunks_mut(PROJECT_BLOCK)
        .zip(radius.spare_capacity_mut()[..n].par_chunks_mut(PROJECT_BLOCK))
        .zip(rect.spare_capacity_mut()[..n].par_chunks_mut(PROJECT_BLOCK))
        .zip(depth.spare_capacity_mut()[..n].par_chunks_mut(PROJECT_BLOCK))
        .enumerate()
        .for_each(|(ci, (((s, r), rc), d))| {
            let lo = ci * PROJECT_BLOCK;
            let gm = geom.range(lo, lo + s.len());
            #[cfg(target_arch = "x86_64")]
            if let Some(cam32) = cam32 {
                // SAFETY: T is f32 (as_f32_cam), so the slices are f32 slices of the same
                // lengths; the CPU has AVX-512F (has_avx512).
                return unsafe {
                    let f32s =
                        |v: &[T]| std::slice::from_raw_parts(v.as_ptr().cast::<f32>(), v.len());
                    let gm32 = GeomIn {
                        means: f32s(gm.means),
                        opacities: f32s(gm.opacities),
                        scales: f32s(gm.scales),
                        rotations: f32s(gm.rotations),
                    };
                    project_block_avx512(
                        cam32,
                        gm32,
                        std::slice::from_raw_parts_mut(
                            s.as_mut_ptr().cast::<MaybeUninit<Splat2D<f32>>>(),
                            s.len(),
                        ),
                        std::slice::from_raw_parts_mut(
                            d.as_mut_ptr().cast::<MaybeUninit<f32>>(),
                            d.len(),
                        ),
                        r,
                        rc,
                    )
                };
            }
            #[cfg(target_arch = "x86_64")]
            if avx2 {
                // SAFETY: the CPU supports AVX2 (has_avx2).
                return unsafe { project_block_avx2(cam, gm, s, d, r, rc) };
            }
            project_block(cam, gm, s, d, r, rc)
        });
    // SAFETY: the loop above wrote all n elements of each (see the block functions).
    unsafe {
        g.set_len(n);
        depth.set_len(n);
        radius.set_len(n);
        rect.set_len(n);
    }
    Projected {
        g,
        depth,
        radius,
        rect,
    }
}

/// Backward of [`project`] for all Gaussians: `screen` holds each Gaussian's
/// [`crate::params::SCREEN`] screen-space gradients (mean x, mean y, conic A, B, C, opacity),
/// `out` receives dL/dgeom (`GEOM` per Gaussian); culled Gaussians are left untouched.
pub fn project_backward<T: Real>(
    cam: &CamK<T>,
    geom: &[T],
    screen: &[T],
    radius: &[u32],
    out: &mut [T],
) {
    const S: usize = crate::params::SCREEN;
    const B: usize = PROJECT_BLOCK;
    let avx2 = has_avx2();
    let geom = GeomIn::split(geom);
    let out = GeomOut::split(out);
    out.means
        .par_chunks_mut(3 * B)
        .zip(out.opacities.par_chunks_mut(B))
        .zip(out.scales.par_chunks_mut(3 * B))
        .zip(out.rotations.par_chunks_mut(4 * B))
        .zip(screen.par_chunks(B * S))
        .zip(radius.par_chunks(B))
        .enumerate()
        .for_each(
            |(ci, (((((means, opacities), scales), rotations), s), r))| {
                let g = geom.range(ci * B, ci * B + r.len());
                let o = GeomOut {
                    means,
                    opacities,
                    scales,
                    rotations,
                };
                #[cfg(target_arch = "x86_64")]
                if avx2 {
                    // SAFETY: the CPU supports AVX2 (has_avx2).
                    return unsafe { project_backward_block_avx2(cam, g, s, r, o) };
                }
                project_backward_block(cam, g, s, r, o)
            },
        );
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn project_backward_block_avx2<T: Real>(
    cam: &CamK<T>,
    geom: GeomIn<T>,
    screen: &[T],
    radius: &[u32],
    out: GeomOut<T>,
) {
    project_backward_block(cam, geom, screen, radius, out)
}

#[inline(always)]
fn project_backward_block<T: Real>(
    cam: &CamK<T>,
    geom: GeomIn<T>,
    screen: &[T],
    radius: &[u32],
    mut out: GeomOut<T>,
) {
    for (i, (s, &r)) in screen.chunks(crate::params::SCREEN).zip(radius).enumerate() {
        if r == 0 {
            continue;
        }
        let d = Grad2D {
            mx: s[0],
            my: s[1],
            ca: s[2],
            cb: s[3],
            cc: s[4],
            opacity: s[5],
        };
        let mut o = [T::ZERO; GEOM];
        project_backward_one(cam, &geom.row(i), &d, &mut o);
        out.put(i, o);
    }
}

/// Gaussians per parallel task of the projection.
const PROJECT_BLOCK: usize = 2048;

fn has_avx2() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx2")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// The camera as `CamK<f32>` when `T` is `f32`.
#[cfg(target_arch = "x86_64")]
fn as_f32_cam<T: Real>(cam: &CamK<T>) -> Option<&CamK<f32>> {
    (std::any::TypeId::of::<T>() == std::any::TypeId::of::<f32>())
        // SAFETY: T and f32 are the same type, so the two are the same struct.
        .then(|| unsafe { &*(cam as *const CamK<T>).cast::<CamK<f32>>() })
}

/// Whether the AVX-512 projection runs (not under `GAGAVATAR_NO_AVX512`, like the raster).
#[cfg(target_arch = "x86_64")]
fn has_avx512() -> bool {
    std::arch::is_x86_feature_detected!("avx512f") && !crate::lanes::simd_disabled()
}

/// Sixteen Gaussians at a time in AVX-512 lanes ([`project_lanes`]), the rest one by one.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx2,fma")]
unsafe fn project_block_avx512(
    cam: &CamK<f32>,
    geom: GeomIn<f32>,
    g: &mut [MaybeUninit<Splat2D<f32>>],
    depth: &mut [MaybeUninit<f32>],
    radius: &mut [MaybeUninit<u32>],
    rect: &mut [MaybeUninit<[u16; 4]>],
) {
    let whole = g.len() / WIDTH * WIDTH;
    for (j, (((s, d), r), rc)) in g[..whole]
        .chunks_exact_mut(WIDTH)
        .zip(depth[..whole].chunks_exact_mut(WIDTH))
        .zip(radius[..whole].chunks_exact_mut(WIDTH))
        .zip(rect[..whole].chunks_exact_mut(WIDTH))
        .enumerate()
    {
        let gm = geom.range(j * WIDTH, (j + 1) * WIDTH);
        project_lanes::<f32, crate::lanes::Z16>(cam, gm, s, d, r, rc);
    }
    project_block(
        cam,
        geom.range(whole, geom.len()),
        &mut g[whole..],
        &mut depth[whole..],
        &mut radius[whole..],
        &mut rect[whole..],
    );
}

/// [`project_block`] compiled with AVX2 (and so SSE4.1): floor and ceil become single
/// instructions instead of libm calls (same results), about half the projection's time.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn project_block_avx2<T: Real>(
    cam: &CamK<T>,
    geom: GeomIn<T>,
    g: &mut [MaybeUninit<Splat2D<T>>],
    depth: &mut [MaybeUninit<T>],
    radius: &mut [MaybeUninit<u32>],
    rect: &mut [MaybeUninit<[u16; 4]>],
) {
    project_block(cam, geom, g, depth, radius, rect)
}

#[inline(always)]
fn project_block<T: Real>(
    cam: &CamK<T>,
    geom: GeomIn<T>,
    g: &mut [MaybeUninit<Splat2D<T>>],
    depth: &mut [MaybeUninit<T>],
    radius: &mut [MaybeUninit<u32>],
    rect: &mut [MaybeUninit<[u16; 4]>],
) {
    for (i, (((s, d), r), rc)) in g
        .iter_mut()
        .zip(depth.iter_mut())
        .zip(radius.iter_mut())
        .zip(rect.iter_mut())
        .enumerate()
    {
        let (si, di, ri, rci) = project_one(cam, &geom.row(i));
        s.write(si);
        d.write(di);
        r.write(ri);
        rc.write(rci);
    }
}

/// [`project_one`] of `WIDTH` Gaussians at once, one per lane, every operation the same and in
/// the same order, so the results are bit-identical, except the block-visiting bounds `ex`,
/// `ey`, whose log is [`Lanes::ln_bound`] in f32: it is inflated far beyond
/// that difference, so the same pixels are visited and the images do not change.
#[inline(always)]
#[cfg_attr(not(target_arch = "x86_64"), allow(dead_code))]
fn project_lanes<T: Real, L: Lanes<T>>(
    cam: &CamK<T>,
    geom: GeomIn<T>,
    out: &mut [MaybeUninit<Splat2D<T>>],
    depth: &mut [MaybeUninit<T>],
    radius: &mut [MaybeUninit<u32>],
    rect: &mut [MaybeUninit<[u16; 4]>],
) {
    assert!(geom.len() == WIDTH && out.len() == WIDTH);
    assert!(radius.len() == WIDTH && rect.len() == WIDTH);
    let mut cols = [[T::ZERO; WIDTH]; GEOM];
    for i in 0..WIDTH {
        let row = geom.row(i);
        for (k, col) in cols.iter_mut().enumerate() {
            col[i] = row[k];
        }
    }
    // (Plain loops and no closures: closures would not inherit the kernel's target features.)
    let mut v = [L::zero(); GEOM];
    for k in 0..GEOM {
        v[k] = L::from_array(cols[k]);
    }
    let s = L::splat;
    // geometry()
    let zero = L::zero();
    let p = [v[0], v[1], v[2]];
    let r = &cam.rot;
    let mut t = [zero; 3];
    for i in 0..3 {
        t[i] = s(r[i][0])
            .mul(p[0])
            .add(s(r[i][1]).mul(p[1]))
            .add(s(r[i][2]).mul(p[2]))
            .add(s(cam.trans[i]));
    }
    let near = t[2].gt(s(T::lit(NEAR_CULL)));
    let (qr, qx, qy, qz) = (v[7], v[8], v[9], v[10]);
    let (one, two) = (s(T::ONE), s(T::lit(2.0)));
    let rq = [
        [
            one.sub(two.mul(qy.mul(qy).add(qz.mul(qz)))),
            two.mul(qx.mul(qy).sub(qr.mul(qz))),
            two.mul(qx.mul(qz).add(qr.mul(qy))),
        ],
        [
            two.mul(qx.mul(qy).add(qr.mul(qz))),
            one.sub(two.mul(qx.mul(qx).add(qz.mul(qz)))),
            two.mul(qy.mul(qz).sub(qr.mul(qx))),
        ],
        [
            two.mul(qx.mul(qz).sub(qr.mul(qy))),
            two.mul(qy.mul(qz).add(qr.mul(qx))),
            one.sub(two.mul(qx.mul(qx).add(qy.mul(qy)))),
        ],
    ];
    let scale = [v[4], v[5], v[6]];
    let mut m = [[zero; 3]; 3];
    for i in 0..3 {
        for k in 0..3 {
            m[i][k] = rq[i][k].mul(scale[k]);
        }
    }
    let mut sigma = [[zero; 3]; 3];
    for i in 0..3 {
        for k in 0..3 {
            sigma[i][k] = m[i][0]
                .mul(m[k][0])
                .add(m[i][1].mul(m[k][1]))
                .add(m[i][2].mul(m[k][2]));
        }
    }
    let tz = t[2];
    let mut tc = [zero; 2];
    for a in 0..2 {
        let ratio = t[a].div(tz);
        let (lo, hi) = (s(-cam.lim), s(cam.lim));
        let rc = L::select(ratio.lt(lo), lo, L::select(ratio.gt(hi), hi, ratio));
        tc[a] = rc.mul(tz);
    }
    let tz2 = tz.mul(tz);
    let j = [
        [s(cam.fx).div(tz), zero, s(cam.fx).mul(tc[0]).neg().div(tz2)],
        [zero, s(cam.fy).div(tz), s(cam.fy).mul(tc[1]).neg().div(tz2)],
    ];
    let w = &cam.rot;
    let mut pj = [[zero; 3]; 2];
    let mut ps = [[zero; 3]; 2];
    for i in 0..2 {
        for k in 0..3 {
            pj[i][k] = j[i][0]
                .mul(s(w[0][k]))
                .add(j[i][1].mul(s(w[1][k])))
                .add(j[i][2].mul(s(w[2][k])));
        }
    }
    for i in 0..2 {
        for k in 0..3 {
            ps[i][k] = pj[i][0]
                .mul(sigma[0][k])
                .add(pj[i][1].mul(sigma[1][k]))
                .add(pj[i][2].mul(sigma[2][k]));
        }
    }
    let mut abc = [zero; 3];
    for (o, (u, v)) in abc.iter_mut().zip([(0, 0), (0, 1), (1, 1)]) {
        let (u, v) = (&ps[u], &pj[v]);
        *o = u[0].mul(v[0]).add(u[1].mul(v[1])).add(u[2].mul(v[2]));
    }
    let dil = s(T::lit(DILATION));
    let (a, b, c) = (abc[0].add(dil), abc[1], abc[2].add(dil));
    // project_one()
    let det = a.mul(c).sub(b.mul(b));
    let singular = det.eq(zero);
    let (ca, cb, cc) = (c.div(det), b.neg().div(det), a.div(det));
    let half = s(T::lit(0.5));
    let mid = half.mul(a.add(c));
    let lambda = mid.add(mid.mul(mid).sub(det).max(s(T::lit(0.1))).sqrt());
    let radius_f = s(T::lit(3.0)).mul(lambda.sqrt()).ceil();
    let ndc_x = s(cam.focal).mul(t[0].div(t[2]));
    let ndc_y = s(cam.focal).mul(t[1].div(t[2]));
    let mx = ndc_x.add(one).mul(s(cam.w)).sub(one).mul(half);
    let my = ndc_y.add(one).mul(s(cam.h)).sub(one).mul(half);
    let opacity = v[3];
    let faint = opacity.lt(s(T::lit(crate::params::MIN_ALPHA)));
    let ln = s(T::lit(255.0)).mul(opacity).ln_bound().max(zero);
    let cut = s(T::lit(2.0))
        .mul(ln)
        .mul(s(T::lit(CUT_INFLATE)))
        .add(s(T::lit(CUT_PAD)));
    let never = s(T::lit(-1.0));
    let ey = L::select(faint, never, cut.mul(c).max(zero).sqrt());
    let ex = L::select(faint, never, cut.mul(a).max(zero).sqrt());
    let keep = near & !singular;
    let neg_half = s(T::lit(-0.5));
    let (qa, qb, qc) = (neg_half.mul(ca), cb.neg(), neg_half.mul(cc));
    let (mx, my, qa, qb, qc) = (
        mx.to_array(),
        my.to_array(),
        qa.to_array(),
        qb.to_array(),
        qc.to_array(),
    );
    let (opacity, dep) = (opacity.to_array(), tz.to_array());
    let (ey, ex, radius_f) = (ey.to_array(), ex.to_array(), radius_f.to_array());
    for i in 0..WIDTH {
        let culled = (Splat2D::default(), T::ZERO, 0, [0; 4]);
        let (oi, di, ri, rci) = if keep >> i & 1 == 0 {
            culled
        } else {
            let rad = radius_f[i].as_f64();
            let (x0, x1) = tile_span(mx[i].as_f64(), rad, cam.grid_x);
            let (y0, y1) = tile_span(my[i].as_f64(), rad, cam.grid_y);
            if (x1 - x0) * (y1 - y0) == 0 {
                culled
            } else {
                let g = Splat2D {
                    mx: mx[i],
                    my: my[i],
                    qa: qa[i],
                    qb: qb[i],
                    qc: qc[i],
                    opacity: opacity[i],
                    ey: ey[i],
                    ex: ex[i],
                };
                let rc = [x0 as u16, x1 as u16, y0 as u16, y1 as u16];
                (g, dep[i], rad as u32, rc)
            }
        };
        out[i].write(oi);
        depth[i].write(di);
        radius[i].write(ri);
        rect[i].write(rci);
    }
}

/// Tiles `[lo, hi)` along one axis (of `grid`) touched by a splat of `radius` pixels around
/// `centre`. The release truncates toward zero and clamps to [0, grid]; for clamped results
/// this equals floor.
#[inline(always)]
fn tile_span(centre: f64, radius: f64, grid: usize) -> (usize, usize) {
    let lo = ((centre - radius) / TILE as f64).floor();
    let hi = ((centre + radius + (TILE - 1) as f64) / TILE as f64).floor();
    let clampi = |v: f64| -> usize { v.clamp(0.0, grid as f64) as usize };
    (clampi(lo), clampi(hi))
}

#[inline(always)]
fn project_one<T: Real>(cam: &CamK<T>, g: &[T]) -> (Splat2D<T>, T, u32, [u16; 4]) {
    let culled = (Splat2D::default(), T::ZERO, 0, [0; 4]);
    let mean = [g[0], g[1], g[2]];
    let opacity = g[3];
    let scale = [g[4], g[5], g[6]];
    let quat = [g[7], g[8], g[9], g[10]];
    let Some(geo) = geometry(cam, mean, scale, quat) else {
        return culled;
    };
    let (a, b, c) = (geo.a, geo.b, geo.c);
    let det = a * c - b * b;
    if det == T::ZERO {
        return culled;
    }
    let (ca, cb, cc) = (c / det, -b / det, a / det);
    let half = T::lit(0.5);
    let mid = half * (a + c);
    let lambda = mid + (mid * mid - det).fmax(T::lit(0.1)).sqrt();
    let radius_f = (T::lit(3.0) * lambda.sqrt()).ceil();
    let (mx, my) = mean2d(cam, &geo.t);
    let radius = radius_f.as_f64();
    let (x0, x1) = tile_span(mx.as_f64(), radius, cam.grid_x);
    let (y0, y1) = tile_span(my.as_f64(), radius, cam.grid_y);
    if (x1 - x0) * (y1 - y0) == 0 {
        return culled;
    }
    // alpha >= 1/255 needs o exp(power) >= 1/255, i.e. d^T Q d <= 2 ln(255 o).
    let o = opacity.as_f64();
    let cut = if opacity < T::lit(crate::params::MIN_ALPHA) {
        -1.0
    } else {
        2.0 * (255.0 * o).ln().max(0.0) * CUT_INFLATE + CUT_PAD
    };
    let reach = |cov: T| {
        if cut > 0.0 {
            (cut * cov.as_f64()).max(0.0).sqrt()
        } else {
            -1.0
        }
    };
    (
        Splat2D {
            mx,
            my,
            qa: T::lit(-0.5) * ca,
            qb: -cb,
            qc: T::lit(-0.5) * cc,
            opacity,
            ey: T::lit(reach(c)),
            ex: T::lit(reach(a)),
        },
        geo.t[2],
        radius as u32,
        [x0 as u16, x1 as u16, y0 as u16, y1 as u16],
    )
}

/// Gradients of the loss w.r.t. the per-Gaussian screen-space quantities.
#[derive(Debug, Clone, Copy, Default)]
pub struct Grad2D<T> {
    pub mx: T,
    pub my: T,
    pub ca: T,
    pub cb: T,
    pub cc: T,
    pub opacity: T,
}

/// Chain rule from screen space back to `[mean, opacity, scale, quat]` for one Gaussian, exact
/// for the forward above (including the zero gradient of clamped tan ratios).
pub fn project_backward_one<T: Real>(cam: &CamK<T>, g: &[T], d: &Grad2D<T>, out: &mut [T]) {
    let mean = [g[0], g[1], g[2]];
    let scale = [g[4], g[5], g[6]];
    let quat = [g[7], g[8], g[9], g[10]];
    out.iter_mut().for_each(|v| *v = T::ZERO);
    let Some(geo) = geometry(cam, mean, scale, quat) else {
        return;
    };
    out[3] = d.opacity;
    let (a, b, c) = (geo.a, geo.b, geo.c);
    let det = a * c - b * b;
    let q = [[c / det, -b / det], [-b / det, a / det]];
    let half = T::lit(0.5);
    let gq = [[d.ca, half * d.cb], [half * d.cb, d.cc]];
    // dL/dS2 = -Q G_Q Q (Q symmetric)
    let mut qg = [[T::ZERO; 2]; 2];
    for i in 0..2 {
        for k in 0..2 {
            qg[i][k] = q[i][0] * gq[0][k] + q[i][1] * gq[1][k];
        }
    }
    let mut gs = [[T::ZERO; 2]; 2];
    for i in 0..2 {
        for k in 0..2 {
            gs[i][k] = -(qg[i][0] * q[0][k] + qg[i][1] * q[1][k]);
        }
    }
    // cov2 = P Sigma P^T: dL/dSigma = P^T G P, dL/dP = 2 G P Sigma (G, Sigma symmetric).
    let p = &geo.p;
    let mut gp = [[T::ZERO; 3]; 2]; // G P
    for i in 0..2 {
        for k in 0..3 {
            gp[i][k] = gs[i][0] * p[0][k] + gs[i][1] * p[1][k];
        }
    }
    let mut gsig = [[T::ZERO; 3]; 3];
    for i in 0..3 {
        for k in 0..3 {
            gsig[i][k] = p[0][i] * gp[0][k] + p[1][i] * gp[1][k];
        }
    }
    let two = T::lit(2.0);
    let mut dp = [[T::ZERO; 3]; 2];
    for i in 0..2 {
        for k in 0..3 {
            dp[i][k] = two
                * (gp[i][0] * geo.sigma[0][k]
                    + gp[i][1] * geo.sigma[1][k]
                    + gp[i][2] * geo.sigma[2][k]);
        }
    }
    // P = J W  =>  dL/dJ = dL/dP W^T
    let w = &cam.rot;
    let mut dj = [[T::ZERO; 3]; 2];
    for i in 0..2 {
        for k in 0..3 {
            dj[i][k] = dp[i][0] * w[k][0] + dp[i][1] * w[k][1] + dp[i][2] * w[k][2];
        }
    }
    let t = geo.t;
    let tz = t[2];
    let tz2 = tz * tz;
    let tz3 = tz2 * tz;
    let mut dt = [T::ZERO; 3];
    // J00 = fx/z, J11 = fy/z
    dt[2] -= dj[0][0] * cam.fx / tz2;
    dt[2] -= dj[1][1] * cam.fy / tz2;
    // J02 = -fx tx/z^2 (free) or -fx (+-lim)/z (clamped); likewise J12.
    for (axis, f) in [(0usize, cam.fx), (1usize, cam.fy)] {
        let djx = dj[axis][2];
        match geo.clamp[axis] {
            0 => {
                dt[axis] -= djx * f / tz2;
                dt[2] += djx * two * f * t[axis] / tz3;
            }
            s => {
                let lim = if s > 0 { cam.lim } else { -cam.lim };
                dt[2] += djx * f * lim / tz2;
            }
        }
    }
    // Mean in pixels: px = fx x/z + const.
    dt[0] += d.mx * cam.fx / tz;
    dt[1] += d.my * cam.fy / tz;
    dt[2] -= (d.mx * cam.fx * t[0] + d.my * cam.fy * t[1]) / tz2;
    // t = W p + trans  =>  dL/dp = W^T dL/dt
    for k in 0..3 {
        out[k] = w[0][k] * dt[0] + w[1][k] * dt[1] + w[2][k] * dt[2];
    }
    // Sigma = M M^T, M = Rq diag(s)  =>  dL/dM = 2 G_Sigma M
    let m = &geo.m;
    let mut dm = [[T::ZERO; 3]; 3];
    for i in 0..3 {
        for k in 0..3 {
            dm[i][k] = two * (gsig[i][0] * m[0][k] + gsig[i][1] * m[1][k] + gsig[i][2] * m[2][k]);
        }
    }
    let rq = &geo.rq;
    let mut dr = [[T::ZERO; 3]; 3];
    for k in 0..3 {
        out[4 + k] = dm[0][k] * rq[0][k] + dm[1][k] * rq[1][k] + dm[2][k] * rq[2][k];
        for i in 0..3 {
            dr[i][k] = dm[i][k] * scale[k];
        }
    }
    let [r, x, y, z] = quat;
    let four = T::lit(4.0);
    // Derivatives of each rotation entry w.r.t. (r, x, y, z).
    let dqr = two
        * (-z * dr[0][1] + y * dr[0][2] + z * dr[1][0] - x * dr[1][2] - y * dr[2][0]
            + x * dr[2][1]);
    let dqx = two
        * (y * dr[0][1] + z * dr[0][2] + y * dr[1][0] - r * dr[1][2] + z * dr[2][0] + r * dr[2][1])
        - four * x * (dr[1][1] + dr[2][2]);
    let dqy = two
        * (x * dr[0][1] + r * dr[0][2] + x * dr[1][0] + z * dr[1][2] - r * dr[2][0] + z * dr[2][1])
        - four * y * (dr[0][0] + dr[2][2]);
    let dqz = two
        * (-r * dr[0][1]
            + x * dr[0][2]
            + r * dr[1][0]
            + y * dr[1][2]
            + x * dr[2][0]
            + y * dr[2][1])
        - four * z * (dr[0][0] + dr[1][1]);
    out[7] = dqr;
    out[8] = dqx;
    out[9] = dqy;
    out[10] = dqz;
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lanes::P16;
    use crate::rng::Rng;

    /// Random Gaussians with every case the projection branches on: behind the camera and at
    /// the near plane, clamped tan ratios (far off to the side), off-screen, faint, tiny and
    /// huge scales, tiny quaternions.
    fn scene(n: usize, seed: u64) -> Vec<f32> {
        let mut rng = Rng::new(seed);
        let mut rows = Vec::with_capacity(n * GEOM);
        for i in 0..n {
            let spread = [0.5, 2.0, 9.0, 40.0][i % 4];
            let mut mean = [0.0; 3].map(|_| rng.range(-spread, spread) as f32);
            if i % 7 == 0 {
                mean[2] = 8.8 + rng.range(-0.05, 0.05) as f32; // about the near plane
            }
            let opacity = [rng.range(0.0, 1.0), 0.001, 1.0 / 255.0, 1.0][i % 4] as f32;
            let sc = [0.0005, 0.005, 0.05, 3.0][(i / 4) % 4];
            let scale = [0.0; 3].map(|_| (sc * rng.range(0.2, 1.0)) as f32);
            let qs = if i % 5 == 0 { 1e-4 } else { 1.0 };
            let quat = [0.0; 4].map(|_| (qs * rng.normal()) as f32);
            rows.extend_from_slice(&mean);
            rows.push(opacity);
            rows.extend_from_slice(&scale);
            rows.extend_from_slice(&quat);
        }
        let mut geom = vec![0.0; n * GEOM];
        let mut out = GeomOut::split(&mut geom);
        for (i, row) in rows.chunks_exact(GEOM).enumerate() {
            out.put(i, row.try_into().unwrap());
        }
        geom
    }

    fn check_lanes<L: Lanes<f32>>(what: &str) {
        // Relative difference allowed in the block-visiting bound (its log is computed
        // differently; the bound is inflated by 2%).
        const CUT_REL_TOL: f32 = 1e-5;
        let cam = Camera::from_transform_matrix(
            &Camera::look_at_origin_matrix(9.0, 0.3, -0.2),
            12.0,
            200,
            120,
        )
        .unwrap();
        let k = CamK::<f32>::new(&cam);
        let n = 64 * WIDTH;
        let geom = scene(n, 7);
        let gin = GeomIn::split(&geom);
        let mut g = vec![MaybeUninit::new(Splat2D::default()); n];
        let mut depth = vec![MaybeUninit::new(0f32); n];
        let mut radius = vec![MaybeUninit::new(0u32); n];
        let mut rect = vec![MaybeUninit::new([0u16; 4]); n];
        for (j, (((s, d), r), rc)) in g
            .chunks_exact_mut(WIDTH)
            .zip(depth.chunks_exact_mut(WIDTH))
            .zip(radius.chunks_exact_mut(WIDTH))
            .zip(rect.chunks_exact_mut(WIDTH))
            .enumerate()
        {
            let gm = gin.range(j * WIDTH, (j + 1) * WIDTH);
            project_lanes::<f32, L>(&k, gm, s, d, r, rc);
        }
        let mut visible = 0;
        for i in 0..n {
            let (want, want_depth, want_r, want_rect) = project_one(&k, &gin.row(i));
            // SAFETY: initialised above (and overwritten by project_lanes).
            let (got, depth_i, radius_i, rect_i) = unsafe {
                (
                    g[i].assume_init_ref(),
                    depth[i].assume_init(),
                    radius[i].assume_init(),
                    rect[i].assume_init(),
                )
            };
            assert_eq!(radius_i, want_r, "{what}: radius of Gaussian {i}");
            assert_eq!(rect_i, want_rect, "{what}: rect of Gaussian {i}");
            let exact = [
                ("mx", got.mx, want.mx),
                ("my", got.my, want.my),
                ("qa", got.qa, want.qa),
                ("qb", got.qb, want.qb),
                ("qc", got.qc, want.qc),
                ("opacity", got.opacity, want.opacity),
                ("depth", depth_i, want_depth),
            ];
            for (name, a, b) in exact {
                assert_eq!(
                    a.to_bits(),
                    b.to_bits(),
                    "{what}: {name} of Gaussian {i}: expected {b}, got {a}"
                );
            }
            for (name, a, b) in [("ex", got.ex, want.ex), ("ey", got.ey, want.ey)] {
                assert!(
                    (a - b).abs() <= CUT_REL_TOL * b.abs().max(1.0),
                    "{what}: {name} of Gaussian {i}: expected {b}, got {a}"
                );
            }
            visible += (want_r > 0) as usize;
        }
        // The scene must exercise both outcomes.
        assert!(visible > n / 8 && visible < n, "{visible} of {n} visible");
    }

    #[test]
    fn lanes_projection_equals_one_by_one() {
        check_lanes::<P16<f32>>("array lanes");
        #[cfg(target_arch = "x86_64")]
        if gagavatar_testkit::avx512_or_skip("lanes_projection_equals_one_by_one (AVX-512 half)") {
            // SAFETY: the CPU has AVX-512F.
            unsafe { check_avx512() };
        }
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f,avx2,fma")]
    unsafe fn check_avx512() {
        check_lanes::<crate::lanes::Z16>("AVX-512 lanes");
    }
}
