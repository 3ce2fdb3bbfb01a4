//! The DPT head (spec section 4, `base_model.*` outside the backbone) on the GPU: per level a
//! 1x1 projection of the ViT tokens, the resize (a transposed convolution whose stride is its
//! kernel as a 1x1 product + pixel spread; identity; a 3x3 stride-2 convolution as im2col + a
//! 1x1 product), `layer_rn` over the photo at the level's size and the features; then the four
//! fusion blocks (pre-activation residual units with the ReLU read in the convolution's input
//! and the residual in its epilogue, align-corners resizing, the 1x1 out conv) and the output
//! convolution into F_local.

use gagavatar_net::config::DIR_ENCODING_DIM;
use gagavatar_net::ModelConfig;

use super::parts::{Ctx, Loader};
use crate::conv::{Act, At, Conv, ConvWeights};
use crate::device::Gpu;
use crate::error::Result;
use crate::kernel::Step;

const PREFIX: &str = "base_model";

enum ResizeW {
    /// The product weight `[cout k k, cin]` (bias in the vector buffer) and `k`.
    Up(ConvWeights, u32, usize),
    Identity,
    Down(ConvWeights),
}

struct LevelW {
    project: ConvWeights,
    resize: ResizeW,
    layer_rn: ConvWeights,
}

struct UnitW {
    conv1: ConvWeights,
    conv2: ConvWeights,
}

struct FusionW {
    unit1: UnitW,
    unit2: UnitW,
    out_conv: ConvWeights,
}

pub(crate) struct DptWeights {
    levels: Vec<LevelW>,
    refinenet: Vec<FusionW>,
    output_conv: ConvWeights,
}

impl DptWeights {
    pub fn load(ld: &mut Loader, cfg: &ModelConfig) -> Result<Self> {
        let (c, f) = (cfg.vit_dim, cfg.dpt_features);
        let mut levels = Vec::with_capacity(4);
        for (k, &ck) in cfg.dpt_channels.iter().enumerate() {
            let project = ld.conv(&format!("{PREFIX}.projects.{k}"), c, ck, 1, true)?;
            let key = format!("{PREFIX}.resize_layers.{k}");
            let resize = match k {
                0 | 1 => {
                    let kk = if k == 0 { 4 } else { 2 };
                    let taps = kk * kk;
                    // `[cin, cout, k, k]` -> `[cout k k, cin]`: output row (co, tap).
                    let w = ld.get(&format!("{key}.weight"), ck * ck * taps)?;
                    let mut wr = vec![0f32; w.len()];
                    for ci in 0..ck {
                        for co in 0..ck {
                            for t in 0..taps {
                                wr[(co * taps + t) * ck + ci] = w[(ci * ck + co) * taps + t];
                            }
                        }
                    }
                    let bias = ld.get(&format!("{key}.bias"), ck)?;
                    let lw = ConvWeights {
                        weight: ld.gpu.buffer_with(&key, &wr),
                        bias: None,
                        cin: ck,
                        cout: ck * taps,
                        k: 1,
                    };
                    ResizeW::Up(lw, ld.push(&bias), kk)
                }
                2 => ResizeW::Identity,
                // 3x3, stride 2: `[cout, cin 9]` is already the weight of the product with
                // the im2col matrix.
                _ => ResizeW::Down(ld.conv(&key, 9 * ck, ck, 1, true)?),
            };
            let layer_rn = ld.conv(&format!("{PREFIX}.layer_rn.{k}"), 3 + ck, f, 3, false)?;
            levels.push(LevelW {
                project,
                resize,
                layer_rn,
            });
        }
        let mut refinenet = Vec::with_capacity(4);
        for j in 0..4 {
            let r = format!("{PREFIX}.refinenet.{j}");
            let mut unit = |u: usize| -> Result<UnitW> {
                Ok(UnitW {
                    conv1: ld.conv(&format!("{r}.resConfUnit{u}.conv1"), f, f, 3, true)?,
                    conv2: ld.conv(&format!("{r}.resConfUnit{u}.conv2"), f, f, 3, true)?,
                })
            };
            let unit1 = unit(1)?;
            let unit2 = unit(2)?;
            refinenet.push(FusionW {
                unit1,
                unit2,
                out_conv: ld.conv(&format!("{r}.out_conv"), f, f, 1, true)?,
            });
        }
        let output_conv = ld.conv(&format!("{PREFIX}.output_conv"), f, f, 3, true)?;
        Ok(Self {
            levels,
            refinenet,
            output_conv,
        })
    }
}

