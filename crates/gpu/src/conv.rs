//! The renderer's kernels as recordable steps: convolutions (with the fused epilogues the
//! StyleUNet needs), x2 resizes, sums, linear layers, the mapping network's normalisation and
//! the modulated convolutions' demodulation.

use std::sync::LazyLock;

use crate::device::Gpu;
use crate::error::{GpuError, Result};
use crate::kernel::{linear_grid, Bind, Grid, Params, Step};
use crate::tuning::{ConvTile, MmaTile, Tuning};

/// Both convolution shaders end in one shared epilogue.
fn with_epilogue(src: &str) -> String {
    format!("{src}\n{}", include_str!("shaders/conv_epilogue.wgsl"))
}
/// The two convolution kernels (f32 and tensor-core) share their parameters, buffers, im2col
/// read and output write.
fn with_io(src: &str) -> String {
    with_epilogue(&format!("{src}\n{}", include_str!("shaders/conv_io.wgsl")))
}
static CONV: LazyLock<String> = LazyLock::new(|| with_io(include_str!("shaders/conv.wgsl")));
static CONV_MMA: LazyLock<String> =
    LazyLock::new(|| with_io(include_str!("shaders/conv_mma.wgsl")));
static CONV_FINISH: LazyLock<String> =
    LazyLock::new(|| with_epilogue(include_str!("shaders/conv_finish.wgsl")));
const RESIZE: &str = include_str!("shaders/resize.wgsl");
const ADD: &str = include_str!("shaders/add.wgsl");
const LINEAR: &str = include_str!("shaders/linear.wgsl");
const RMS_NORM: &str = include_str!("shaders/rms_norm.wgsl");
const DEMOD: &str = include_str!("shaders/demod.wgsl");

/// A buffer and an offset into it, in f32 elements.
#[derive(Debug, Clone, Copy)]
pub struct At<'a> {
    pub buf: &'a wgpu::Buffer,
    pub off: u32,
}

impl<'a> At<'a> {
    pub fn new(buf: &'a wgpu::Buffer) -> Self {
        Self { buf, off: 0 }
    }
    pub fn off(buf: &'a wgpu::Buffer, off: usize) -> Self {
        Self {
            buf,
            off: off as u32,
        }
    }
}

/// One convolution of a `[cin, h, w]` image and its epilogue (see conv.wgsl). Offsets of the
/// per-channel vectors are into the shared `vecs` buffer.
#[derive(Debug, Clone, Copy)]
pub struct Conv<'a> {
    pub cin: usize,
    pub cout: usize,
    pub h: usize,
    pub w: usize,
    /// 1 or 3.
    pub k: usize,
    pub input: At<'a>,
    /// `[cout, cin, k, k]`
    pub weight: &'a wgpu::Buffer,
    pub bias: Option<u32>,
    pub in_scale: Option<u32>,
    pub out_scale: Option<u32>,
    /// `[h, w]` noise and its weight's offset in `vecs` (a trained scalar, so read from a
    /// buffer rather than baked into the recorded dispatch).
    pub noise: Option<(At<'a>, u32)>,
    /// ReLU of the input as it is read.
    pub in_relu: bool,
    pub act: Act,
    /// `[cout, h, w]` added after the activation.
    pub residual: Option<At<'a>>,
    /// SFT scale and shift maps `[cout, h, w]` (in one buffer).
    pub sft: Option<(&'a wgpu::Buffer, u32, u32)>,
    pub sigmoid: bool,
    pub out: At<'a>,
}

/// A convolution's (or linear layer's, `k` = 1) weight on the GPU, `[cout, cin k k]`, and its
/// bias's offset in the vector buffer.
pub struct ConvWeights {
    pub weight: wgpu::Buffer,
    pub bias: Option<u32>,
    pub cin: usize,
    pub cout: usize,
    pub k: usize,
}

impl<'a> Conv<'a> {
    /// `w` over `[cin, h, wd]` with its bias and nothing else in the epilogue (set the other
    /// fields with `Conv { act: .., ..Conv::plain(..) }`).
    pub fn plain(w: &'a ConvWeights, (h, wd): (usize, usize), input: At<'a>, out: At<'a>) -> Self {
        Conv {
            cin: w.cin,
            cout: w.cout,
            h,
            w: wd,
            k: w.k,
            input,
            weight: &w.weight,
            bias: w.bias,
            in_scale: None,
            out_scale: None,
            noise: None,
            in_relu: false,
            act: Act::None,
            residual: None,
            sft: None,
            sigmoid: false,
            out,
        }
    }
}

/// The activation of a convolution's epilogue.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum Act {
    #[default]
    None,
    /// Leaky ReLU with slope 0.2 (the renderer).
    Lrelu,
    Relu,
    /// GELU with erf (the ViT's MLP).
    Gelu,
}

impl Act {
    fn code(self) -> u32 {
        match self {
            Act::None => 0,
            Act::Lrelu => 1,
            Act::Relu => 2,
            Act::Gelu => 3,
        }
    }
}

/// Records the renderer's kernels; holds what all of them share.
pub struct Ops<'a> {
    pub gpu: &'a Gpu,
    pub tuning: &'a Tuning,
    /// Biases, styles and demodulation factors (see renderer.rs).
    pub vecs: &'a wgpu::Buffer,
    /// Bound where a kernel's optional input is absent.
    pub dummy: &'a wgpu::Buffer,
    /// Scratch for split-K partial sums, large enough for every layer that uses it.
    pub split_scratch: &'a wgpu::Buffer,
}

