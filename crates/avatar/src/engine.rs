//! Loading once: the weights (release `.pt` or safetensors), the FLAME asset they go with, and
//! reconstructing avatars from a source crop and its tracked record.

use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

use candle_core::{DType, Device, Tensor};
use gagavatar_flame::{
    BasisLayout, FlameAsset, FlameIdentity, FlameModel, LoadOptions, TrackedFrame,
};
use gagavatar_gpu::reconstruct::GpuReconstruct;
use gagavatar_net::checkpoint;
use gagavatar_net::model::GagAvatar;
use gagavatar_net::style_unet::Noise;
use gagavatar_net::ModelConfig;
use gagavatar_ops::Precision;

use crate::avatar::Avatar;
use crate::cache::{track_input, TrackTo, Tracked};
use crate::convert::{image_tensor, transforms_tensor};
use crate::error::{input_err, AvatarError, Result};
pub use crate::flame_source::{FlameSource, SYNTHETIC_FLAME};
use crate::monitor::Monitor;
use crate::tracking::{PhotoTrack, Tracker};

/// What [`Engine::open`] loads.
#[derive(Debug, Clone)]
pub struct EngineConfig {
    /// `GAGAvatar.pt`, or safetensors from `convert` / `init-weights` / `train`.
    pub weights: PathBuf,
    pub flame: FlameSource,
    /// The architecture, when the weights file does not say (the release `.pt` is `release`).
    pub preset: Option<String>,
    /// Shape components at the start of the asset's `shapedirs`.
    pub n_shape: usize,
    /// Expression components after them.
    pub n_exp: usize,
    /// The renderer's noise: the fixed buffers (reproducible) or fresh per frame (the
    /// release's behaviour).
    pub noise: Noise,
    /// The CPU model's products: f32 (the release's arithmetic) or bf16 with f32 sums (CPUs
    /// with AVX512-BF16; `Engine::open` refuses it elsewhere, before loading anything).
    pub precision: Precision,
}

impl EngineConfig {
    /// The release's component counts (300 shape, 100 expression), fixed noise, and the FLAME
    /// asset the weights name.
    pub fn new(weights: impl Into<PathBuf>) -> Self {
        EngineConfig {
            weights: weights.into(),
            flame: FlameSource::FromWeights,
            preset: None,
            n_shape: 300,
            n_exp: 100,
            noise: Noise::Fixed,
            precision: Precision::F32,
        }
    }
}

/// The model and FLAME, loaded once and shared by every avatar made from them.
pub struct Engine {
    model: Arc<GagAvatar>,
    flame: Arc<FlameModel>,
    flame_source: FlameSource,
    noise: Noise,
    flame_label: String,
    warnings: Vec<String>,
    /// The tracking models, loaded on first use (rendering alone never needs them).
    tracker: Mutex<Option<Arc<Tracker>>>,
}

impl Engine {
    /// Reads the weights, builds the model, loads the FLAME asset and checks that they fit.
    /// A suspected asset mismatch is not an error: it is in [`Engine::warnings`].
    pub fn open(cfg: &EngineConfig) -> Result<Self> {
        cfg.precision.check()?;
        let explicit = cfg
            .preset
            .as_deref()
            .map(|name| {
                ModelConfig::preset(name).ok_or_else(|| {
                    input_err(
                        "preset",
                        format!(
                            "unknown preset `{name}` (choose one of {})",
                            ModelConfig::PRESETS.join(", ")
                        ),
                    )
                })
            })
            .transpose()?;
        let weights_err = |source| AvatarError::Weights {
            path: cfg.weights.clone(),
            source: Box::new(source),
        };
        let weights = checkpoint::read_weights(&cfg.weights).map_err(weights_err)?;
        let trained_with = weights
            .metadata
            .get(checkpoint::FLAME_METADATA_KEY)
            .cloned();
        let model_cfg = checkpoint::resolve_config(&weights, explicit.as_ref());
        checkpoint::check_keys(&model_cfg, &weights.tensors).map_err(weights_err)?;
        let mut model = checkpoint::build_model(&model_cfg, weights.tensors, &Device::Cpu)
            .map_err(weights_err)?;
        model.set_precision(cfg.precision)?;

        let source = match &cfg.flame {
            FlameSource::FromWeights => {
                default_flame(trained_with.as_deref(), &model.cfg.name, &cfg.weights)?
            }
            other => other.clone(),
        };
        let (flame, flame_label) = load_flame(&source, cfg.n_shape, cfg.n_exp)?;
        if flame.n_vertices != model.cfg.n_vertices {
            return Err(AvatarError::FlameVertices {
                asset: flame.n_vertices,
                model: model.cfg.n_vertices,
            });
        }
        let mut warnings = Vec::new();
        if let Some(w) = flame_mismatch(
            trained_with.as_deref(),
            &model.cfg.name,
            flame.asset_fingerprint,
        ) {
            warnings.push(format!(
                "{} with FLAME {flame_label}: {w}",
                cfg.weights.display()
            ));
        }
        Ok(Engine {
            model: Arc::new(model),
            flame: Arc::new(flame),
            flame_source: source,
            noise: cfg.noise,
            flame_label,
            warnings,
            tracker: Mutex::new(None),
        })
    }