/// DPT's activations. `f_local` holds F_local `[F, S, S]` followed by room for the direction
/// encoding's `DIR_ENCODING_DIM` planes (the generators' input).
pub struct GpuDpt {
    f: usize,
    g: usize,
    channels: [usize; 4],
    sizes: [usize; 4],
    plane: usize,
    projected: [wgpu::Buffer; 4],
    up: [wgpu::Buffer; 4],
    /// `[3 + c_k, s_k, s_k]`: the photo at the level's size (uploaded), then the features.
    pub levels: [wgpu::Buffer; 4],
    rn: [wgpu::Buffer; 4],
    temps: [wgpu::Buffer; 4],
    upsampled: wgpu::Buffer,
    fused: [wgpu::Buffer; 4],
    pub f_local: wgpu::Buffer,
}

impl GpuDpt {
    pub fn new(gpu: &Gpu, cfg: &ModelConfig) -> Self {
        let f = cfg.dpt_features;
        let g = cfg.grid();
        let channels = cfg.dpt_channels;
        let sizes = [0, 1, 2, 3].map(|k| cfg.dpt_level_size(k));
        let s = cfg.plane_size();
        let buf = |label: &str, len: usize| gpu.buffer(label, 4 * len as u64);
        let ups = [16, 4, 0, 9];
        let big = f * sizes[0] * sizes[0];
        Self {
            f,
            g,
            channels,
            sizes,
            plane: s,
            projected: [0, 1, 2, 3].map(|k| buf("dpt projected", channels[k] * g * g)),
            up: [0, 1, 2, 3].map(|k| {
                let cols = if k == 3 { sizes[3] * sizes[3] } else { g * g };
                buf("dpt resize product", ups[k] * channels[k] * cols)
            }),
            levels: [0, 1, 2, 3].map(|k| buf("dpt level", (3 + channels[k]) * sizes[k] * sizes[k])),
            rn: [0, 1, 2, 3].map(|k| buf("dpt layer_rn", f * sizes[k] * sizes[k])),
            temps: [0, 1, 2, 3].map(|_| buf("dpt fusion scratch", big)),
            upsampled: buf("dpt fusion upsampled", 4 * big),
            fused: [0, 1, 2, 3].map(|j| {
                let side = if j == 3 { s } else { sizes[2 - j] };
                buf("dpt fused", f * side * side)
            }),
            f_local: buf("F_local + encoding", (f + DIR_ENCODING_DIM) * s * s),
        }
    }