fn flag(b: bool) -> String {
    if b { "true" } else { "false" }.to_string()
}

/// The per-thread accumulators of a tile's `tm x tn` outputs, as scalar variables (written out
/// so that every compiler keeps them in registers).
pub(crate) fn micro_decl(t: ConvTile) -> String {
    let mut s = String::new();
    for i in 0..t.tm {
        for j in 0..t.tn {
            s += &format!("    var acc_{i}_{j} = 0.0;\n");
        }
    }
    s
}

/// One depth step of the micro-tile: `tm` weights times `tn` inputs, unrolled.
pub(crate) fn micro_body(t: ConvTile) -> String {
    let mut s = String::new();
    for i in 0..t.tm {
        s += &format!("            let a_{i} = As[ar + {i}u];\n");
    }
    for j in 0..t.tn {
        s += &format!("            let b_{j} = Bs[br + {j}u];\n");
    }
    for i in 0..t.tm {
        for j in 0..t.tn {
            s += &format!("            acc_{i}_{j} = fma(a_{i}, b_{j}, acc_{i}_{j});\n");
        }
    }
    s
}

pub(crate) fn micro_emit(t: ConvTile) -> String {
    let mut s = String::new();
    for i in 0..t.tm {
        for j in 0..t.tn {
            s += &format!("    emit(co0 + {i}u, pix0 + {j}u, acc_{i}_{j}, wid.z);\n");
        }
    }
    s
}

/// How a convolution is split: its tile and, for split-K, the depth per slice and the slice
/// count.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ConvPlan {
    pub tile: Tile,
    pub split: u32,
    pub slices: u32,
}

/// Which kernel and tile a convolution runs with.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Tile {
    /// conv.wgsl, f32.
    Simt(ConvTile),
    /// conv_mma.wgsl, f16 tensor cores with f32 sums.
    Mma(MmaTile),
}

impl Tile {
    /// Output rows (channels) and columns (pixels) per workgroup, depth step.
    fn dims(&self) -> (u32, u32, u32) {
        match self {
            Tile::Simt(t) => (t.bm, t.bn, t.bk),
            Tile::Mma(t) => (t.bm, t.bn, t.bk),
        }
    }
}

/// The plan for a layer: the small tile below 32x32 pixels; the tensor-core kernel where
/// `tuning.mma` (see [`Tuning::for_device`]), its tile fitted to few output channels; split-K where the layer's tiles alone would not
/// fill the device (fewer than 256 workgroups) and the depth is more than two slices.
pub fn plan(tuning: &Tuning, cin: usize, cout: usize, h: usize, w: usize, k: usize) -> ConvPlan {
    let small = h * w < 1024;
    let (tile, split) = match (tuning.mma, small) {
        (false, false) => (Tile::Simt(tuning.conv), tuning.conv_split_k),
        (false, true) => (Tile::Simt(tuning.conv_small), tuning.conv_split_k),
        (true, false) => (
            Tile::Mma(tuning.mma_tile.fitted(cout, tuning.mma_fit)),
            tuning.mma_split_k,
        ),
        (true, true) => (Tile::Mma(tuning.mma_small), tuning.mma_split_k),
    };
    let (bm, bn, bk) = tile.dims();
    let tiles = (h * w).div_ceil(bn as usize) * cout.div_ceil(bm as usize);
    let depth = cin * k * k;
    let split = split as usize;
    if split > 0 && tiles < 256 && depth > 2 * split {
        let split = split.next_multiple_of(bk as usize);
        ConvPlan {
            tile,
            split: split as u32,
            slices: depth.div_ceil(split) as u32,
        }
    } else {
        ConvPlan {
            tile,
            split: 0,
            slices: 1,
        }
    }
}

