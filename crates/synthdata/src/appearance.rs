//! Procedural per-identity appearance, evaluated per sample from the point's *canonical*
//! coordinate (its position on the FLAME template), so texture sticks to the skin as the face
//! moves and does not depend on the shape code.
//!
//! Canonical coordinates are in "face units": origin midway between the eyeball centres, one
//! unit = the distance between them, FLAME axes (+x the subject's left, +y up, +z out of the
//! face). Regions are placed from the asset's own landmarks and eyeballs ([`HeadAnchors`]), so
//! the same code paints the synthetic asset and the licensed FLAME.
//!
//! Identity features: skin tone and mottling, cheek blush, hair (hairline, back length, colour,
//! streaks), eyebrows, iris colour and size, lip colour, beard stubble, a pattern (freckles,
//! spots or face-paint stripes), a few asymmetric moles, and the key light's direction.

use gagavatar_flame::FlameAsset;

use crate::error::{config_err, Result};
use crate::sample::Rng;

/// What a face is made of.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Material {
    Skin,
    /// Eyeball of joint 3 (the subject's left, +x) or 4.
    Eye(u8),
}

/// Static landmarks of the release's 51 (iBUG 17..67): brows, nose tip, outer mouth contour.
const LMK_BROWS: std::ops::Range<usize> = 0..10;
const LMK_NOSE_TIP: usize = 13;
const LMK_MOUTH_OUTER: std::ops::Range<usize> = 31..43;
const STATIC_LANDMARKS: usize = 51;

/// Where the face's parts are on the template, in face units.
#[derive(Debug, Clone)]
pub struct HeadAnchors {
    /// Face units per template unit (1 / interocular distance).
    pub scale: f32,
    /// Template-space origin of face units (midpoint of the eyeball centres).
    pub origin: [f32; 3],
    /// Eyeball centres: joint 3 (+x), joint 4 (-x).
    pub eye_centre: [[f32; 3]; 2],
    /// Eyeball radius.
    pub eye_radius: f32,
    /// Brow landmark (x, y) pairs per side (+x side first), sorted by x.
    pub brows: [Vec<[f32; 2]>; 2],
    pub nose_tip: [f32; 3],
    pub mouth_centre: [f32; 3],
    /// Half width and half height of the outer mouth contour.
    pub mouth_half: [f32; 2],
    /// Centre of the cranium (x, z used as the axis for azimuths).
    pub crown: [f32; 3],
    /// Highest template point.
    pub top: f32,
    /// Per vertex: canonical coordinate in face units.
    pub canonical: Vec<[f32; 3]>,
    /// Per vertex: material.
    pub vertex_material: Vec<Material>,
    /// Per face: material (an eye only when all three vertices are that eye's).
    pub face_material: Vec<Material>,
}