    pub(crate) fn record(
        &self,
        ctx: &Ctx,
        w: &DptWeights,
        tokens: &[wgpu::Buffer; 4],
    ) -> Result<Vec<Step>> {
        let ops = ctx.ops();
        let g = self.g;
        let mut steps = Vec::new();
        for (k, lw) in w.levels.iter().enumerate() {
            let (ck, sk) = (self.channels[k], self.sizes[k]);
            let level = &self.levels[k];
            let feat = At::off(level, 3 * sk * sk);
            let project_to = match lw.resize {
                ResizeW::Identity => feat,
                _ => At::new(&self.projected[k]),
            };
            steps.extend(ctx.conv(&Conv::plain(
                &lw.project,
                (g, g),
                At::new(&tokens[k]),
                project_to,
            ))?);
            match &lw.resize {
                ResizeW::Up(product, bias, kk) => {
                    steps.extend(ctx.conv(&Conv::plain(
                        product,
                        (g, g),
                        At::new(&self.projected[k]),
                        At::new(&self.up[k]),
                    ))?);
                    steps.push(ops.shuffle((ck, g, *kk), *bias, At::new(&self.up[k]), feat)?);
                }
                ResizeW::Identity => {}
                ResizeW::Down(product) => {
                    let (step, oh, ow) = ops.im2col(
                        (ck, g, g),
                        3,
                        2,
                        1,
                        At::new(&self.projected[k]),
                        At::new(&self.up[k]),
                    )?;
                    debug_assert_eq!((oh, ow), (sk, sk));
                    steps.push(step);
                    steps.extend(ctx.conv(&Conv::plain(
                        product,
                        (1, sk * sk),
                        At::new(&self.up[k]),
                        feat,
                    ))?);
                }
            }
            steps.extend(ctx.conv(&Conv::plain(
                &lw.layer_rn,
                (sk, sk),
                At::new(level),
                At::new(&self.rn[k]),
            ))?);
        }
        let s = self.sizes;
        // (input, skip, input side, output side) of refinenet.0 .. refinenet.3.
        let plan: [(&wgpu::Buffer, Option<&wgpu::Buffer>, usize, usize); 4] = [
            (&self.rn[3], None, s[3], s[2]),
            (&self.fused[0], Some(&self.rn[2]), s[2], s[1]),
            (&self.fused[1], Some(&self.rn[1]), s[1], s[0]),
            (&self.fused[2], Some(&self.rn[0]), s[0], 2 * s[0]),
        ];
        for (j, (fw, (a, skip, si, so))) in w.refinenet.iter().zip(plan).enumerate() {
            steps.extend(self.fusion(ctx, fw, a, skip, (si, so), &self.fused[j])?);
        }
        let p = self.plane;
        steps.extend(ctx.conv(&Conv::plain(
            &w.output_conv,
            (p, p),
            At::new(&self.fused[3]),
            At::new(&self.f_local),
        ))?);
        Ok(steps)
    }

    /// `x + conv2(relu(conv1(relu(x))))` into `out`, through `t`.
    fn unit(
        &self,
        ctx: &Ctx,
        u: &UnitW,
        side: usize,
        x: &wgpu::Buffer,
        t: &wgpu::Buffer,
        out: &wgpu::Buffer,
    ) -> Result<Vec<Step>> {
        let mut steps = ctx.conv(&Conv {
            in_relu: true,
            act: Act::Relu,
            ..Conv::plain(&u.conv1, (side, side), At::new(x), At::new(t))
        })?;
        steps.extend(ctx.conv(&Conv {
            residual: Some(At::new(x)),
            ..Conv::plain(&u.conv2, (side, side), At::new(t), At::new(out))
        })?);
        Ok(steps)
    }

    fn fusion(
        &self,
        ctx: &Ctx,
        fw: &FusionW,
        a: &wgpu::Buffer,
        skip: Option<&wgpu::Buffer>,
        (si, so): (usize, usize),
        out: &wgpu::Buffer,
    ) -> Result<Vec<Step>> {
        let [t0, t1, t2, t3] = &self.temps;
        let mut steps = Vec::new();
        let mut cur = a;
        if let Some(skip) = skip {
            steps.extend(self.unit(ctx, &fw.unit1, si, skip, t0, t1)?);
            steps.push(ctx.ops().add(self.f * si * si, a, t1, t2)?);
            cur = t2;
        }
        steps.extend(self.unit(ctx, &fw.unit2, si, cur, t0, t3)?);
        steps.push(ctx.ops().resize_to(
            (self.f, si, si),
            (so, so),
            At::new(t3),
            At::new(&self.upsampled),
        )?);
        steps.extend(ctx.conv(&Conv::plain(
            &fw.out_conv,
            (so, so),
            At::new(&self.upsampled),
            At::new(out),
        ))?);
        Ok(steps)
    }

    /// F_local `[F, S, S]` read back.
    pub fn download(&self, gpu: &Gpu) -> Result<Vec<f32>> {
        gpu.read_f32(&self.f_local, self.f * self.plane * self.plane)
    }
}