/// The generated parts of conv_mma.wgsl for a tile: the accumulators (from zeros in workgroup
/// memory), one 16-deep step of `fm x fn` multiply-adds, and the sums' way out (each block
/// stored to the subgroup's staging area, then through the epilogue).
fn mma_parts(t: MmaTile) -> [(&'static str, String); 6] {
    let (mut decl, mut step, mut store) = (String::new(), String::new(), String::new());
    for i in 0..t.fm {
        step += &format!(
            "            let a_{i} = coopLoadT<coop_mat16x16<f16, A>>(&As[(wm + {}u) * BK + kk], BK);\n",
            16 * i
        );
    }
    for j in 0..t.fn_ {
        step += &format!(
            "            let b_{j} = coopLoadT<coop_mat16x16<f16, B>>(&Bs[kk * BN + wn + {}u], BN);\n",
            16 * j
        );
    }
    for i in 0..t.fm {
        for j in 0..t.fn_ {
            decl +=
                &format!("    var c_{i}_{j} = coopLoadT<coop_mat16x16<f32, C>>(&Cs[cs], 16u);\n");
            step += &format!("            c_{i}_{j} = coopMultiplyAdd(a_{i}, b_{j}, c_{i}_{j});\n");
            store += &format!(
                "    workgroupBarrier();\n    coopStoreT(c_{i}_{j}, &Cs[cs], 16u);\n    workgroupBarrier();\n    \
                 for (var e = lane; e < 256u; e = e + 32u) {{\n        \
                 emit(m0 + wm + {}u + e / 16u, n0 + wn + {}u + e % 16u, Cs[cs + e], wid.z);\n    }}\n",
                16 * i,
                16 * j
            );
        }
    }
    let [reg_decl, reg_fetch, reg_store] = register_staging(t);
    [
        ("ACC_DECL", decl),
        ("MMA", step),
        ("STORE", store),
        ("REG_DECL", reg_decl),
        ("REG_FETCH", reg_fetch),
        ("REG_STORE", reg_store),
    ]
}

/// conv_mma.wgsl's prefetching staging for a tile, written out as scalars: each thread's
/// elements `t + i THREADS` of the weight and input tiles, their registers, the reads at depth
/// `kf` into them, and their stores to workgroup memory.
fn register_staging(t: MmaTile) -> [String; 3] {
    let threads = t.threads().max(1);
    let a_per = (t.bm * t.bk).div_ceil(threads);
    let b_per = (t.bk * t.bn).div_ceil(threads);
    let (mut decl, mut fetch, mut store) = (String::new(), String::new(), String::new());
    for i in 0..a_per {
        let off = i * threads;
        decl += &format!("        var ra_{i} = f16(0.0);\n");
        fetch += &format!("            ra_{i} = fetch_a(t + {off}u, m0, kf, k_hi);\n");
        store += &format!(
            "            if (t + {off}u < BM * BK) {{\n                As[t + {off}u] = ra_{i};\n            }}\n"
        );
    }
    for i in 0..b_per {
        let off = i * threads;
        decl += &format!("        var rb_{i} = f16(0.0);\n");
        fetch += &format!("            rb_{i} = fetch_b(t + {off}u, n0, kf, k_hi, b_y, b_x);\n");
        store += &format!(
            "            if (t + {off}u < BK * BN) {{\n                Bs[t + {off}u] = rb_{i};\n            }}\n"
        );
    }
    [decl, fetch, store]
}

/// A convolution's compile-time options (the epilogue's flags, see conv.wgsl).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Options {
    pub in_scale: bool,
    pub in_relu: bool,
    pub out_scale: bool,
    pub bias: bool,
    pub noise: bool,
    pub act: Act,
    pub resid: bool,
    pub sft: bool,
    pub sigmoid: bool,
}

impl Conv<'_> {
    pub fn options(&self) -> Options {
        Options {
            in_scale: self.in_scale.is_some(),
            in_relu: self.in_relu,
            out_scale: self.out_scale.is_some(),
            bias: self.bias.is_some(),
            noise: self.noise.is_some(),
            act: self.act,
            resid: self.residual.is_some(),
            sft: self.sft.is_some(),
            sigmoid: self.sigmoid,
        }
    }
}

/// The values substituted into conv.wgsl or conv_mma.wgsl for a tile, kernel size, split-K
/// depth (0 = none) and options.
pub fn conv_consts(tile: Tile, k: usize, split: u32, o: Options) -> Vec<(&'static str, String)> {
    let mut v: Vec<(&str, String)> = match tile {
        Tile::Simt(t) => vec![
            ("ACC_DECL", micro_decl(t)),
            ("MICRO", micro_body(t)),
            ("EMIT", micro_emit(t)),
            ("BM", t.bm.to_string()),
            ("BN", t.bn.to_string()),
            ("BK", t.bk.to_string()),
            ("TM", t.tm.to_string()),
            ("TN", t.tn.to_string()),
        ],
        Tile::Mma(t) => {
            let mut v = mma_parts(t).to_vec();
            v.extend([
                ("BM", t.bm.to_string()),
                ("BN", t.bn.to_string()),
                ("BK", t.bk.to_string()),
                ("FM", t.fm.to_string()),
                ("FN", t.fn_.to_string()),
                ("PREFETCH", flag(t.prefetch)),
            ]);
            v
        }
    };
    v.extend([
        ("KSIZE", k.to_string()),
        ("SPLIT", split.to_string()),
        ("IN_SCALE", flag(o.in_scale)),
        ("IN_RELU", flag(o.in_relu)),
        ("OUT_SCALE", flag(o.out_scale)),
        ("BIAS", flag(o.bias)),
        ("NOISE", flag(o.noise)),
        ("ACT", o.act.code().to_string()),
        ("RESID", flag(o.resid)),
        ("SFT", flag(o.sft)),
        ("SIGMOID", flag(o.sigmoid)),
    ]);
    v
}

/// conv_mma.wgsl with its values substituted (for checking it where no device runs it).
pub fn mma_source(t: MmaTile, k: usize, split: u32, o: Options) -> Result<String> {
    let body = crate::kernel::substitute(
        "conv_mma",
        &CONV_MMA,
        &conv_consts(Tile::Mma(t), k, split, o),
    )?;
    Ok(crate::kernel::module_source(&body))
}