    pub fn model(&self) -> &GagAvatar {
        &self.model
    }

    pub fn flame(&self) -> &FlameModel {
        &self.flame
    }

    /// The FLAME asset loaded ([`FlameSource::FromWeights`] resolved to what the weights name).
    pub fn flame_source(&self) -> &FlameSource {
        &self.flame_source
    }

    /// Which FLAME asset was loaded, for messages (a path, or the built-in synthetic asset).
    pub fn flame_label(&self) -> &str {
        &self.flame_label
    }

    /// The side of the square images the model reads and renders.
    pub fn image_size(&self) -> usize {
        self.model.cfg.image_size
    }

    /// Things worth telling the user that did not stop loading (a FLAME asset the weights were
    /// probably not trained with). The library prints nothing itself.
    pub fn warnings(&self) -> &[String] {
        &self.warnings
    }

    /// The tracker, with the engine's FLAME asset, so records fit the avatars it drives.
    /// Loaded on first use and kept.
    pub fn tracker(&self) -> Result<Arc<Tracker>> {
        let mut slot = self.tracker.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(t) = slot.as_ref() {
            return Ok(t.clone());
        }
        let t = Arc::new(Tracker::new(&self.flame_source)?);
        *slot = Some(t.clone());
        Ok(t)
    }

    /// Tracks a photo in memory: its record and its 512 crop (as a tracked folder would store
    /// it), ready for [`Engine::avatar`]. `label` names it in "no face found in LABEL".
    pub fn track_photo(&self, image: &image::RgbImage, label: &str) -> Result<PhotoTrack> {
        self.tracker()?.track_photo(image, label)
    }

    /// Tracks a photo, a video or a folder of images into `to` (a folder, or the cache where a
    /// previous run's folder for the same bytes is reused), and returns what it holds.
    pub fn track(&self, input: &Path, to: &TrackTo, monitor: &dyn Monitor) -> Result<Tracked> {
        self.track_as(input, to, "input", false, monitor)
    }

    /// [`Engine::track`], naming the input `what` in messages (`source`, `driver`), and with
    /// `photo_only` refusing anything but a photo.
    pub fn track_as(
        &self,
        input: &Path,
        to: &TrackTo,
        what: &str,
        photo_only: bool,
        monitor: &dyn Monitor,
    ) -> Result<Tracked> {
        track_input(
            input,
            &self.flame_source,
            to,
            what,
            photo_only,
            || self.tracker(),
            monitor,
        )
    }

    /// Reconstructs an avatar from the source crop and its tracked record (the record's shape
    /// is the identity, its camera the source view). A crop that is not `image_size` square is
    /// resized (antialiased) first.
    pub fn avatar(&self, image: &image::RgbImage, record: &TrackedFrame) -> Result<Avatar> {
        let t = image_tensor(image, self.image_size())?;
        self.avatar_from_tensor(&t, record)
    }

