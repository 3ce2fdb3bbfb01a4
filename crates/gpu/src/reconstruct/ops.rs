//! The kernels `reconstruct` adds to the renderer's (see `conv.rs`), as recordable steps:
//! LayerNorm, attention, im2col, the ViT's token assembly, the transposed convolutions' pixel
//! spread, align-corners resizing, per-row sums and fills, and the Gaussians' activation.

use crate::conv::{At, Ops};
use crate::error::{GpuError, Result};
use crate::kernel::{linear_grid, Bind, Grid, Params, Step};

const LAYER_NORM: &str = include_str!("../shaders/layer_norm.wgsl");
const ATTENTION: &str = include_str!("../shaders/attention.wgsl");
const IM2COL: &str = include_str!("../shaders/im2col.wgsl");
const TOKENS: &str = include_str!("../shaders/tokens.wgsl");
const SHUFFLE: &str = include_str!("../shaders/shuffle.wgsl");
const RESIZE_AC: &str = include_str!("../shaders/resize_ac.wgsl");
const ROWS: &str = include_str!("../shaders/rows.wgsl");
const GAUSSIANS: &str = include_str!("../shaders/gaussians.wgsl");
const ROTATIONS_ACROSS: &str = include_str!("../shaders/rotations_across.wgsl");
const RESIZE_TAPS: &str = include_str!("../shaders/resize_taps.wgsl");

/// Tap tables of resizes (the CPU path's `Taps`) in two buffers, and where each one is.
pub struct TapTables {
    pub starts: wgpu::Buffer,
    pub weights: wgpu::Buffer,
    /// Per resize: (rows: start offset, weight offset, taps), (columns: the same).
    pub at: Vec<[(u32, u32, u32); 2]>,
}

impl TapTables {
    /// Tables for resizing `[in, in]` to `[out, out]` for each `(in, out)`, with `mode`.
    pub fn new(
        gpu: &crate::Gpu,
        sizes: &[(usize, usize)],
        mode: gagavatar_ops::ResizeMode,
    ) -> Self {
        let (mut starts, mut weights, mut at) = (Vec::<u32>::new(), Vec::<f32>::new(), Vec::new());
        for &(input, output) in sizes {
            let t = gagavatar_ops::resample::Taps::new(input, output, mode);
            let axis = (starts.len() as u32, weights.len() as u32, t.n as u32);
            starts.extend(t.start.iter().map(|&s| s as u32));
            weights.extend(t.w.iter().map(|&w| w as f32));
            // Square images: the same table serves rows and columns.
            at.push([axis, axis]);
        }
        Self {
            starts: gpu.buffer_with("resize starts", &starts),
            weights: gpu.buffer_with("resize weights", &weights),
            at,
        }
    }
}

/// Keys per tile of the attention kernel: two tiles of `KT x D` f32 fill 16 KiB of workgroup
/// memory at D = 64 (WebGPU's guaranteed minimum).
const ATTENTION_KEYS: usize = 32;

/// attention.wgsl's generated parts for heads of `d` channels: the query and output as
/// scalars, the dot product in four partial sums, the rescale, the accumulation, the store.
fn attention_consts(d: usize) -> Vec<(&'static str, String)> {
    let (mut decl, mut dot, mut rescale, mut accum, mut store) = (
        String::new(),
        String::new(),
        String::new(),
        String::new(),
        String::new(),
    );
    for e in 0..d {
        decl += &format!("    let q_{e} = q_at(q_row + {e}u * p.n, qi, valid);\n");
        decl += &format!("    var o_{e} = 0.0;\n");
        rescale += &format!("                o_{e} = o_{e} * corr;\n");
        accum += &format!("            o_{e} = fma(pj, Vs[kb + {e}u], o_{e});\n");
        store += &format!("        y[o_row + {e}u * p.n] = o_{e} * inv;\n");
    }
    let lanes = 4.min(d);
    for part in 0..lanes {
        dot += &format!("            var s_{part} = 0.0;\n");
    }
    for e in 0..d {
        let part = e % lanes;
        dot += &format!("            s_{part} = fma(q_{e}, Ks[kb + {e}u], s_{part});\n");
    }
    let sum: Vec<String> = (0..lanes).map(|k| format!("s_{k}")).collect();
    dot += &format!("            let s = {};", sum.join(" + "));
    vec![
        ("D", d.to_string()),
        ("KT", ATTENTION_KEYS.to_string()),
        ("DECL", decl),
        ("DOT", dot),
        ("RESCALE", rescale),
        ("ACCUM", accum),
        ("STORE", store),
    ]
}

