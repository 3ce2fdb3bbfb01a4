//! `gagavatar splat` and `gagavatar example-scene`: render a Gaussian scene with the release's
//! camera convention.

use anyhow::{bail, Context, Result};
use candle_core::{DType, Device, Tensor};
use clap::Args;
use gagavatar_formats::atomic::write_atomic;
use gagavatar_splat::testscene::{avatar_scene, Regime};
use gagavatar_splat::{splat, Camera, GaussianScene, Gaussians};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// A camera file: the release's `transform_matrix` plus intrinsics.
#[derive(Debug, Serialize, Deserialize)]
pub struct CameraFile {
    /// `[R | T]`, 3x4, PyTorch3D row-vector convention.
    pub transform_matrix: Vec<Vec<f64>>,
    /// NDC focal length.
    #[serde(default = "default_focal")]
    pub focal: f64,
    pub width: usize,
    pub height: usize,
    /// Per-channel background (default 0 on every channel).
    #[serde(default)]
    pub background: Option<Vec<f32>>,
}

fn default_focal() -> f64 {
    12.0
}

impl CameraFile {
    pub fn load(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("reading camera file {}", path.display()))?;
        serde_json::from_str(&text)
            .with_context(|| format!("parsing camera file {}", path.display()))
    }

    /// 512x512, focal 12, at distance 9 on the axis facing the origin (the release's framing).
    pub fn default_view() -> Self {
        let tm = Camera::look_at_origin_matrix(9.0, 0.0, 0.0);
        Self {
            transform_matrix: tm.iter().map(|r| r.to_vec()).collect(),
            focal: 12.0,
            width: 512,
            height: 512,
            background: None,
        }
    }

    pub fn camera(&self) -> Result<Camera> {
        let tm = &self.transform_matrix;
        if tm.len() != 3 || tm.iter().any(|r| r.len() != 4) {
            bail!("transform_matrix must be 3 rows of 4 numbers");
        }
        let mut m = [[0.0; 4]; 3];
        for (r, row) in tm.iter().enumerate() {
            m[r].copy_from_slice(row);
        }
        Ok(Camera::from_transform_matrix(
            &m,
            self.focal,
            self.width,
            self.height,
        )?)
    }
}

#[derive(Debug, Args)]
#[command(after_help = "Examples:\n  \
    gagavatar splat -o out.png    (the built-in avatar-like scene and camera)\n  \
    gagavatar example-scene -o scene.safetensors --camera-out camera.json\n  \
    gagavatar splat --scene scene.safetensors --camera camera.json -o out.png --features-out out.safetensors")]
pub struct SplatArgs {
    /// Scene: safetensors with `means` [N,3], `features` [N,C], `opacities` [N,1], `scales`
    /// [N,3], `rotations` [N,4] (activated values), or a 3DGS .ply. Default: the built-in
    /// avatar-like scene of `gagavatar example-scene`.
    #[arg(long)]
    scene: Option<PathBuf>,
    /// Camera JSON: `transform_matrix` (3x4), `focal` (NDC, default 12), `width`, `height`,
    /// optional `background` [C]. Default: 512x512, focal 12, distance 9 facing the origin.
    #[arg(long)]
    camera: Option<PathBuf>,
    /// Output PNG of channels 0..2 clamped to [0, 1] (a single-channel scene is shown in grey).
    #[arg(short, long)]
    output: PathBuf,
    /// Also write every channel as tensor `image` [C,H,W] f32 to this safetensors file.
    #[arg(long)]
    features_out: Option<PathBuf>,
}

pub fn run_splat(args: SplatArgs) -> Result<()> {
    let scene = match &args.scene {
        Some(path) => GaussianScene::load(path)?,
        None => avatar_scene(296, 5023, 32, Regime::Small, 1).0,
    };
    let cam_file = match &args.camera {
        Some(path) => CameraFile::load(path)?,
        None => CameraFile::default_view(),
    };
    let camera_name = args
        .camera
        .as_ref()
        .map_or("default camera".to_string(), |p| p.display().to_string());
    let cam = cam_file
        .camera()
        .with_context(|| format!("camera file {camera_name}"))?;
    let c = scene.channels;
    let bg = match &cam_file.background {
        Some(b) if b.len() == c => b.clone(),
        Some(b) => bail!(
            "camera file {camera_name}: background has {} values but the scene has {c} channels",
            b.len()
        ),
        None => vec![0.0; c],
    };
    let dev = Device::Cpu;
    let tensors = scene.to_tensors(&dev)?;
    let bg = Tensor::from_vec(bg, c, &dev)?;
    let out = splat(
        &Gaussians::from_tensors(&tensors),
        &bg,
        std::slice::from_ref(&cam),
    )?;
    let image = out.image.squeeze(0)?.to_dtype(DType::F32)?;
    write_png(&image, &args.output)?;
    if let Some(path) = &args.features_out {
        let bytes = safetensors_bytes(&[("image", &image)])?;
        write_atomic(path, &bytes)?;
    }
    let radii: Vec<u32> = out.radii.flatten_all()?.to_vec1()?;
    eprintln!(
        "rendered {} of {} Gaussians ({} tile pairs) to {}x{} with {c} channels -> {}",
        radii.iter().filter(|&&r| r > 0).count(),
        scene.len(),
        out.tile_pairs[0],
        cam.width,
        cam.height,
        args.output.display()
    );
    Ok(())
}