    /// The GPU half of [`Engine::avatar_on_gpu`]: the reconstruct pass with this engine's
    /// weights uploaded to `gpu` (once; keep it for every source photo).
    pub fn gpu_reconstruct(
        &self,
        gpu: Arc<gagavatar_gpu::Gpu>,
        tuning: &gagavatar_gpu::Tuning,
    ) -> Result<GpuReconstruct> {
        Ok(GpuReconstruct::new(gpu, tuning, &self.model)?)
    }

    /// [`Engine::avatar`] with the network run on the GPU of `rec` (from
    /// [`Engine::gpu_reconstruct`]): the Gaussians stay there for a GPU drive on that device
    /// (a copy is also read back for the CPU's uses: `.ply` export, the CPU drive).
    pub fn avatar_on_gpu(
        &self,
        rec: &GpuReconstruct,
        image: &image::RgbImage,
        record: &TrackedFrame,
    ) -> Result<Avatar> {
        let t = image_tensor(image, self.image_size())?;
        let (transform, identity) = self.source_parts(&t, record)?;
        let on_gpu = Arc::new(rec.run_owned(&t, &transforms_tensor(&[transform])?)?);
        let gpu = rec.gpu_arc();
        let gaussians = on_gpu.download(&gpu)?;
        let mut avatar = Avatar::new(
            self.model.clone(),
            self.flame.clone(),
            gaussians,
            identity,
            record.clone(),
            self.noise,
        );
        avatar.on_gpu = Some((gpu, on_gpu));
        Ok(avatar)
    }

    /// The source's camera and FLAME identity, with the image's shape checked.
    fn source_parts(
        &self,
        image: &Tensor,
        record: &TrackedFrame,
    ) -> Result<([[f64; 4]; 3], FlameIdentity)> {
        let size = self.image_size();
        if image.dims() != [1, 3, size, size] {
            return Err(input_err(
                "source image",
                format!("expected [1, 3, {size}, {size}], got {:?}", image.dims()),
            ));
        }
        let transform = record
            .transform_matrix
            .ok_or_else(|| input_err("the source record", "no transform_matrix"))?;
        let shape = record.params(&self.flame)?.shape;
        Ok((transform, self.flame.identity(&shape)?))
    }

    /// [`Engine::avatar`] from an image tensor `[1, 3, S, S]` in [0, 1].
    pub fn avatar_from_tensor(&self, image: &Tensor, record: &TrackedFrame) -> Result<Avatar> {
        let (transform, identity) = self.source_parts(image, record)?;
        let gaussians = self
            .model
            .reconstruct(image, &transforms_tensor(&[transform])?)?;
        Ok(Avatar::new(
            self.model.clone(),
            self.flame.clone(),
            gaussians,
            identity,
            record.clone(),
            self.noise,
        ))
    }
}

/// Loads a FLAME asset with `n_shape` shape and `n_exp` expression components; returns it with
/// a label for messages. [`FlameSource::FromWeights`] must be resolved first (it is an error
/// here).
pub fn load_flame(
    source: &FlameSource,
    n_shape: usize,
    n_exp: usize,
) -> Result<(FlameModel, String)> {
    let (asset, label) = match source {
        FlameSource::File(path) => {
            let options = LoadOptions {
                layout: Some(BasisLayout {
                    shape: n_shape,
                    expression: n_exp,
                }),
            };
            let asset =
                FlameAsset::load(path, &options).map_err(|source| AvatarError::FlameAsset {
                    path: path.clone(),
                    n_shape,
                    n_exp,
                    source: Box::new(source),
                })?;
            (asset, path.display().to_string())
        }
        FlameSource::Synthetic => (
            gagavatar_flame::synthesize(0),
            "the built-in synthetic asset".to_string(),
        ),
        FlameSource::FromWeights => {
            return Err(input_err(
                "FLAME",
                "the asset the weights name is only known once they are read (Engine::open)",
            ))
        }
    };
    Ok((
        FlameModel::from_asset(&asset, &Device::Cpu, DType::F32)?,
        label,
    ))
}