impl Ops<'_> {
    /// Floats of split-K scratch a layer needs (0 when it is not split).
    pub fn split_need(
        tuning: &Tuning,
        cin: usize,
        cout: usize,
        h: usize,
        w: usize,
        k: usize,
    ) -> usize {
        let p = plan(tuning, cin, cout, h, w, k);
        if p.split > 0 {
            p.slices as usize * cout * h * w
        } else {
            0
        }
    }

    pub fn conv(&self, c: &Conv) -> Result<Vec<Step>> {
        if c.k != 1 && c.k != 3 {
            return Err(GpuError::Unsupported(format!(
                "{}x{} convolution",
                c.k, c.k
            )));
        }
        if c.noise.is_some() && c.residual.is_some() {
            return Err(GpuError::Unsupported(
                "a convolution with both noise and a residual".into(),
            ));
        }
        let p = plan(self.tuning, c.cin, c.cout, c.h, c.w, c.k);
        let need = 4 * p.slices as u64 * (c.cout * c.h * c.w) as u64;
        if p.split > 0 && need > self.split_scratch.size() {
            return Err(GpuError::Device(format!(
                "split-K scratch of {} bytes for a {}->{} {}x{} layer that needs {need}",
                self.split_scratch.size(),
                c.cin,
                c.cout,
                c.h,
                c.w
            )));
        }
        let (bm, bn, _) = p.tile.dims();
        let (name, name_split, source): (_, _, &str) = match p.tile {
            Tile::Simt(_) => ("conv", "conv_split", &CONV),
            Tile::Mma(_) => ("conv_mma", "conv_mma_split", &CONV_MMA),
        };
        let opts = c.options();
        let consts = |split: u32| conv_consts(p.tile, c.k, split, opts);
        let aux = c
            .noise
            .map(|(a, _)| a)
            .or(c.residual)
            .unwrap_or(At::new(self.dummy));
        let (sft_buf, sft_scale, sft_shift) = c.sft.unwrap_or((self.dummy, 0, 0));
        let params = |slices: u32| {
            Params::new()
                .u(c.cin as u32)
                .u(c.cout as u32)
                .u(c.h as u32)
                .u(c.w as u32)
                .u(c.input.off)
                .u(c.out.off)
                .u(c.bias.unwrap_or(0))
                .u(c.in_scale.unwrap_or(0))
                .u(c.out_scale.unwrap_or(0))
                .u(aux.off)
                .u(sft_scale)
                .u(sft_shift)
                .u(c.noise.map_or(0, |(_, w)| w))
                .u(slices)
        };
        let mut binds = vec![Bind::Uniform];
        binds.extend([Bind::Read; 5]);
        binds.push(Bind::ReadWrite);
        let grid_xy = [
            (c.h * c.w).div_ceil(bn as usize) as u32,
            c.cout.div_ceil(bm as usize) as u32,
        ];
        let note = format!("{}->{} {}x{} k{}", c.cin, c.cout, c.h, c.w, c.k);
        if p.split == 0 {
            let k = self.gpu.kernel(name, source, &consts(0), &binds)?;
            let u = self.gpu.uniform("conv", &params(1));
            let g = self.gpu.bind(
                &k,
                &[
                    &u,
                    c.input.buf,
                    c.weight,
                    self.vecs,
                    aux.buf,
                    sft_buf,
                    c.out.buf,
                ],
            )?;
            return Ok(vec![Step::new(
                k,
                g,
                Grid::Fixed([grid_xy[0], grid_xy[1], 1]),
            )
            .with_note(note)]);
        }
        let k = self
            .gpu
            .kernel(name_split, source, &consts(p.split), &binds)?;
        let u = self.gpu.uniform("conv split", &params(p.slices));
        let g = self.gpu.bind(
            &k,
            &[
                &u,
                c.input.buf,
                c.weight,
                self.vecs,
                self.dummy,
                self.dummy,
                self.split_scratch,
            ],
        )?;
        let mut fb = vec![Bind::Uniform];
        fb.extend([Bind::Read; 4]);
        fb.push(Bind::ReadWrite);
        let finish_consts: Vec<(&str, String)> = consts(0)
            .into_iter()
            .filter(|(n, _)| {
                matches!(
                    *n,
                    "OUT_SCALE" | "BIAS" | "NOISE" | "ACT" | "RESID" | "SFT" | "SIGMOID"
                )
            })
            .collect();
        let kf = self
            .gpu
            .kernel("conv_finish", &CONV_FINISH, &finish_consts, &fb)?;
        let gf = self.gpu.bind(
            &kf,
            &[
                &u,
                self.split_scratch,
                self.vecs,
                aux.buf,
                sft_buf,
                c.out.buf,
            ],
        )?;
        Ok(vec![
            Step::new(k, g, Grid::Fixed([grid_xy[0], grid_xy[1], p.slices]))
                .with_note(note.clone()),
            Step::new(kf, gf, linear_grid(c.cout * c.h * c.w, 256)).with_note(note),
        ])
    }

    /// x2 bilinear upsampling (`up`) or x0.5 (2x2 mean) of `[c, h, w]`.
    pub fn resize(
        &self,
        up: bool,
        c: usize,
        h: usize,
        w: usize,
        input: At,
        out: At,
    ) -> Result<Step> {
        let k = self.gpu.kernel(
            if up { "upsample" } else { "downsample" },
            RESIZE,
            &[("UP", flag(up))],
            &[Bind::Uniform, Bind::Read, Bind::ReadWrite],
        )?;
        let u = self.gpu.uniform(
            "resize",
            &Params::new()
                .u(c as u32)
                .u(h as u32)
                .u(w as u32)
                .u(input.off)
                .u(out.off),
        );
        let n = if up { 4 * c * h * w } else { c * h * w / 4 };
        let g = self.gpu.bind(&k, &[&u, input.buf, out.buf])?;
        Ok(Step::new(k, g, linear_grid(n, 256)))
    }

    /// `out = a + b` over `n` values (whole buffers).
    pub fn add(
        &self,
        n: usize,
        a: &wgpu::Buffer,
        b: &wgpu::Buffer,
        out: &wgpu::Buffer,
    ) -> Result<Step> {
        let k = self.gpu.kernel(
            "add",
            ADD,
            &[],
            &[Bind::Uniform, Bind::Read, Bind::Read, Bind::ReadWrite],
        )?;
        let u = self.gpu.uniform("add", &Params::new().u(n as u32));
        let g = self.gpu.bind(&k, &[&u, a, b, out])?;
        Ok(Step::new(k, g, linear_grid(n, 256)))
    }

    /// `out[o] = act(W x + b)` with `W` `[n_out, n_in]`.
    #[allow(clippy::too_many_arguments)]
    pub fn linear(
        &self,
        n_in: usize,
        n_out: usize,
        x: At,
        weight: &wgpu::Buffer,
        bias: &wgpu::Buffer,
        lrelu: bool,
        out: At,
    ) -> Result<Step> {
        self.linear_strided(n_in, n_out, (x, 1), weight, bias, lrelu, out)
    }

    /// [`Ops::linear`] reading `x` every `stride` values (a column of a channel-major
    /// activation).
    #[allow(clippy::too_many_arguments)]
    pub fn linear_strided(
        &self,
        n_in: usize,
        n_out: usize,
        (x, stride): (At, usize),
        weight: &wgpu::Buffer,
        bias: &wgpu::Buffer,
        lrelu: bool,
        out: At,
    ) -> Result<Step> {
        let k = self.gpu.kernel(
            "linear",
            LINEAR,
            &[],
            &[
                Bind::Uniform,
                Bind::Read,
                Bind::Read,
                Bind::Read,
                Bind::ReadWrite,
            ],
        )?;
        let u = self.gpu.uniform(
            "linear",
            &Params::new()
                .u(n_in as u32)
                .u(n_out as u32)
                .u(x.off)
                .u(out.off)
                .u(lrelu as u32)
                .u(stride as u32),
        );
        let g = self.gpu.bind(&k, &[&u, x.buf, weight, bias, out.buf])?;
        let gx = n_out.min(65535) as u32;
        let gy = n_out.div_ceil(65535) as u32;
        Ok(Step::new(k, g, Grid::Fixed([gx, gy, 1])))
    }

    /// `out = x / sqrt(mean(x^2) + 1e-8)` over `n` values.
    pub fn rms_norm(&self, n: usize, x: &wgpu::Buffer, out: &wgpu::Buffer) -> Result<Step> {
        let k = self.gpu.kernel(
            "rms_norm",
            RMS_NORM,
            &[],
            &[Bind::Uniform, Bind::Read, Bind::ReadWrite],
        )?;
        let u = self.gpu.uniform("rms", &Params::new().u(n as u32));
        let g = self.gpu.bind(&k, &[&u, x, out])?;
        Ok(Step::new(k, g, Grid::Fixed([1, 1, 1])))
    }

    /// `vecs[out + o] = gain / sqrt(sum_i vecs[style + i]^2 energy[o, i] + 1e-8)`.
    pub fn demod(
        &self,
        cin: usize,
        cout: usize,
        energy: &wgpu::Buffer,
        style_off: u32,
        out_off: u32,
        gain: f32,
    ) -> Result<Step> {
        let k = self.gpu.kernel(
            "demod",
            DEMOD,
            &[],
            &[Bind::Uniform, Bind::Read, Bind::ReadWrite],
        )?;
        let u = self.gpu.uniform(
            "demod",
            &Params::new()
                .u(cin as u32)
                .u(cout as u32)
                .u(style_off)
                .u(out_off)
                .f(gain),
        );
        let g = self.gpu.bind(&k, &[&u, energy, self.vecs])?;
        Ok(Step::new(k, g, Grid::Fixed([cout as u32, 1, 1])))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernel::record_all;
    use crate::testutil::{assert_close, gpu};
    use candle_core::{Device, Tensor};
    use gagavatar_splat::testscene::Rng;

    /// One layer in f32 against an f64 reference: sums of at most a few hundred products of
    /// values of order one.
    const LAYER_TOL: f64 = 2e-5;

    fn run(g: &Gpu, steps: &[Step]) {
        let mut enc = g
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: None });
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor::default());
            record_all(&mut pass, steps);
        }
        g.queue.submit([enc.finish()]);
    }

    fn rand(rng: &mut Rng, n: usize, lo: f64, hi: f64) -> Vec<f32> {
        (0..n).map(|_| rng.range(lo, hi) as f32).collect()
    }

    #[derive(Clone, Copy, Default)]
    struct Opts {
        bias: bool,
        in_scale: bool,
        out_scale: bool,
        noise: bool,
        in_relu: bool,
        act: Act,
        residual: bool,
        sft: bool,
        sigmoid: bool,
    }

    /// Where the tests keep the noise weight in `vecs` (past the other vectors).
    const NOISE_W_AT: u32 = 299;

    #[allow(clippy::too_many_arguments)]
    fn reference(
        x: &[f32],
        w: &[f32],
        vecs: &[f32],
        aux: &[f32],
        sft: &[f32],
        (cin, cout, h, wd, k): (usize, usize, usize, usize, usize),
        o: Opts,
        noise_w: f32,
    ) -> Vec<f32> {
        let hw = h * wd;
        let pad = (k / 2) as isize;
        let mut out = vec![0f32; cout * hw];
        for co in 0..cout {
            for py in 0..h {
                for px in 0..wd {
                    let mut acc = 0f64;
                    for ci in 0..cin {
                        let s = if o.in_scale {
                            vecs[100 + ci] as f64
                        } else {
                            1.0
                        };
                        for ky in 0..k {
                            for kx in 0..k {
                                let yy = py as isize + ky as isize - pad;
                                let xx = px as isize + kx as isize - pad;
                                if yy < 0 || xx < 0 || yy >= h as isize || xx >= wd as isize {
                                    continue;
                                }
                                let mut xv = x[7 + ci * hw + yy as usize * wd + xx as usize] as f64;
                                if o.in_relu {
                                    xv = xv.max(0.0);
                                }
                                acc += w[((co * cin + ci) * k + ky) * k + kx] as f64 * xv * s;
                            }
                        }
                    }
                    let p = py * wd + px;
                    let mut v = acc;
                    if o.out_scale {
                        v *= vecs[200 + co] as f64;
                    }
                    if o.bias {
                        v += vecs[co] as f64;
                    }
                    if o.noise {
                        v += noise_w as f64 * aux[3 + p] as f64;
                    }
                    v = match o.act {
                        Act::None => v,
                        Act::Lrelu => v.max(0.2 * v),
                        Act::Relu => v.max(0.0),
                        Act::Gelu => {
                            0.5 * v
                                * (1.0
                                    + candle_core::cpu::erf::erf_f64(v / std::f64::consts::SQRT_2))
                        }
                    };
                    if o.residual {
                        v += aux[3 + co * hw + p] as f64;
                    }
                    if o.sft {
                        v = v * sft[co * hw + p] as f64 + sft[(cout + co) * hw + p] as f64;
                    }
                    if o.sigmoid {
                        v = 1.0 / (1.0 + (-v).exp());
                    }
                    out[co * hw + p] = v as f32;
                }
            }
        }
        out
    }

    /// Every epilogue option, 1x1 and 3x3, sizes that are not whole tiles, input and output
    /// at offsets into their buffers, with and without split-K, and two tile shapes.
    #[test]
    fn convolutions_match_a_direct_reference() {
        let Some(g) = gpu() else { return };
        check_conv_cases(
            g,
            &[
                "",
                "conv_split_k=48",
                "conv_bm=16,conv_bn=32,conv_bk=8,conv_tm=4,conv_tn=2,conv_small_bm=32,\
                 conv_small_bn=8,conv_small_tm=2,conv_small_tn=2",
            ],
            LAYER_TOL,
        );
    }

    /// The tensor-core kernel (f16 inputs, f32 sums): the same cases, where the device has
    /// cooperative matrices (not lavapipe: there `mma_kernel_is_valid_wgsl_and_spirv` is what
    /// checks it).
    #[test]
    fn mma_convolutions_match_a_direct_reference() {
        let Some(g) = crate::testutil::mma_gpu() else {
            return;
        };
        check_conv_cases(
            g,
            &[
                "mma=1",
                "mma=1,mma_fit=0,mma_prefetch=0,mma_small_prefetch=0",
                "mma=1,mma_prefetch=0,mma_small_prefetch=0",
                "mma=1,mma_fit=0",
                "mma=1,mma_split_k=64",
                "mma=1,mma_bm=32,mma_bn=64,mma_fm=1,mma_fn=2,mma_small_bm=32,mma_small_bn=16,\
                 mma_small_fm=1,mma_small_fn=1,mma_bk=16,mma_small_bk=48",
            ],
            MMA_TOL,
        );
    }

    /// f16 inputs: each product carries two roundings of 2^-11 relative; over up to 576
    /// products of order 0.1 and the epilogue's scales, a few 1e-3 at worst.
    const MMA_TOL: f64 = 1e-2;

    /// The generated tensor-core WGSL parses, validates (f16 and cooperative matrices
    /// allowed) and translates to SPIR-V, for each option and tile shape.
    #[test]
    fn mma_kernel_is_valid_wgsl_and_spirv() {
        use naga::valid::{Capabilities, ValidationFlags, Validator};
        let all = Options {
            in_scale: true,
            in_relu: true,
            out_scale: true,
            bias: true,
            noise: true,
            act: Act::Lrelu,
            resid: false,
            sft: true,
            sigmoid: true,
        };
        let resid = Options {
            resid: true,
            ..Options::default()
        };
        let t = Tuning::default();
        let other = MmaTile {
            bm: 32,
            bn: 64,
            bk: 16,
            fm: 1,
            fn_: 2,
            prefetch: false,
        };
        let big = MmaTile {
            bm: 128,
            bn: 128,
            bk: 32,
            fm: 2,
            fn_: 2,
            prefetch: true,
        };
        for (tile, k, split, o) in [
            (big, 3, 0, all),
            (t.mma_tile, 3, 0, all),
            (t.mma_tile, 1, 0, resid),
            (
                t.mma_tile,
                1,
                0,
                Options {
                    act: Act::Gelu,
                    ..resid
                },
            ),
            (t.mma_small, 3, 288, Options::default()),
            (other, 3, 0, all),
            (t.mma_tile.fitted(16, true), 3, 0, all),
            (t.mma_tile.fitted(32, true), 1, 0, resid),
            (
                MmaTile {
                    prefetch: false,
                    ..t.mma_tile.fitted(16, true)
                },
                3,
                144,
                all,
            ),
        ] {
            let src = mma_source(tile, k, split, o).unwrap();
            let module = naga::front::wgsl::parse_str(&src)
                .unwrap_or_else(|e| panic!("{tile:?} k{k}: {}", e.emit_to_string(&src)));
            let caps = Capabilities::SHADER_FLOAT16 | Capabilities::COOPERATIVE_MATRIX;
            let info = Validator::new(ValidationFlags::all(), caps)
                .validate(&module)
                .unwrap_or_else(|e| panic!("{tile:?} k{k}: {}", e.emit_to_string(&src)));
            let spv = naga::back::spv::write_vec(
                &module,
                &info,
                &naga::back::spv::Options::default(),
                None,
            )
            .unwrap_or_else(|e| panic!("{tile:?} k{k}: SPIR-V: {e}"));
            assert!(spv.len() > 100, "{tile:?}: {} words of SPIR-V", spv.len());
        }
    }

    fn check_conv_cases(g: &Gpu, tunes: &[&str], tol: f64) {
        let mut rng = Rng::new(21);
        let all = Opts {
            bias: true,
            in_scale: true,
            out_scale: true,
            noise: true,
            in_relu: false,
            act: Act::Lrelu,
            residual: false,
            sft: true,
            sigmoid: false,
        };
        let cases = [
            (
                3,
                5,
                5,
                7,
                3,
                Opts {
                    bias: true,
                    ..Opts::default()
                },
            ),
            (16, 8, 16, 16, 1, all),
            (9, 33, 12, 10, 3, all),
            (
                20,
                4,
                40,
                40,
                3,
                Opts {
                    act: Act::Lrelu,
                    residual: true,
                    bias: true,
                    ..Opts::default()
                },
            ),
            (
                12,
                9,
                9,
                11,
                3,
                Opts {
                    in_relu: true,
                    act: Act::Relu,
                    residual: true,
                    bias: true,
                    ..Opts::default()
                },
            ),
            (
                40,
                17,
                1,
                37,
                1,
                Opts {
                    act: Act::Gelu,
                    out_scale: true,
                    bias: true,
                    ..Opts::default()
                },
            ),
            (
                6,
                3,
                8,
                8,
                1,
                Opts {
                    residual: true,
                    sigmoid: true,
                    in_scale: true,
                    bias: true,
                    ..Opts::default()
                },
            ),
            (64, 24, 4, 4, 3, all),
            // 17..=32 output channels over 1024 pixels: the tensor cores' tile fitted to 32 rows
            // (the 20 -> 4 layer above takes the 16-row one).
            (24, 20, 33, 35, 3, all),
        ];
        for tune in tunes {
            let mut t = Tuning::default();
            t.apply(tune).unwrap();
            t.check(&g.limits).unwrap();
            for &(cin, cout, h, w, k, o) in &cases {
                let hw = h * w;
                let mut x = vec![0f32; 7];
                x.extend(rand(&mut rng, cin * hw, -1.0, 1.0));
                let wt = rand(&mut rng, cout * cin * k * k, -0.3, 0.3);
                let vecs = rand(&mut rng, 300, 0.5, 1.5);
                let aux = rand(&mut rng, 3 + cout * hw, -1.0, 1.0);
                let sft = rand(&mut rng, 2 * cout * hw, -1.0, 1.0);
                let want = reference(
                    &x,
                    &wt,
                    &vecs,
                    &aux,
                    &sft,
                    (cin, cout, h, w, k),
                    o,
                    vecs[NOISE_W_AT as usize],
                );
                let (xb, wb, vb, ab, sb) = (
                    g.buffer_with("x", &x),
                    g.buffer_with("w", &wt),
                    g.buffer_with("v", &vecs),
                    g.buffer_with("a", &aux),
                    g.buffer_with("s", &sft),
                );
                let out = g.buffer("y", 4 * (5 + cout * hw) as u64);
                let dummy = g.buffer("d", 16);
                let scratch = g.buffer(
                    "split",
                    4 * Ops::split_need(&t, cin, cout, h, w, k).max(1) as u64,
                );
                let ops = Ops {
                    gpu: g,
                    tuning: &t,
                    vecs: &vb,
                    dummy: &dummy,
                    split_scratch: &scratch,
                };
                let steps = ops
                    .conv(&Conv {
                        cin,
                        cout,
                        h,
                        w,
                        k,
                        input: At::off(&xb, 7),
                        weight: &wb,
                        bias: o.bias.then_some(0),
                        in_scale: o.in_scale.then_some(100),
                        out_scale: o.out_scale.then_some(200),
                        noise: o.noise.then_some((At::off(&ab, 3), NOISE_W_AT)),
                        in_relu: o.in_relu,
                        act: o.act,
                        residual: o.residual.then_some(At::off(&ab, 3)),
                        sft: o.sft.then_some((&sb, 0, (cout * hw) as u32)),
                        sigmoid: o.sigmoid,
                        out: At::off(&out, 5),
                    })
                    .unwrap();
                run(g, &steps);
                let got = g.read_f32(&out, 5 + cout * hw).unwrap();
                assert_close(
                    &format!("conv {cin}->{cout} {h}x{w} k{k} [{tune}]"),
                    &want,
                    &got[5..],
                    tol,
                );
            }
        }
    }

    #[test]
    fn resizes_match_the_cpu() {
        use gagavatar_net::style_unet::{downsample2x, upsample2x};
        let Some(g) = gpu() else { return };
        let mut rng = Rng::new(4);
        let t = Tuning::default();
        let d = g.buffer("d", 16);
        let ops = Ops {
            gpu: g,
            tuning: &t,
            vecs: &d,
            dummy: &d,
            split_scratch: &d,
        };
        for (c, h, w) in [(3, 4, 4), (5, 6, 10), (2, 32, 32)] {
            let x = rand(&mut rng, c * h * w, -1.0, 1.0);
            let xt = Tensor::from_slice(&x, (1, c, h, w), &Device::Cpu).unwrap();
            for up in [true, false] {
                let want: Vec<f32> = if up {
                    upsample2x(&xt)
                } else {
                    downsample2x(&xt)
                }
                .unwrap()
                .flatten_all()
                .unwrap()
                .to_vec1()
                .unwrap();
                let xb = g.buffer_with("x", &x);
                let yb = g.buffer("y", 4 * want.len() as u64);
                run(
                    g,
                    &[ops.resize(up, c, h, w, At::new(&xb), At::new(&yb)).unwrap()],
                );
                let got = g.read_f32(&yb, want.len()).unwrap();
                assert_close(&format!("resize up={up} {c}x{h}x{w}"), &want, &got, 1e-6);
            }
        }
    }

    /// Linear layers (with and without the activation, more outputs than one dispatch row),
    /// the mapping network's normalisation and the demodulation, against f64 loops.
    #[test]
    fn vector_kernels_match_a_reference() {
        let Some(g) = gpu() else { return };
        let mut rng = Rng::new(8);
        let t = Tuning::default();
        let d = g.buffer("d", 16);
        for (n_in, n_out, act) in [(5, 3, false), (8, 70_000, true), (4096, 17, false)] {
            let x = rand(&mut rng, n_in + 2, -1.0, 1.0);
            let w = rand(&mut rng, n_in * n_out, -0.1, 0.1);
            let b = rand(&mut rng, n_out, -0.5, 0.5);
            let want: Vec<f32> = (0..n_out)
                .map(|o| {
                    let s: f64 = (0..n_in)
                        .map(|i| w[o * n_in + i] as f64 * x[2 + i] as f64)
                        .sum::<f64>()
                        + b[o] as f64;
                    (if act { s.max(0.2 * s) } else { s }) as f32
                })
                .collect();
            let (xb, wb, bb) = (
                g.buffer_with("x", &x),
                g.buffer_with("w", &w),
                g.buffer_with("b", &b),
            );
            let yb = g.buffer("y", 4 * (n_out + 1) as u64);
            let ops = Ops {
                gpu: g,
                tuning: &t,
                vecs: &d,
                dummy: &d,
                split_scratch: &d,
            };
            run(
                g,
                &[ops
                    .linear(n_in, n_out, At::off(&xb, 2), &wb, &bb, act, At::off(&yb, 1))
                    .unwrap()],
            );
            let got = g.read_f32(&yb, n_out + 1).unwrap();
            assert_close(
                &format!("linear {n_in}->{n_out}"),
                &want,
                &got[1..],
                LAYER_TOL,
            );
        }
        let x = rand(&mut rng, 300, -2.0, 2.0);
        let ms = x.iter().map(|&v| (v as f64).powi(2)).sum::<f64>() / 300.0;
        let want: Vec<f32> = x
            .iter()
            .map(|&v| (v as f64 / (ms + 1e-8).sqrt()) as f32)
            .collect();
        let (xb, yb) = (g.buffer_with("x", &x), g.buffer("y", 1200));
        let ops = Ops {
            gpu: g,
            tuning: &t,
            vecs: &d,
            dummy: &d,
            split_scratch: &d,
        };
        run(g, &[ops.rms_norm(300, &xb, &yb).unwrap()]);
        assert_close("rms norm", &want, &g.read_f32(&yb, 300).unwrap(), 1e-6);
        let (cin, cout) = (130, 9);
        let energy = rand(&mut rng, cin * cout, 0.0, 2.0);
        let mut vecs = rand(&mut rng, 10 + cin, -1.0, 1.0);
        vecs.extend(vec![0f32; cout]);
        let want: Vec<f32> = (0..cout)
            .map(|o| {
                let s: f64 = (0..cin)
                    .map(|i| (vecs[10 + i] as f64).powi(2) * energy[o * cin + i] as f64)
                    .sum();
                (1.4 / (s + 1e-8).sqrt()) as f32
            })
            .collect();
        let vb = g.buffer_with("v", &vecs);
        let eb = g.buffer_with("e", &energy);
        let ops = Ops {
            gpu: g,
            tuning: &t,
            vecs: &vb,
            dummy: &d,
            split_scratch: &d,
        };
        run(
            g,
            &[ops
                .demod(cin, cout, &eb, 10, (10 + cin) as u32, 1.4)
                .unwrap()],
        );
        let got = g.read_f32(&vb, 10 + cin + cout).unwrap();
        assert_close("demodulation", &want, &got[10 + cin..], LAYER_TOL);
    }
}
