//! `gagavatar convert`, `init-weights` and `dump`: getting weights in and proving parity.

use std::borrow::Cow;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use candle_core::{Device, Tensor};
use clap::Args;
use gagavatar_flame::{FlameModel, TrackedFrame};
use gagavatar_formats::image::DecodeOptions;
use gagavatar_net::checkpoint::{
    self, check_keys, read_weights, write_safetensors, write_tensors, write_torch_checkpoint,
};
use gagavatar_net::style_unet::Noise;
use gagavatar_net::ModelConfig;

pub fn preset(name: &str) -> Result<ModelConfig> {
    ModelConfig::preset(name).with_context(|| {
        format!(
            "unknown preset `{name}` (choose one of {})",
            ModelConfig::PRESETS.join(", ")
        )
    })
}

#[derive(Debug, Args)]
#[command(
    after_help = "Examples:\n  gagavatar convert GAGAvatar.pt gagavatar.safetensors\n  gagavatar convert trained.safetensors trained.pt   # loads in the release Python code"
)]
pub struct ConvertArgs {
    /// The release checkpoint (torch zip) or a safetensors file.
    input: PathBuf,
    /// Output: a `.pt`/`.pth` name writes a torch checkpoint in the release layout
    /// (`{"model": state_dict, "meta_cfg": config}`, for `torch.load`); any other name writes
    /// safetensors (same keys; the configuration is stored in its metadata).
    output: PathBuf,
    /// Architecture of the weights (`release`, `small`, `tiny`); default: from the file, else release.
    #[arg(long)]
    preset: Option<String>,
}

pub fn run_convert(a: ConvertArgs) -> Result<()> {
    let explicit = a.preset.as_deref().map(preset).transpose()?;
    let weights =
        read_weights(&a.input).with_context(|| format!("reading {}", a.input.display()))?;
    let cfg = checkpoint::resolve_config(&weights, explicit.as_ref());
    check_keys(&cfg, &weights.tensors)?;
    let tensors: BTreeMap<String, Tensor> = weights.tensors.into_iter().collect();
    let torch = a
        .output
        .extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| e.eq_ignore_ascii_case("pt") || e.eq_ignore_ascii_case("pth"));
    if torch {
        write_torch_checkpoint(&a.output, &tensors, Some(&cfg))?;
    } else {
        write_tensors(&a.output, &tensors, Some(&cfg))?;
    }
    eprintln!(
        "wrote {} ({} tensors, `{}` architecture)",
        a.output.display(),
        tensors.len(),
        cfg.name
    );
    Ok(())
}

#[derive(Debug, Args)]
#[command(
    after_help = "Example:\n  gagavatar init-weights --preset tiny --seed 1 -o tiny.safetensors"
)]
pub struct InitWeightsArgs {
    /// Architecture: release, small or tiny.
    #[arg(long, default_value = "release")]
    preset: String,
    /// Seed; each key draws from its own stream, so the same seed gives the same values.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Output safetensors (release key layout, configuration in the metadata).
    #[arg(short, long)]
    output: PathBuf,
}

pub fn run_init_weights(a: InitWeightsArgs) -> Result<()> {
    let cfg = preset(&a.preset)?;
    let w = checkpoint::init_weights(&cfg, a.seed)?;
    let n: usize = w.values().map(|(_, v)| v.len()).sum();
    write_safetensors(
        &a.output,
        w.iter()
            .map(|(k, (s, v))| (k.clone(), s.as_slice(), Cow::Borrowed(v.as_slice()))),
        Some(&cfg),
    )?;
    eprintln!(
        "wrote {} ({} tensors, {:.1} M values, preset {}, seed {})",
        a.output.display(),
        w.len(),
        n as f64 / 1e6,
        cfg.name,
        a.seed
    );
    Ok(())
}

/// Reads an RGB image as `[1, 3, size, size]` in [0, 1], resizing (antialiased bilinear) when
/// its size differs.
/// Decodes a source photo (large ones downscaled while decoding), saying so when it is not
/// `size` square: the library resizes it (antialiased) to the model's input.
pub fn read_rgb(path: &Path, size: usize) -> Result<image::RgbImage> {
    let opts = DecodeOptions {
        min_side: 1,
        fit_within: Some((4 * size) as u32),
    };
    let img = gagavatar_formats::image::read_image(path, &opts)?.rgb;
    let (w, h) = (img.width() as usize, img.height() as usize);
    if h != size || w != size {
        eprintln!(
            "note: resizing {} from {w}x{h} to {size}x{size}",
            path.display()
        );
    }
    Ok(img)
}

/// [`read_rgb`] as the model's input tensor `[1, 3, size, size]`.
pub fn read_image(path: &Path, size: usize) -> Result<Tensor> {
    Ok(gagavatar_avatar::image_tensor(
        &read_rgb(path, size)?,
        size,
    )?)
}

pub use gagavatar_avatar::SYNTHETIC_FLAME;

/// A FLAME asset by its command-line name (`synthetic`, or a path).
pub fn load_flame(path: &Path, n_shape: usize, n_exp: usize) -> Result<FlameModel> {
    let source = gagavatar_avatar::FlameSource::from_arg(path);
    Ok(gagavatar_avatar::load_flame(&source, n_shape, n_exp)
        .map_err(with_flag_hints)?
        .0)
}

/// The library's error, with the command-line flags that fix it named where they exist.
pub fn with_flag_hints(e: gagavatar_avatar::AvatarError) -> anyhow::Error {
    match e {
        gagavatar_avatar::AvatarError::FlameAsset {
            path,
            n_shape,
            n_exp,
            source,
        } => anyhow::Error::new(*source).context(format!(
            "loading FLAME {} as {n_shape} shape + {n_exp} expression components (--n-shape, \
             --n-exp)",
            path.display()
        )),
        other => other.into(),
    }
}