/// The asset [`FlameSource::FromWeights`] stands for.
fn default_flame(
    trained_with: Option<&str>,
    architecture: &str,
    weights: &Path,
) -> Result<FlameSource> {
    let synthetic = format!("{:016x}", synthetic_fingerprint());
    match trained_with {
        Some(fp) if fp.eq_ignore_ascii_case(&synthetic) => Ok(FlameSource::Synthetic),
        Some(fp) => Err(AvatarError::FlameNeeded(format!(
            "{} were trained with the FLAME asset of fingerprint {fp}: name that asset (--flame)",
            weights.display()
        ))),
        None if architecture == "release" => Err(AvatarError::FlameNeeded(format!(
            "{} are release weights: name the FLAME asset they were trained with \
             (--flame FLAME_with_eye.pt)",
            weights.display()
        ))),
        None => Ok(FlameSource::Synthetic),
    }
}

/// Why a FLAME asset (by fingerprint) does not fit weights, or `None` when it does or cannot be
/// told. Weights written by `gagavatar train` record their asset's fingerprint; for others the
/// architecture tells: the release's weights were trained with the real FLAME, the `tiny` and
/// `small` ones (trained here) with the built-in synthetic asset unless `train --flame` said
/// otherwise.
pub fn flame_mismatch(
    trained_with: Option<&str>,
    architecture: &str,
    asset: u64,
) -> Option<String> {
    let synthetic = synthetic_fingerprint();
    let ours = format!("{asset:016x}");
    match trained_with {
        Some(fp) if fp.eq_ignore_ascii_case(&ours) => None,
        Some(fp) => Some(format!(
            "the weights were trained with another FLAME asset (fingerprint {fp}, this one is \
             {ours}{}); the avatar will be distorted. Pass the asset they were trained with",
            if asset == synthetic { ", the built-in synthetic one" } else { "" }
        )),
        None if architecture == "release" && asset == synthetic => Some(
            "the release weights were trained with the real FLAME asset (FLAME_with_eye.pt), not \
             the built-in synthetic stand-in; the avatar will be distorted"
                .into(),
        ),
        None if architecture != "release" && asset != synthetic => Some(format!(
            "`{architecture}` weights without a recorded FLAME asset were trained with the built-in \
             synthetic one (--flame synthetic); this asset differs (fingerprint {ours}), so the \
             avatar may be distorted"
        )),
        None => None,
    }
}

/// The fingerprint of the built-in synthetic asset (`gagavatar flame synth`, seed 0).
pub fn synthetic_fingerprint() -> u64 {
    static FP: std::sync::OnceLock<u64> = std::sync::OnceLock::new();
    *FP.get_or_init(|| gagavatar_flame::synthesize(0).fingerprint())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn flame_mismatches_are_reported() {
        let synthetic = synthetic_fingerprint();
        let other = synthetic ^ 1;
        let fp = |x: u64| format!("{x:016x}");
        // Recorded fingerprints decide.
        assert!(flame_mismatch(Some(&fp(synthetic)), "tiny", synthetic).is_none());
        assert!(flame_mismatch(Some(&fp(other)), "release", other).is_none());
        let w = flame_mismatch(Some(&fp(other)), "tiny", synthetic).unwrap();
        assert!(
            w.contains("another FLAME asset") && w.contains("synthetic"),
            "{w}"
        );
        // Without one, the architecture: release with the stand-in, tiny with another asset.
        let w = flame_mismatch(None, "release", synthetic).unwrap();
        assert!(w.contains("FLAME_with_eye.pt"), "{w}");
        assert!(flame_mismatch(None, "release", other).is_none());
        assert!(flame_mismatch(None, "tiny", synthetic).is_none());
        assert!(flame_mismatch(None, "small", other).is_some());
    }

    #[test]
    fn the_default_flame_is_the_one_the_weights_name() {
        let w = Path::new("w.safetensors");
        let synthetic = format!("{:016x}", synthetic_fingerprint());
        assert_eq!(
            default_flame(Some(&synthetic), "release", w).unwrap(),
            FlameSource::Synthetic
        );
        assert_eq!(
            default_flame(None, "tiny", w).unwrap(),
            FlameSource::Synthetic
        );
        let e = default_flame(None, "release", w).unwrap_err().to_string();
        assert!(e.contains("FLAME_with_eye.pt"), "{e}");
        let e = default_flame(Some("0123"), "tiny", w)
            .unwrap_err()
            .to_string();
        assert!(e.contains("0123") && e.contains("--flame"), "{e}");
    }
}