fn flag(b: bool) -> String {
    if b { "true" } else { "false" }.to_string()
}

/// The ImageNet normalisation applied after a resize: per channel mean and 1/std.
pub type Normalize = ([f32; 3], [f32; 3]);

/// A LayerNorm's shape: `n` tokens of `c` channels, read every `in_stride` and written every
/// `out_stride` values per channel.
#[derive(Debug, Clone, Copy)]
pub struct NormShape {
    pub c: usize,
    pub n: usize,
    pub in_stride: usize,
    pub out_stride: usize,
}

/// Where the Gaussians of one generator go: `m` of them from Gaussian `g0` on, with `c`
/// feature channels; `lift` = (side of the plane, the plane buffer, offset into the means,
/// +1 or -1) for the lifting generators.
pub struct GaussianOut<'a> {
    pub m: usize,
    pub c: usize,
    pub g0: usize,
    pub lift: Option<(usize, &'a wgpu::Buffer, usize, f32)>,
    /// features, opacities, scales, rotations, means.
    pub buffers: [&'a wgpu::Buffer; 5],
}

impl Ops<'_> {
    /// LayerNorm over channels with `gamma`, `beta` at offsets into the vector buffer.
    pub fn layer_norm(
        &self,
        s: NormShape,
        (gamma, beta): (u32, u32),
        eps: f32,
        input: At,
        out: At,
    ) -> Result<Step> {
        let slices = self.tuning.ln_slices;
        let k = self.gpu.kernel(
            "layer_norm",
            LAYER_NORM,
            &[("SLICES", slices.to_string())],
            &[Bind::Uniform, Bind::Read, Bind::Read, Bind::ReadWrite],
        )?;
        let u = self.gpu.uniform(
            "layer norm",
            &Params::new()
                .u(s.c as u32)
                .u(s.n as u32)
                .u(input.off)
                .u(s.in_stride as u32)
                .u(out.off)
                .u(s.out_stride as u32)
                .u(gamma)
                .u(beta)
                .f(eps),
        );
        let g = self.gpu.bind(&k, &[&u, input.buf, self.vecs, out.buf])?;
        Ok(Step::new(
            k,
            g,
            Grid::Fixed([s.n.div_ceil(256 / slices as usize) as u32, 1, 1]),
        )
        .with_note(format!("{} ch x {}", s.c, s.n)))
    }

    /// Self-attention of `heads` heads of `d` channels over `n` tokens, `qkv` `[3 heads d, n]`
    /// -> `out` `[heads d, n]`.
    pub fn attention(&self, heads: usize, d: usize, n: usize, qkv: At, out: At) -> Result<Step> {
        let shared = 2 * ATTENTION_KEYS * d * 4;
        if shared > self.gpu.limits.max_compute_workgroup_storage_size as usize {
            return Err(GpuError::Unsupported(format!(
                "attention heads of {d} channels need {shared} bytes of workgroup memory"
            )));
        }
        let k = self.gpu.kernel(
            "attention",
            ATTENTION,
            &attention_consts(d),
            &[Bind::Uniform, Bind::Read, Bind::ReadWrite],
        )?;
        let u = self.gpu.uniform(
            "attention",
            &Params::new()
                .u(n as u32)
                .u((heads * d) as u32)
                .u(qkv.off)
                .u(out.off)
                .f(1.0 / (d as f32).sqrt()),
        );
        let g = self.gpu.bind(&k, &[&u, qkv.buf, out.buf])?;
        Ok(
            Step::new(k, g, Grid::Fixed([n.div_ceil(64) as u32, heads as u32, 1]))
                .with_note(format!("{heads} heads x {d}, {n} tokens")),
        )
    }

    /// The patches of a `k x k`, `stride`, `pad` convolution of `[c, h, w]` as a
    /// `[c k k, oh ow]` matrix.
    #[allow(clippy::too_many_arguments)]
    pub fn im2col(
        &self,
        (c, h, w): (usize, usize, usize),
        k: usize,
        stride: usize,
        pad: usize,
        input: At,
        out: At,
    ) -> Result<(Step, usize, usize)> {
        let oh = (h + 2 * pad - k) / stride + 1;
        let ow = (w + 2 * pad - k) / stride + 1;
        let kern = self.gpu.kernel(
            "im2col",
            IM2COL,
            &[],
            &[Bind::Uniform, Bind::Read, Bind::ReadWrite],
        )?;
        let u = self.gpu.uniform(
            "im2col",
            &Params::new()
                .u(c as u32)
                .u(h as u32)
                .u(w as u32)
                .u(k as u32)
                .u(stride as u32)
                .u(pad as u32)
                .u(oh as u32)
                .u(ow as u32)
                .u(input.off)
                .u(out.off),
        );
        let g = self.gpu.bind(&kern, &[&u, input.buf, out.buf])?;
        Ok((
            Step::new(kern, g, linear_grid(c * k * k * oh * ow, 256)),
            oh,
            ow,
        ))
    }

    /// The ViT's first activation `[c, g + 1]` from the embedded patches `[c, g]` and `emb`
    /// (class token at `cls`, position embedding `[1 + g, c]` at `pos`).
    pub fn tokens(
        &self,
        c: usize,
        g: usize,
        patches: &wgpu::Buffer,
        (emb, cls, pos): (&wgpu::Buffer, u32, u32),
        out: &wgpu::Buffer,
    ) -> Result<Step> {
        let k = self.gpu.kernel(
            "tokens",
            TOKENS,
            &[],
            &[Bind::Uniform, Bind::Read, Bind::Read, Bind::ReadWrite],
        )?;
        let u = self.gpu.uniform(
            "tokens",
            &Params::new().u(c as u32).u(g as u32).u(cls).u(pos),
        );
        let gr = self.gpu.bind(&k, &[&u, patches, emb, out])?;
        Ok(Step::new(k, gr, linear_grid(c * (g + 1), 256)))
    }

    /// `[c k k, g, g]` -> `[c, g k, g k]` plus the bias at `bias` in the vector buffer.
    pub fn shuffle(
        &self,
        (c, g, k): (usize, usize, usize),
        bias: u32,
        input: At,
        out: At,
    ) -> Result<Step> {
        let kern = self.gpu.kernel(
            "shuffle",
            SHUFFLE,
            &[],
            &[Bind::Uniform, Bind::Read, Bind::Read, Bind::ReadWrite],
        )?;
        let u = self.gpu.uniform(
            "shuffle",
            &Params::new()
                .u(c as u32)
                .u(g as u32)
                .u(k as u32)
                .u(input.off)
                .u(out.off)
                .u(bias),
        );
        let gr = self.gpu.bind(&kern, &[&u, input.buf, self.vecs, out.buf])?;
        Ok(Step::new(kern, gr, linear_grid(c * g * g * k * k, 256)))
    }

    /// Bilinear, align_corners=True: `[c, h, w]` -> `[c, oh, ow]`.
    pub fn resize_to(
        &self,
        (c, h, w): (usize, usize, usize),
        (oh, ow): (usize, usize),
        input: At,
        out: At,
    ) -> Result<Step> {
        let k = self.gpu.kernel(
            "resize_ac",
            RESIZE_AC,
            &[],
            &[Bind::Uniform, Bind::Read, Bind::ReadWrite],
        )?;
        let u = self.gpu.uniform(
            "resize",
            &Params::new()
                .u(c as u32)
                .u(h as u32)
                .u(w as u32)
                .u(oh as u32)
                .u(ow as u32)
                .u(input.off)
                .u(out.off),
        );
        let g = self.gpu.bind(&k, &[&u, input.buf, out.buf])?;
        Ok(Step::new(k, g, linear_grid(c * oh * ow, 256)))
    }

    /// `out[r, c] = (a[r, c] +) b[r]`, optionally ReLU, over `[rows, cols]`.
    pub fn rows(
        &self,
        (rows, cols): (usize, usize),
        a: Option<At>,
        b: At,
        relu: bool,
        out: At,
    ) -> Result<Step> {
        let k = self.gpu.kernel(
            "rows",
            ROWS,
            &[("HAS_A", flag(a.is_some())), ("RELU", flag(relu))],
            &[Bind::Uniform, Bind::Read, Bind::Read, Bind::ReadWrite],
        )?;
        let a = a.unwrap_or(At::new(self.dummy));
        let u = self.gpu.uniform(
            "rows",
            &Params::new()
                .u(rows as u32)
                .u(cols as u32)
                .u(a.off)
                .u(b.off)
                .u(out.off),
        );
        let g = self.gpu.bind(&k, &[&u, a.buf, b.buf, out.buf])?;
        Ok(Step::new(k, g, linear_grid(rows * cols, 256)))
    }

    /// A generator's raw output `[c + 8 (+ 1), m]` activated into the splatting's buffers.
    /// `spare` is bound where the plane and means are not used (it must differ from
    /// `self.dummy`: one is read, the other written).
    pub fn gaussians(&self, o: &GaussianOut, raw: At, spare: &wgpu::Buffer) -> Result<Step> {
        let k = self.gpu.kernel(
            "gaussians",
            GAUSSIANS,
            &[("LIFT", flag(o.lift.is_some()))],
            &[
                Bind::Uniform,
                Bind::Read,
                Bind::Read,
                Bind::ReadWrite,
                Bind::ReadWrite,
                Bind::ReadWrite,
                Bind::ReadWrite,
                Bind::ReadWrite,
            ],
        )?;
        let (side, plane, means_off, sign) = o.lift.unwrap_or((1, self.dummy, 0, 1.0));
        let means = if o.lift.is_some() {
            o.buffers[4]
        } else {
            spare
        };
        let u = self.gpu.uniform(
            "gaussians",
            &Params::new()
                .u(o.m as u32)
                .u(o.c as u32)
                .u(side as u32)
                .u(o.g0 as u32)
                .u(raw.off)
                .u(means_off as u32)
                .f(sign),
        );
        let [features, opacities, scales, rotations, _] = o.buffers;
        let g = self.gpu.bind(
            &k,
            &[
                &u, raw.buf, plane, features, opacities, scales, rotations, means,
            ],
        )?;
        Ok(Step::new(k, g, linear_grid(o.m, 256)))
    }

    /// The expression Gaussians' rotations: rows `c + 4 ..` of the raw `[c + 8, m]` output,
    /// each component normalised across the `m` Gaussians, into `rotations` at Gaussian `g0`.
    pub fn rotations_across(
        &self,
        (m, c, g0): (usize, usize, usize),
        raw: At,
        rotations: &wgpu::Buffer,
    ) -> Result<Step> {
        let k = self.gpu.kernel(
            "rotations_across",
            ROTATIONS_ACROSS,
            &[],
            &[Bind::Uniform, Bind::Read, Bind::ReadWrite],
        )?;
        let u = self.gpu.uniform(
            "rotations",
            &Params::new()
                .u(m as u32)
                .u(g0 as u32)
                .u(raw.off + ((c + 4) * m) as u32),
        );
        let g = self.gpu.bind(&k, &[&u, raw.buf, rotations])?;
        Ok(Step::new(k, g, Grid::Fixed([1, 1, 1])))
    }

    /// `[c, h, h]` -> `[c, oh, oh]` through resize `k` of `tables`, optionally normalised.
    #[allow(clippy::too_many_arguments)]
    pub fn resize_taps(
        &self,
        tables: &TapTables,
        k: usize,
        (c, h, oh): (usize, usize, usize),
        normalize: Option<Normalize>,
        input: At,
        out: At,
    ) -> Result<Step> {
        let [(sy, wy, ny), (sx, wx, nx)] = tables.at[k];
        let kern = self.gpu.kernel(
            "resize_taps",
            RESIZE_TAPS,
            &[("NORMALIZE", flag(normalize.is_some()))],
            &[
                Bind::Uniform,
                Bind::Read,
                Bind::Read,
                Bind::Read,
                Bind::ReadWrite,
            ],
        )?;
        let (mean, inv) = normalize.unwrap_or(([0.0; 3], [1.0; 3]));
        let mut p = Params::new()
            .u(c as u32)
            .u(h as u32)
            .u(h as u32)
            .u(oh as u32)
            .u(oh as u32)
            .u(ny)
            .u(nx)
            .u(sy)
            .u(sx)
            .u(wy)
            .u(wx)
            .u(input.off)
            .u(out.off)
            .u(0)
            .u(0)
            .u(0);
        for v in mean.iter().chain(&[0.0]).chain(&inv).chain(&[1.0]) {
            p = p.f(*v);
        }
        let u = self.gpu.uniform("resize taps", &p);
        let g = self.gpu.bind(
            &kern,
            &[&u, input.buf, &tables.starts, &tables.weights, out.buf],
        )?;
        Ok(Step::new(kern, g, linear_grid(c * oh * oh, 256)).with_note(format!("{h} -> {oh}")))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testutil::{assert_close, gpu};
    use gagavatar_splat::testscene::Rng;

    /// f32 sums of up to 1370 x 64 products against f64.
    const ATTENTION_TOL: f64 = 2e-5;

    fn ops<'a>(g: &'a crate::Gpu, t: &'a crate::Tuning, b: &'a wgpu::Buffer) -> Ops<'a> {
        Ops {
            gpu: g,
            tuning: t,
            vecs: b,
            dummy: b,
            split_scratch: b,
        }
    }

    /// Attention of channel-major qkv against f64 loops, for token counts below, at and far
    /// above one tile of keys and one workgroup of queries, at offsets into the buffers.
    #[test]
    fn attention_matches_f64() {
        let Some(g) = gpu() else { return };
        let t = crate::Tuning::default();
        let spare = g.buffer("spare", 16);
        let ops = ops(g, &t, &spare);
        let mut rng = Rng::new(3);
        for (heads, d, n) in [
            (2, 16, 5),
            (2, 16, 70),
            (1, 64, 100),
            (1, 64, 500),
            (2, 64, 677),
            (3, 64, 1370),
        ] {
            let c = heads * d;
            let off = 3;
            let x: Vec<f32> = (0..off + 3 * c * n)
                .map(|_| (rng.normal() * 1.5) as f32)
                .collect();
            let scale = 1.0 / (d as f64).sqrt();
            let at = |row: usize, tok: usize| x[off + row * n + tok] as f64;
            let mut want = vec![0f32; c * n];
            for h in 0..heads {
                for i in 0..n {
                    let logits: Vec<f64> = (0..n)
                        .map(|j| {
                            (0..d)
                                .map(|e| at(h * d + e, i) * scale * at(c + h * d + e, j))
                                .sum()
                        })
                        .collect();
                    let m = logits.iter().cloned().fold(f64::MIN, f64::max);
                    let w: Vec<f64> = logits.iter().map(|l| (l - m).exp()).collect();
                    let z: f64 = w.iter().sum();
                    for e in 0..d {
                        let v: f64 = (0..n).map(|j| w[j] * at(2 * c + h * d + e, j)).sum();
                        want[(h * d + e) * n + i] = (v / z) as f32;
                    }
                }
            }
            let xb = g.buffer_with("qkv", &x);
            let out = g.buffer("out", 4 * (2 + c * n) as u64);
            let step = ops
                .attention(heads, d, n, At::off(&xb, off), At::off(&out, 2))
                .unwrap();
            g.submit(&[step]);
            let got = g.read_f32(&out, 2 + c * n).unwrap();
            assert_close(
                &format!("attention {heads} heads x {d}, {n} tokens"),
                &want,
                &got[2..],
                ATTENTION_TOL,
            );
        }
    }

    /// The photo's resizes against the CPU path's `resize` (and normalisation): enlarging,
    /// shrinking by a little and by a lot (wide antialias windows), at offsets.
    #[test]
    fn resize_taps_match_the_cpu_resize() {
        use candle_core::{Device, Tensor};
        use gagavatar_ops::{resize, ResizeMode};
        let Some(g) = gpu() else { return };
        let t = crate::Tuning::default();
        let spare = g.buffer("spare", 16);
        let ops = ops(g, &t, &spare);
        let mut rng = Rng::new(5);
        let sizes = [(64, 70), (70, 20), (70, 5), (70, 70), (518, 19)];
        let tables = TapTables::new(g, &sizes, ResizeMode::Antialias);
        let norm: Normalize = ([0.4, 0.5, 0.6], [4.0, 4.5, 5.0]);
        for (k, &(h, oh)) in sizes.iter().enumerate() {
            let x: Vec<f32> = (0..3 * h * h).map(|_| rng.uniform() as f32).collect();
            let xt = Tensor::from_vec(x.clone(), (1, 3, h, h), &Device::Cpu).unwrap();
            let r = resize(&xt, oh, oh, ResizeMode::Antialias).unwrap();
            let plain: Vec<f32> = r.flatten_all().unwrap().to_vec1().unwrap();
            let normed: Vec<f32> = plain
                .iter()
                .enumerate()
                .map(|(i, v)| {
                    let c = i / (oh * oh);
                    (v - norm.0[c]) * norm.1[c]
                })
                .collect();
            let mut padded = vec![0f32; 5];
            padded.extend(&x);
            let xb = g.buffer_with("x", &padded);
            for (what, n, want) in [("plain", None, &plain), ("normalised", Some(norm), &normed)] {
                let out = g.buffer("y", 4 * (1 + 3 * oh * oh) as u64);
                let step = ops
                    .resize_taps(&tables, k, (3, h, oh), n, At::off(&xb, 5), At::off(&out, 1))
                    .unwrap();
                g.submit(&[step]);
                let got = g.read_f32(&out, 1 + 3 * oh * oh).unwrap();
                assert_close(
                    &format!("resize {h} -> {oh}, {what}"),
                    want,
                    &got[1..],
                    RESIZE_TOL,
                );
            }
        }
    }

    /// Sums of up to ~30 x 30 weighted values in another order than the CPU's separable passes.
    const RESIZE_TOL: f64 = 1e-5;
}