fn sub(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn norm(a: [f32; 3]) -> f32 {
    (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt()
}

fn mix(a: [f32; 3], b: [f32; 3], t: f32) -> [f32; 3] {
    [
        a[0] + (b[0] - a[0]) * t,
        a[1] + (b[1] - a[1]) * t,
        a[2] + (b[2] - a[2]) * t,
    ]
}

fn scale3(a: [f32; 3], s: f32) -> [f32; 3] {
    [a[0] * s, a[1] * s, a[2] * s]
}

fn smoothstep(e0: f32, e1: f32, x: f32) -> f32 {
    let t = ((x - e0) / (e1 - e0)).clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

impl HeadAnchors {
    /// Finds the parts on an asset: eyeballs are the vertices skinned (weight >= 0.5) to the
    /// eye joints, the rest comes from the 51 static landmarks.
    pub fn new(asset: &FlameAsset) -> Result<Self> {
        let nv = asset.n_vertices;
        let lm = &asset.landmarks;
        if lm.static_faces.len() < STATIC_LANDMARKS {
            return Err(config_err(
                "flame",
                format!(
                    "the asset has {} static landmarks; placing the face needs the release's {}",
                    lm.static_faces.len(),
                    STATIC_LANDMARKS
                ),
            ));
        }
        let tv = |v: usize| -> [f32; 3] {
            [
                asset.v_template[3 * v],
                asset.v_template[3 * v + 1],
                asset.v_template[3 * v + 2],
            ]
        };
        let eye_of = |v: usize| -> Option<u8> {
            let w = &asset.weights[v * 5..v * 5 + 5];
            if w[3] >= 0.5 {
                Some(0)
            } else if w[4] >= 0.5 {
                Some(1)
            } else {
                None
            }
        };
        let mut eye_sum = [[0f64; 3]; 2];
        let mut eye_n = [0usize; 2];
        for v in 0..nv {
            if let Some(e) = eye_of(v) {
                let p = tv(v);
                for d in 0..3 {
                    eye_sum[e as usize][d] += p[d] as f64;
                }
                eye_n[e as usize] += 1;
            }
        }
        if eye_n.contains(&0) {
            return Err(config_err(
                "flame",
                "the asset has no eyeball vertices (none skinned to the eye joints 3 and 4)",
            ));
        }
        let eye_t: [[f32; 3]; 2] = [0, 1].map(|e| eye_sum[e].map(|s| (s / eye_n[e] as f64) as f32));
        let dist = norm(sub(eye_t[0], eye_t[1]));
        if !(dist.is_finite() && dist > 1e-6) {
            return Err(config_err(
                "flame",
                "the two eyeballs coincide; cannot size the face",
            ));
        }
        let origin = scale3([0, 1, 2].map(|d| eye_t[0][d] + eye_t[1][d]), 0.5);
        let scale = 1.0 / dist;
        let to_face = |p: [f32; 3]| scale3(sub(p, origin), scale);
        let canonical: Vec<[f32; 3]> = (0..nv).map(|v| to_face(tv(v))).collect();
        let lmk = |i: usize| -> [f32; 3] {
            let f = asset.faces[lm.static_faces[i] as usize];
            let b = lm.static_bary[i];
            let mut p = [0f32; 3];
            for k in 0..3 {
                let c = canonical[f[k] as usize];
                for d in 0..3 {
                    p[d] += b[k] * c[d];
                }
            }
            p
        };
        let mut brows: [Vec<[f32; 2]>; 2] = [Vec::new(), Vec::new()];
        for i in LMK_BROWS {
            let p = lmk(i);
            brows[if p[0] >= 0.0 { 0 } else { 1 }].push([p[0], p[1]]);
        }
        for side in &mut brows {
            side.sort_by(|a, b| a[0].total_cmp(&b[0]));
        }
        let mouth: Vec<[f32; 3]> = LMK_MOUTH_OUTER.map(lmk).collect();
        let mut mouth_centre = [0f32; 3];
        for p in &mouth {
            for d in 0..3 {
                mouth_centre[d] += p[d] / mouth.len() as f32;
            }
        }
        let extent = |d: usize| {
            let lo = mouth.iter().map(|p| p[d]).fold(f32::INFINITY, f32::min);
            let hi = mouth.iter().map(|p| p[d]).fold(f32::NEG_INFINITY, f32::max);
            0.5 * (hi - lo)
        };
        let mouth_half = [extent(0).max(0.05), extent(1).max(0.05)];
        let eye_centre = eye_t.map(to_face);
        let mut eye_radius = 0f32;
        for (v, c) in canonical.iter().enumerate() {
            if let Some(e) = eye_of(v) {
                eye_radius += norm(sub(*c, eye_centre[e as usize])) / (eye_n[0] + eye_n[1]) as f32;
            }
        }
        // The cranium: skin above the mouth.
        let mut crown = [0f64; 3];
        let mut n = 0usize;
        let mut top = f32::NEG_INFINITY;
        for (v, c) in canonical.iter().enumerate() {
            if eye_of(v).is_none() {
                top = top.max(c[1]);
                if c[1] > mouth_centre[1] {
                    for d in 0..3 {
                        crown[d] += c[d] as f64;
                    }
                    n += 1;
                }
            }
        }
        let crown = crown.map(|s| (s / n.max(1) as f64) as f32);
        let vertex_material: Vec<Material> = (0..nv)
            .map(|v| eye_of(v).map_or(Material::Skin, Material::Eye))
            .collect();
        let face_material = asset
            .faces
            .iter()
            .map(|f| {
                let m = f.map(|v| vertex_material[v as usize]);
                if m[0] == m[1] && m[1] == m[2] {
                    m[0]
                } else {
                    Material::Skin
                }
            })
            .collect();
        Ok(Self {
            scale,
            origin,
            eye_centre,
            eye_radius,
            brows,
            nose_tip: lmk(LMK_NOSE_TIP),
            mouth_centre,
            mouth_half,
            crown,
            top,
            canonical,
            vertex_material,
            face_material,
        })
    }

    /// Brow curve height at `x` on one side (`None` outside the brow's span).
    fn brow_y(&self, side: usize, x: f32) -> Option<(f32, f32)> {
        let pts = &self.brows[side];
        let (first, last) = (pts.first()?, pts.last()?);
        let margin = 0.08;
        if x < first[0] - margin || x > last[0] + margin {
            return None;
        }
        // Taper weight at the ends.
        let w = smoothstep(first[0] - margin, first[0] + 0.05, x)
            * (1.0 - smoothstep(last[0] - 0.05, last[0] + margin, x));
        let mut y = first[1];
        for seg in pts.windows(2) {
            if x >= seg[0][0] && x <= seg[1][0] {
                let t = (x - seg[0][0]) / (seg[1][0] - seg[0][0]).max(1e-6);
                y = seg[0][1] + t * (seg[1][1] - seg[0][1]);
            } else if x > seg[1][0] {
                y = seg[1][1];
            }
        }
        Some((y, w))
    }
}

// ------------------------------------------------------------------------------------------
// Noise

fn hash_u32(mut x: u32) -> u32 {
    // Chris Wellons' lowbias32 finaliser: cheap and well mixed.
    x ^= x >> 16;
    x = x.wrapping_mul(0x7feb_352d);
    x ^= x >> 15;
    x = x.wrapping_mul(0x846c_a68b);
    x ^ (x >> 16)
}

fn hash3(seed: u32, i: i32, j: i32, k: i32) -> u32 {
    // One finaliser over a random linear combination: plenty for texture, 3x cheaper than
    // chaining three.
    hash_u32(
        seed.wrapping_add((i as u32).wrapping_mul(0x8DA6_B343))
            .wrapping_add((j as u32).wrapping_mul(0xD816_3841))
            .wrapping_add((k as u32).wrapping_mul(0xCB1A_B31F)),
    )
}

fn unit(h: u32) -> f32 {
    (h >> 8) as f32 * (1.0 / 16_777_216.0)
}

/// Smooth value noise in [-1, 1].
fn value_noise(seed: u32, p: [f32; 3]) -> f32 {
    let fl = p.map(f32::floor);
    let i = fl.map(|x| x as i32);
    let f = [p[0] - fl[0], p[1] - fl[1], p[2] - fl[2]];
    let w = f.map(|t| t * t * (3.0 - 2.0 * t));
    let c = |dx: i32, dy: i32, dz: i32| unit(hash3(seed, i[0] + dx, i[1] + dy, i[2] + dz));
    let lerp = |a: f32, b: f32, t: f32| a + (b - a) * t;
    let x00 = lerp(c(0, 0, 0), c(1, 0, 0), w[0]);
    let x10 = lerp(c(0, 1, 0), c(1, 1, 0), w[0]);
    let x01 = lerp(c(0, 0, 1), c(1, 0, 1), w[0]);
    let x11 = lerp(c(0, 1, 1), c(1, 1, 1), w[0]);
    let y0 = lerp(x00, x10, w[1]);
    let y1 = lerp(x01, x11, w[1]);
    2.0 * lerp(y0, y1, w[2]) - 1.0
}

/// How much of a feature with `freq` cycles per face unit to keep when one pixel spans `fp`
/// face units: all of it well below the Nyquist rate (half a cycle per pixel), none near it,
/// so small images get the feature's average instead of aliasing speckle.
fn lod(freq: f32, fp: f32) -> f32 {
    1.0 - smoothstep(0.25, 0.5, freq * fp)
}

/// Value noise at `freq` features per face unit, faded out where pixels cannot resolve it.
fn noise_at(seed: u32, p: [f32; 3], freq: f32, fp: f32) -> f32 {
    let keep = lod(freq, fp);
    if keep <= 0.0 {
        return 0.0;
    }
    keep * value_noise(seed, p.map(|x| x * freq))
}

/// Random round dots: one per cell of side `cell` with probability `density`, radius
/// `radius * cell` (at most 0.3 cell, so a dot never leaves its cell). Returns coverage in [0, 1];
/// cells only a few pixels wide (`fp` face units per pixel) fade to the mean coverage.
fn dots(seed: u32, p: [f32; 3], cell: f32, radius: f32, density: f32, fp: f32) -> f32 {
    let radius = radius.min(0.3);
    // Mean area fraction of a plane through the dots: density x pi r^2 x (size spread, cut).
    let mean = density * 1.3 * radius * radius;
    let detail = smoothstep(1.5, 4.0, cell / fp.max(1e-9));
    if detail <= 0.0 {
        return mean;
    }
    detail * dot_cell(seed, p, cell, radius, density) + (1.0 - detail) * mean
}

fn dot_cell(seed: u32, p: [f32; 3], cell: f32, radius: f32, density: f32) -> f32 {
    let g = p.map(|x| x / cell);
    let c = g.map(|x| x.floor() as i32);
    let h = hash3(seed, c[0], c[1], c[2]);
    if unit(h) >= density {
        return 0.0;
    }
    let r = radius * (0.6 + 0.4 * unit(hash_u32(h ^ 0x51)));
    let centre = [0u32, 1, 2].map(|d| r + (1.0 - 2.0 * r) * unit(hash_u32(h.wrapping_add(d + 1))));
    let d = norm([
        g[0] - c[0] as f32 - centre[0],
        g[1] - c[1] as f32 - centre[1],
        g[2] - c[2] as f32 - centre[2],
    ]) / r;
    1.0 - smoothstep(0.75, 1.0, d)
}

// ------------------------------------------------------------------------------------------
// Identity appearance

/// Face-paint / skin pattern that helps tell identities apart.
#[derive(Debug, Clone, PartialEq)]
pub enum Pattern {
    None,
    /// Small brown dots over the nose and cheeks.
    Freckles {
        density: f32,
        colour: [f32; 3],
    },
    /// Larger coloured spots anywhere on the skin.
    Spots {
        cell: f32,
        density: f32,
        colour: [f32; 3],
    },
    /// Wavy painted stripes across the face.
    Stripes {
        direction: [f32; 3],
        period: f32,
        colour: [f32; 3],
    },
}

/// Everything that makes one synthetic person look like themselves.
#[derive(Debug, Clone, PartialEq)]
pub struct Appearance {
    pub skin: [f32; 3],
    /// Amplitude of the low-frequency skin mottling.
    pub skin_variation: f32,
    pub blush: f32,
    pub hair: [f32; 3],
    /// Front hairline height as a fraction of the way from the brows to the top of the head
    /// (above 1: bald on top).
    pub hairline: f32,
    /// Height (face units) down to which hair covers the back of the head.
    pub hair_back: f32,
    /// Azimuth (radians from the front) where the hairline starts dropping toward the back.
    pub temple: f32,
    /// Streaks per radian of azimuth.
    pub streaks: f32,
    pub brow_colour: [f32; 3],
    pub brow_thickness: f32,
    pub iris: [f32; 3],
    /// Angular radius of the iris on the eyeball (radians).
    pub iris_angle: f32,
    pub lips: [f32; 3],
    /// Stubble density (0: none).
    pub beard: f32,
    pub pattern: Pattern,
    /// Moles: centre (face units) and radius.
    pub moles: Vec<([f32; 3], f32)>,
    /// Key light direction in head (world) space, unit length.
    pub light: [f32; 3],
    pub ambient: f32,
    /// Seed of the identity's noise fields.
    pub noise_seed: u32,
}

const SKIN_TONES: [[f32; 3]; 7] = [
    [0.96, 0.84, 0.76],
    [0.92, 0.76, 0.64],
    [0.80, 0.62, 0.48],
    [0.70, 0.50, 0.36],
    [0.55, 0.37, 0.25],
    [0.40, 0.26, 0.18],
    [0.27, 0.18, 0.13],
];

const NATURAL_HAIR: [[f32; 3]; 8] = [
    [0.05, 0.04, 0.04],
    [0.18, 0.11, 0.07],
    [0.36, 0.22, 0.12],
    [0.55, 0.24, 0.10],
    [0.80, 0.64, 0.38],
    [0.90, 0.85, 0.72],
    [0.58, 0.58, 0.58],
    [0.28, 0.20, 0.15],
];

const VIVID_HAIR: [[f32; 3]; 6] = [
    [0.15, 0.30, 0.85],
    [0.90, 0.35, 0.60],
    [0.20, 0.70, 0.35],
    [0.50, 0.25, 0.75],
    [0.10, 0.65, 0.70],
    [0.95, 0.55, 0.10],
];

const IRIS: [[f32; 3]; 8] = [
    [0.30, 0.17, 0.08],
    [0.16, 0.10, 0.05],
    [0.48, 0.38, 0.18],
    [0.25, 0.50, 0.25],
    [0.25, 0.45, 0.80],
    [0.50, 0.56, 0.62],
    [0.55, 0.30, 0.75],
    [0.80, 0.55, 0.10],
];

const LIPSTICK: [[f32; 3]; 5] = [
    [0.75, 0.08, 0.12],
    [0.90, 0.40, 0.55],
    [0.45, 0.12, 0.35],
    [0.30, 0.08, 0.08],
    [0.95, 0.45, 0.25],
];

/// Darkest albedo channel value (keeps covered pixels distinguishable from the background).
const MIN_ALBEDO: f32 = 0.03;
const SCLERA: [f32; 3] = [0.94, 0.91, 0.88];
const PUPIL: [f32; 3] = [0.03, 0.03, 0.03];
/// The inside of the head seen through the mouth (dark red) or past the eyeballs (near black),
/// unlit.
pub const MOUTH_INTERIOR: [f32; 3] = [0.16, 0.04, 0.04];
pub const INTERIOR: [f32; 3] = [0.04, 0.03, 0.03];

fn pick(rng: &mut Rng, palette: &[[f32; 3]]) -> [f32; 3] {
    palette[(rng.uniform() * palette.len() as f64) as usize % palette.len()]
}

fn pick_jitter(rng: &mut Rng, palette: &[[f32; 3]], amount: f64) -> [f32; 3] {
    let c = pick(rng, palette);
    jitter(rng, c, amount)
}

fn jitter(rng: &mut Rng, c: [f32; 3], amount: f64) -> [f32; 3] {
    c.map(|x| (x as f64 + rng.range(-amount, amount)).clamp(0.0, 1.0) as f32)
}

impl Appearance {
    /// Draws an identity's appearance from its own random stream.
    pub fn sample(rng: &mut Rng, anchors: &HeadAnchors) -> Self {
        // Skin: anywhere along the tone ramp, slightly warmer or cooler.
        let t = rng.uniform() * (SKIN_TONES.len() - 1) as f64;
        let i = (t as usize).min(SKIN_TONES.len() - 2);
        let skin = mix(SKIN_TONES[i], SKIN_TONES[i + 1], (t - i as f64) as f32);
        let skin = jitter(rng, skin, 0.03);
        let vivid = rng.uniform() < 0.2;
        let hair = pick_jitter(rng, if vivid { &VIVID_HAIR } else { &NATURAL_HAIR }, 0.04);
        let bald = rng.uniform() < 0.12;
        let hairline = if bald {
            1.2
        } else {
            rng.range(0.15, 0.55) as f32
        };
        let long = rng.uniform() < 0.4;
        let mouth_y = anchors.mouth_centre[1];
        let hair_back = if long {
            mouth_y - rng.range(1.0, 2.5) as f32
        } else {
            mouth_y + rng.range(-0.3, 0.6) as f32
        };
        let brow_colour = if rng.uniform() < 0.7 {
            scale3(hair, 0.7)
        } else {
            jitter(rng, [0.12, 0.08, 0.06], 0.05)
        };
        let lips = if rng.uniform() < 0.3 {
            pick_jitter(rng, &LIPSTICK, 0.04)
        } else {
            let base = mix(skin, [0.72, 0.28, 0.30], rng.range(0.35, 0.6) as f32);
            jitter(rng, base, 0.03)
        };
        let pattern = match (rng.uniform() * 5.0) as usize {
            0 => Pattern::None,
            1 => Pattern::Freckles {
                density: rng.range(0.25, 0.6) as f32,
                colour: mix(skin, [0.35, 0.18, 0.08], 0.55),
            },
            2 => Pattern::Spots {
                cell: rng.range(0.22, 0.4) as f32,
                density: rng.range(0.3, 0.6) as f32,
                colour: pick_jitter(rng, &VIVID_HAIR, 0.1),
            },
            3 => {
                let a = rng.range(-1.2, 1.2);
                Pattern::Stripes {
                    direction: [a.cos() as f32, a.sin() as f32, 0.0],
                    period: rng.range(0.25, 0.5) as f32,
                    colour: pick_jitter(rng, &VIVID_HAIR, 0.1),
                }
            }
            _ => Pattern::Freckles {
                density: rng.range(0.1, 0.3) as f32,
                colour: mix(skin, [0.3, 0.15, 0.07], 0.4),
            },
        };
        let n_moles = (rng.uniform() * 4.0) as usize;
        let moles = (0..n_moles)
            .map(|_| {
                let x = rng.range(-1.3, 1.3) as f32;
                let y = rng.range(mouth_y as f64 - 0.6, 0.9) as f32;
                // On the surface: the nearest template vertex in (x, y) on the front.
                let p = anchors
                    .canonical
                    .iter()
                    .zip(&anchors.vertex_material)
                    .filter(|(c, m)| **m == Material::Skin && c[2] > anchors.crown[2])
                    .min_by(|a, b| {
                        let da = (a.0[0] - x).powi(2) + (a.0[1] - y).powi(2);
                        let db = (b.0[0] - x).powi(2) + (b.0[1] - y).powi(2);
                        da.total_cmp(&db)
                    })
                    .map(|(c, _)| *c)
                    .unwrap_or([x, y, 0.0]);
                (p, rng.range(0.025, 0.05) as f32)
            })
            .collect();
        let lx = rng.range(-0.7, 0.7);
        let ly = rng.range(0.2, 0.9);
        let l = [lx, ly, 1.0];
        let ln = (l[0] * l[0] + l[1] * l[1] + l[2] * l[2]).sqrt();
        Self {
            skin,
            skin_variation: rng.range(0.03, 0.1) as f32,
            blush: rng.range(0.0, 0.25) as f32,
            hair,
            hairline,
            hair_back,
            temple: rng.range(0.7, 1.1) as f32,
            streaks: rng.range(8.0, 20.0) as f32,
            brow_colour,
            brow_thickness: rng.range(0.05, 0.1) as f32,
            iris: pick_jitter(rng, &IRIS, 0.04),
            iris_angle: rng.range(0.5, 0.7) as f32,
            lips,
            beard: if rng.uniform() < 0.25 {
                rng.range(0.3, 0.8) as f32
            } else {
                0.0
            },
            pattern,
            moles,
            light: l.map(|x| (x / ln) as f32),
            ambient: rng.range(0.3, 0.45) as f32,
            noise_seed: (rng.next_u64() >> 32) as u32,
        }
    }

    /// Surface colour at canonical point `q` of a face made of `material`, for pixels `fp` face
    /// units wide (details finer than about two pixels fade to their average).
    pub fn albedo(&self, a: &HeadAnchors, material: Material, q: [f32; 3], fp: f32) -> [f32; 3] {
        let c = match material {
            Material::Eye(e) => self.eye(a, e as usize, q, fp),
            Material::Skin => self.skin_at(a, q, fp),
        };
        // Nothing on the head is as black as the background.
        c.map(|x| x.max(MIN_ALBEDO))
    }

    /// Colour of the head's inside at canonical point `q` (seen through a hole).
    pub fn interior(&self, a: &HeadAnchors, q: [f32; 3]) -> [f32; 3] {
        let dx = (q[0] - a.mouth_centre[0]) / (2.0 * a.mouth_half[0]);
        let dy = (q[1] - a.mouth_centre[1]) / (2.0 * a.mouth_half[1] + 0.3);
        mix(
            INTERIOR,
            MOUTH_INTERIOR,
            1.0 - smoothstep(0.7, 1.0, (dx * dx + dy * dy).sqrt()),
        )
    }

    fn eye(&self, a: &HeadAnchors, e: usize, q: [f32; 3], fp: f32) -> [f32; 3] {
        let d = sub(q, a.eye_centre[e]);
        let r = norm(d).max(1e-6);
        let angle = (d[2] / r).clamp(-1.0, 1.0).acos();
        let pupil = self.iris_angle * 0.38;
        if angle < pupil {
            return PUPIL;
        }
        if angle < self.iris_angle {
            // Radial fibres and a darker limbal ring.
            let phi = d[1].atan2(d[0]);
            // 23 fibres per radian on an iris about 0.14 face units across: ~26 per unit.
            let fibres = 0.85 + 0.15 * lod(26.0, fp) * (phi * 23.0).sin() * (phi * 7.0 + 1.3).cos();
            let ring = 1.0 - 0.45 * smoothstep(0.75, 1.0, angle / self.iris_angle);
            return scale3(self.iris, fibres * ring);
        }
        let edge = smoothstep(self.iris_angle, self.iris_angle + 0.05, angle);
        mix(scale3(self.iris, 0.5), SCLERA, edge)
    }

    fn skin_at(&self, a: &HeadAnchors, q: [f32; 3], fp: f32) -> [f32; 3] {
        let seed = self.noise_seed;
        let azimuth = (q[0] - a.crown[0]).atan2(q[2] - a.crown[2]);
        let front = azimuth.abs() < 1.3;
        let mouth = a.mouth_centre;

        // Base tone with gentle mottling; the neck a little darker.
        let mottle = noise_at(seed, q, 1.6, fp) * 0.7 + noise_at(seed ^ 7, q, 5.0, fp) * 0.3;
        let mut c = scale3(self.skin, 1.0 + self.skin_variation * mottle);
        let chin = mouth[1] - 0.6;
        c = scale3(c, 1.0 - 0.15 * smoothstep(chin, chin - 0.8, q[1]));

        if front {
            // Cheeks.
            if self.blush > 0.0 {
                let cy = 0.5 * mouth[1] - 0.1;
                let w = [-1.0f32, 1.0]
                    .iter()
                    .map(|s| {
                        let dx = q[0] - s * 0.75;
                        let dy = q[1] - cy;
                        (-(dx * dx + dy * dy) / 0.09).exp()
                    })
                    .sum::<f32>();
                c = mix(c, [0.85, 0.35, 0.35], self.blush * w.min(1.0));
            }
            match &self.pattern {
                Pattern::None => {}
                Pattern::Freckles { density, colour } => {
                    let dx = q[0] / 1.3;
                    let dy = (q[1] - 0.5 * mouth[1]) / 0.7;
                    let region = (-(dx * dx + dy * dy)).exp();
                    let f = dots(seed ^ 0xF4EC, q, 0.07, 0.28, *density, fp);
                    c = mix(c, *colour, f * region);
                }
                Pattern::Spots {
                    cell,
                    density,
                    colour,
                } => {
                    let f = dots(seed ^ 0x5B07, q, *cell, 0.3, *density, fp);
                    c = mix(c, *colour, 0.85 * f);
                }
                Pattern::Stripes {
                    direction,
                    period,
                    colour,
                } => {
                    let s = (q[0] * direction[0] + q[1] * direction[1]) / period
                        * std::f32::consts::TAU
                        + 1.5 * noise_at(seed ^ 0x57, q, 2.0, fp);
                    // Stripes too fine for the image fade to their mean coverage (~0.25).
                    let keep = lod(1.0 / period, fp);
                    let band = keep * smoothstep(0.55, 0.8, s.sin()) + (1.0 - keep) * 0.25;
                    // Keep the paint off the mouth and eyes.
                    let dm = ((q[0] - mouth[0]) / (a.mouth_half[0] + 0.25)).powi(2)
                        + ((q[1] - mouth[1]) / (a.mouth_half[1] + 0.25)).powi(2);
                    let de = [0, 1]
                        .iter()
                        .map(|&e| {
                            let d = sub(q, a.eye_centre[e]);
                            d[0] * d[0] + d[1] * d[1]
                        })
                        .fold(f32::INFINITY, f32::min);
                    let keep = smoothstep(1.0, 1.3, dm) * smoothstep(0.1, 0.16, de);
                    c = mix(c, *colour, 0.9 * band * keep);
                }
            }
            // A dark rim around the eye sockets (lashes, lid crease) makes the eyes readable at
            // low resolution.
            for e in 0..2 {
                let d = sub(q, a.eye_centre[e]);
                let r = (d[0] * d[0] + d[1] * d[1]).sqrt() / a.eye_radius.max(1e-3);
                let w = smoothstep(0.85, 1.0, r) * (1.0 - smoothstep(1.05, 1.35, r));
                c = scale3(c, 1.0 - 0.35 * w);
            }
            // Lips.
            let dx = (q[0] - mouth[0]) / (a.mouth_half[0] * 1.1);
            let dy = (q[1] - mouth[1]) / (a.mouth_half[1] * 1.2);
            let r = (dx * dx + dy * dy).sqrt();
            let lip = 1.0 - smoothstep(0.8, 1.0, r);
            // Beard stubble below the nose, around the mouth and over the chin.
            if self.beard > 0.0 && lip < 1.0 {
                let top = a.nose_tip[1] - 0.12;
                let region = smoothstep(top, top - 0.1, q[1])
                    * smoothstep(chin - 0.25, chin, q[1])
                    * (1.0 - smoothstep(0.9, 1.2, azimuth.abs()));
                if region > 0.0 {
                    let keep = lod(40.0, fp);
                    let speck = keep * smoothstep(-0.2, 0.5, noise_at(seed ^ 0xBEA2, q, 40.0, fp))
                        + (1.0 - keep) * 0.4;
                    let w = 0.85 * region * self.beard * speck * (1.0 - lip);
                    c = mix(c, scale3(self.hair, 0.8), w);
                }
            }
            c = mix(c, self.lips, lip);
            // Brows.
            let side = if q[0] >= 0.0 { 0 } else { 1 };
            if let Some((y, w)) = a.brow_y(side, q[0]) {
                let dy = (q[1] - y - 0.02) / self.brow_thickness;
                let b = w * (-(dy * dy)).exp();
                let hairs = 0.8 + 0.2 * noise_at(seed ^ 0xB2, q, 30.0, fp);
                c = mix(c, self.brow_colour, (b * hairs).min(1.0));
            }
            for (p, r) in &self.moles {
                let d = norm(sub(q, *p)) / r;
                // Sub-pixel moles would flicker in and out; they fade instead.
                let strength = smoothstep(0.5, 1.5, r / fp.max(1e-9));
                c = mix(
                    c,
                    [0.2, 0.12, 0.08],
                    strength * (1.0 - smoothstep(0.7, 1.0, d)),
                );
            }
        }

        // Hair last: it covers everything under it.
        let brow_top = a.brows[0]
            .iter()
            .chain(&a.brows[1])
            .map(|p| p[1])
            .fold(f32::NEG_INFINITY, f32::max);
        let front_line = brow_top + self.hairline * (a.top - brow_top);
        let t = smoothstep(self.temple, self.temple + 1.2, azimuth.abs());
        let line = front_line
            + (self.hair_back - front_line) * t
            + 0.12 * noise_at(seed ^ 0x4A1, q, 3.0, fp);
        let hair_w = smoothstep(-0.04, 0.04, q[1] - line);
        if hair_w > 0.0 {
            // `streaks * 6` per radian on a head about 1.5 face units in radius.
            let keep = lod(self.streaks * 6.0 / (std::f32::consts::TAU * 1.5), fp);
            let streak = keep
                * (azimuth * self.streaks * 6.0 + 3.0 * noise_at(seed ^ 0x57E, q, 2.5, fp)).sin();
            let fine = noise_at(seed ^ 0xF1, q, 25.0, fp);
            let h = scale3(self.hair, 0.85 + 0.12 * streak + 0.08 * fine);
            c = mix(c, h, hair_w);
        }
        c
    }
}