pub fn transform_tensor(record: &TrackedFrame, which: &str) -> Result<Tensor> {
    let tm = record
        .transform_matrix
        .with_context(|| format!("the {which} record has no transform_matrix"))?;
    let flat: Vec<f32> = tm.iter().flatten().map(|&x| x as f32).collect();
    Ok(Tensor::from_vec(flat, (1, 3, 4), &Device::Cpu)?)
}

/// FLAME vertices `[1, V, 3]` (x5) for the target's expression, jaw and eyes with the source's
/// identity (spec section 10).
pub fn target_vertices(
    flame: &FlameModel,
    source: &TrackedFrame,
    target: &TrackedFrame,
) -> Result<Tensor> {
    let mut rec = target.clone();
    rec.shapecode = source.shapecode.clone();
    let out = flame.forward(&rec.params(flame)?)?;
    Ok(out.vertices)
}

#[derive(Debug, Args)]
#[command(
    after_help = "Writes every stage with batch dim 1: source_image, source_transform, input_518, \
dino_0..3, f_id, f_local, plane_points, plane_dir, dir_encoding, target_points, target_transform, \
gs_xyz, gs_colors, gs_opacities, gs_scales, gs_rotations, coarse, fine. Compare with \
`python3 tools/reference/net_reference.py compare --weights W --dump D`.\n\n\
Example:\n  gagavatar dump --ckpt GAGAvatar.pt --flame FLAME_with_eye.pt --source src.png \\\n    \
--source-record src.json --target-record tgt.json -o dump.safetensors"
)]
pub struct DumpArgs {
    /// Weights: the release `.pt` or safetensors (from `convert` or `init-weights`).
    #[arg(long)]
    ckpt: PathBuf,
    /// FLAME asset (`FLAME_with_eye.pt` or safetensors with the same keys).
    #[arg(long)]
    flame: PathBuf,
    /// Source image (PNG/JPEG, ideally image_size x image_size).
    #[arg(long)]
    source: PathBuf,
    /// Tracked-frame JSON of the source (needs transform_matrix and shapecode).
    #[arg(long)]
    source_record: PathBuf,
    /// Tracked-frame JSON of the target (expression, pose, eyes, transform_matrix).
    #[arg(long)]
    target_record: PathBuf,
    /// Output safetensors.
    #[arg(short, long)]
    output: PathBuf,
    /// Architecture, when the weights file does not say (the release `.pt` is `release`).
    #[arg(long)]
    preset: Option<String>,
    /// Draw fresh renderer noise per call (the release's behaviour) instead of the fixed buffers.
    #[arg(long)]
    fresh_noise: bool,
    #[arg(long, default_value_t = 300)]
    n_shape: usize,
    #[arg(long, default_value_t = 100)]
    n_exp: usize,
}

pub fn run_dump(a: DumpArgs) -> Result<()> {
    let explicit = a.preset.as_deref().map(preset).transpose()?;
    let model = checkpoint::load_model(&a.ckpt, explicit.as_ref(), &Device::Cpu)
        .with_context(|| format!("loading {}", a.ckpt.display()))?;
    let cfg = model.cfg.clone();
    let flame = load_flame(&a.flame, a.n_shape, a.n_exp)?;
    let source = TrackedFrame::from_json_file(&a.source_record)?;
    let target = TrackedFrame::from_json_file(&a.target_record)?;
    let image = read_image(&a.source, cfg.image_size)?;
    let src_t = transform_tensor(&source, "source")?;
    let tgt_t = transform_tensor(&target, "target")?;
    let verts = target_vertices(&flame, &source, &target)?;
    if verts.dim(1)? != cfg.n_vertices {
        bail!(
            "the FLAME asset has {} vertices, the model expects {}",
            verts.dim(1)?,
            cfg.n_vertices
        );
    }
    let (avatar, trace) = model.reconstruct_traced(&image, &src_t)?;
    let noise = if a.fresh_noise {
        Noise::Fresh
    } else {
        Noise::Fixed
    };
    let frame = model.drive(&avatar, &verts, &tgt_t, noise)?;
    let mut out: BTreeMap<String, Tensor> = BTreeMap::new();
    out.insert("source_image".into(), image);
    out.insert("source_transform".into(), src_t);
    out.insert("input_518".into(), trace.input_518);
    for (k, d) in trace.dino.iter().enumerate() {
        out.insert(format!("dino_{k}"), d.clone());
    }
    out.insert("f_id".into(), trace.f_id);
    out.insert("f_local".into(), trace.f_local);
    out.insert("plane_points".into(), trace.plane_points);
    out.insert("plane_dir".into(), trace.plane_dir);
    out.insert("dir_encoding".into(), trace.dir_encoding);
    out.insert("gs_xyz".into(), avatar.positions(&verts)?);
    out.insert("target_points".into(), verts);
    out.insert("target_transform".into(), tgt_t);
    out.insert("gs_colors".into(), avatar.colors);
    out.insert("gs_opacities".into(), avatar.opacities);
    out.insert("gs_scales".into(), avatar.scales);
    out.insert("gs_rotations".into(), avatar.rotations);
    out.insert("coarse".into(), frame.coarse);
    out.insert("fine".into(), frame.fine);
    write_tensors(&a.output, &out, Some(&cfg))?;
    eprintln!("wrote {} ({} tensors)", a.output.display(), out.len());
    Ok(())
}