/// Serialises named tensors to safetensors bytes (written atomically by the caller).
pub fn safetensors_bytes(tensors: &[(&str, &Tensor)]) -> Result<Vec<u8>> {
    let owned: Vec<(String, Tensor)> = tensors
        .iter()
        .map(|(n, t)| (n.to_string(), (*t).clone()))
        .collect();
    let refs: Vec<(&str, &Tensor)> = owned.iter().map(|(n, t)| (n.as_str(), t)).collect();
    Ok(safetensors::serialize(refs, None)?)
}

/// `[C, H, W]` -> 8-bit RGB PNG of channels 0..2 clamped to [0, 1], written atomically.
pub fn write_png(image: &Tensor, path: &Path) -> Result<()> {
    let (c, h, w) = image.dims3()?;
    let data: Vec<f32> = image.flatten_all()?.to_vec1()?;
    let mut rgb = vec![0u8; h * w * 3];
    for (i, px) in rgb.chunks_mut(3).enumerate() {
        for (k, v) in px.iter_mut().enumerate() {
            let ch = k.min(c - 1);
            let x = data[ch * h * w + i];
            *v = (x.clamp(0.0, 1.0) * 255.0).round() as u8;
        }
    }
    let img = image::RgbImage::from_raw(w as u32, h as u32, rgb).context("image buffer size")?;
    let mut bytes = Vec::new();
    img.write_to(
        &mut std::io::Cursor::new(&mut bytes),
        image::ImageFormat::Png,
    )?;
    write_atomic(path, &bytes)?;
    Ok(())
}

#[derive(Debug, Args)]
#[command(
    after_help = "Example:\n  gagavatar example-scene -o scene.safetensors --camera-out camera.json"
)]
pub struct ExampleSceneArgs {
    /// Output scene (.safetensors or .ply).
    #[arg(short, long)]
    output: PathBuf,
    /// Also write a matching camera JSON (512x512, focal 12, distance 9).
    #[arg(long)]
    camera_out: Option<PathBuf>,
    /// Points per side of each of the two lifted planes.
    #[arg(long, default_value_t = 296)]
    plane: usize,
    /// Head points.
    #[arg(long, default_value_t = 5023)]
    head: usize,
    /// Feature channels (the first three are a colour pattern).
    #[arg(long, default_value_t = 32)]
    channels: usize,
    /// Use the large-Gaussian regime (world scales ~0.025 instead of ~0.005).
    #[arg(long)]
    large: bool,
    #[arg(long, default_value_t = 1)]
    seed: u64,
}

/// The avatar-like scene of the benchmarks, saved for the `splat` command.
pub fn run_example_scene(args: ExampleSceneArgs) -> Result<()> {
    if args.plane < 2 || args.channels == 0 {
        bail!("--plane must be at least 2 and --channels at least 1");
    }
    let regime = if args.large {
        Regime::Large
    } else {
        Regime::Small
    };
    let (scene, cam) = avatar_scene(args.plane, args.head, args.channels, regime, args.seed);
    let ext = args
        .output
        .extension()
        .and_then(|e| e.to_str())
        .unwrap_or("")
        .to_ascii_lowercase();
    match ext.as_str() {
        "ply" => scene.save_ply(&args.output)?,
        "safetensors" => {
            let dev = Device::Cpu;
            let [m, f, o, s, r] = scene.to_tensors(&dev)?;
            let bytes = safetensors_bytes(&[
                ("means", &m),
                ("features", &f),
                ("opacities", &o),
                ("scales", &s),
                ("rotations", &r),
            ])?;
            write_atomic(&args.output, &bytes)?;
        }
        _ => bail!("output must end in .safetensors or .ply"),
    }
    if let Some(path) = &args.camera_out {
        let file = CameraFile::default_view();
        debug_assert_eq!((file.width, file.height), (cam.width, cam.height));
        write_atomic(path, serde_json::to_string_pretty(&file)?.as_bytes())?;
    }
    eprintln!(
        "wrote {} Gaussians to {}",
        scene.len(),
        args.output.display()
    );
    Ok(())
}
