//! Model sizes. `release` is the published architecture (spec sections 3-8); the small presets
//! keep every structural rule (key names, the 8x plane upsampling, the 4x4 bottom of the U-Net)
//! and shrink widths, depths and resolutions so tests and CPU training run in seconds.

use serde::{Deserialize, Serialize};

/// Every size the network needs. Derived sizes are methods so they cannot disagree.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ModelConfig {
    /// Preset name, informational.
    pub name: String,
    /// Model, splatting and renderer resolution (square): 512.
    pub image_size: usize,
    /// DINO input resolution (square): 518 = 37 patches of 14.
    pub dino_size: usize,
    /// ViT patch size: 14.
    pub patch: usize,
    /// ViT width: 768.
    pub vit_dim: usize,
    /// ViT blocks: 12 (the last four feed the DPT head).
    pub vit_depth: usize,
    /// Attention heads: 12.
    pub vit_heads: usize,
    /// MLP hidden width: 3072.
    pub vit_mlp: usize,
    /// DPT fusion width, also the channel count of F_local: 256.
    pub dpt_features: usize,
    /// `projects.k` output channels: 256, 512, 1024, 1024.
    pub dpt_channels: [usize; 4],
    /// FLAME vertices, i.e. expression Gaussians: 5023.
    pub n_vertices: usize,
    /// Width of the learned per-vertex `head_base`: 256.
    pub head_base_dim: usize,
    /// Width of `gs_generator_g.feature_layers`: 256.
    pub gs_linear_hidden: usize,
    /// Hidden width of each attribute head of `gs_generator_g`: 128.
    pub gs_head_hidden: usize,
    /// Hidden width of `gs_generator_l*.gaussian_conv`: 128.
    pub gs_conv_hidden: usize,
    /// Feature channels per Gaussian (first 3 are RGB): 32.
    pub color_dim: usize,
    /// StyleGAN2 latent width: 512.
    pub style_dim: usize,
    /// Linear layers in `style_mlp`: 8.
    pub style_mlp_layers: usize,
    /// Decoder channels at resolution r are `min(decoder_max_channels, decoder_channel_base / r)`:
    /// 16384 and 512 give 512 up to 32x32, then 256, 128, 64, 32 at 512x512.
    pub decoder_channel_base: usize,
    pub decoder_max_channels: usize,
    /// Whether training keeps the DINOv2 backbone (`base_model.dino_model.*`) fixed: `None`
    /// follows [`ModelConfig::backbone_frozen`]'s rule (frozen exactly when the ViT is shaped
    /// like the pretrained DINOv2 ViT-B/14, i.e. in the release); `Some` overrides it. Not
    /// written when `None`, so configurations stored before it existed still compare equal.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub freeze_backbone: Option<bool>,
    /// Ablation "one-plane lifting" (paper, VFHQ PSNR 21.34): only `gs_generator_l0`'s lifted
    /// point set is used; `gs_generator_l1` keeps its keys but does not run, so an avatar has
    /// `V + S^2` Gaussians and `lifted_xyz` is `[B, S^2, 3]`.
    #[serde(default)]
    pub one_plane: bool,
    /// Ablation "without F_id" (paper, 21.13): the expression branch gets zeros where F_id
    /// would be (its input width, hence the key set, is unchanged). F_local is unaffected.
    #[serde(default)]
    pub no_fid_in_expression: bool,
    /// Ablation "without neural renderer" (paper, 20.34): `fine` is the coarse image's RGB
    /// channels (0..3) and the StyleUNet (`upsampler.*`, still loaded) is skipped.
    #[serde(default)]
    pub no_neural_renderer: bool,
}

/// Harmonic frequencies of the direction encoding (1, 2, 4, 8): 3 * (2 * 4) + 3 = 27 values.
pub const DIR_ENCODING_DIM: usize = 27;
/// NDC focal length of every camera in the release.
pub const FOCAL: f64 = 12.0;

/// Checkpoint-key prefix of the DINOv2 backbone.
pub const BACKBONE_PREFIX: &str = "base_model.dino_model.";
/// Checkpoint-key prefix of the renderer's fixed noise buffers.
pub const NOISE_BUFFER_PREFIX: &str = "upsampler.stylegan_decoder.noises.";

impl ModelConfig {
    /// The published model; loads `GAGAvatar.pt`.
    pub fn release() -> Self {
        Self {
            name: "release".into(),
            image_size: 512,
            dino_size: 518,
            patch: 14,
            vit_dim: 768,
            vit_depth: 12,
            vit_heads: 12,
            vit_mlp: 3072,
            dpt_features: 256,
            dpt_channels: [256, 512, 1024, 1024],
            n_vertices: 5023,
            head_base_dim: 256,
            gs_linear_hidden: 256,
            gs_head_hidden: 128,
            gs_conv_hidden: 128,
            color_dim: 32,
            style_dim: 512,
            style_mlp_layers: 8,
            decoder_channel_base: 16384,
            decoder_max_channels: 512,
            freeze_backbone: None,
            one_plane: false,
            no_fid_in_expression: false,
            no_neural_renderer: false,
        }
    }

    /// For tests and goldens: 64x64 images, a 5x5 patch grid, a 40x40 plane, narrow layers.
    pub fn tiny() -> Self {
        Self {
            name: "tiny".into(),
            image_size: 64,
            dino_size: 70,
            patch: 14,
            vit_dim: 32,
            vit_depth: 4,
            vit_heads: 2,
            vit_mlp: 128,
            dpt_features: 16,
            dpt_channels: [16, 32, 64, 64],
            n_vertices: 5023,
            head_base_dim: 16,
            gs_linear_hidden: 32,
            gs_head_hidden: 16,
            gs_conv_hidden: 16,
            color_dim: 32,
            style_dim: 32,
            style_mlp_layers: 2,
            decoder_channel_base: 1024,
            decoder_max_channels: 32,
            freeze_backbone: None,
            one_plane: false,
            no_fid_in_expression: false,
            no_neural_renderer: false,
        }
    }

    /// For CPU training: 256x256 images, an 18x18 patch grid, a 144x144 plane.
    pub fn small() -> Self {
        Self {
            name: "small".into(),
            image_size: 256,
            dino_size: 252,
            patch: 14,
            vit_dim: 192,
            vit_depth: 4,
            vit_heads: 3,
            vit_mlp: 768,
            dpt_features: 64,
            dpt_channels: [48, 96, 192, 192],
            n_vertices: 5023,
            head_base_dim: 64,
            gs_linear_hidden: 128,
            gs_head_hidden: 64,
            gs_conv_hidden: 64,
            color_dim: 32,
            style_dim: 128,
            style_mlp_layers: 4,
            decoder_channel_base: 4096,
            decoder_max_channels: 128,
            freeze_backbone: None,
            one_plane: false,
            no_fid_in_expression: false,
            no_neural_renderer: false,
        }
    }

    /// Whether training keeps the DINOv2 backbone fixed: `freeze_backbone` when set, else
    /// frozen exactly when the ViT has DINOv2 ViT-B/14's shape (patch 14, width 768, 12 blocks,
    /// 12 heads, MLP 3072), the only shape whose pretrained weights exist (the release trains
    /// with it frozen, spec 11). The small presets train their ViT from scratch.
    pub fn backbone_frozen(&self) -> bool {
        self.freeze_backbone.unwrap_or(
            self.patch == 14
                && self.vit_dim == 768
                && self.vit_depth == 12
                && self.vit_heads == 12
                && self.vit_mlp == 3072,
        )
    }

    /// Lifted points per avatar: 2 S^2 (S^2 with `one_plane`).
    pub fn lifted_points(&self) -> usize {
        let s2 = self.plane_size() * self.plane_size();
        if self.one_plane {
            s2
        } else {
            2 * s2
        }
    }

    /// A preset by name (`release`, `small`, `tiny`).
    pub fn preset(name: &str) -> Option<Self> {
        match name {
            "release" => Some(Self::release()),
            "small" => Some(Self::small()),
            "tiny" => Some(Self::tiny()),
            _ => None,
        }
    }

    pub const PRESETS: [&'static str; 3] = ["release", "small", "tiny"];

    /// Patches per side of the DINO input: 37.
    pub fn grid(&self) -> usize {
        self.dino_size / self.patch
    }

    /// Side of the point plane and of F_local: 8 x grid = 296 (DPT: x4, then x2 in refinenet.3).
    pub fn plane_size(&self) -> usize {
        8 * self.grid()
    }

    /// Side of DPT level k after `resize_layers.k`: 4g, 2g, g, ceil(g/2) (148, 74, 37, 19).
    pub fn dpt_level_size(&self, k: usize) -> usize {
        let g = self.grid();
        match k {
            0 => 4 * g,
            1 => 2 * g,
            2 => g,
            _ => g.div_ceil(2),
        }
    }

    /// Gaussians per avatar: 5023 + 2 S^2 = 180,255 (5023 + S^2 with `one_plane`).
    pub fn n_gaussians(&self) -> usize {
        self.n_vertices + self.lifted_points()
    }

    /// ResBlocks down (and up) in the StyleUNet: log2(image) - 2 = 7 (512 -> 4).
    pub fn renderer_levels(&self) -> usize {
        self.image_size.trailing_zeros() as usize - 2
    }

    /// StyleGAN2 decoder channels at resolution `res`.
    pub fn decoder_channels(&self, res: usize) -> usize {
        (self.decoder_channel_base / res).min(self.decoder_max_channels)
    }

    /// U-Net channels at resolution `res`: half the decoder's (256 .. 16 in the release).
    pub fn unet_channels(&self, res: usize) -> usize {
        self.decoder_channels(res) / 2
    }

    /// Checks the structural rules the modules rely on.
    pub fn validate(&self) -> Result<(), String> {
        let p = |c: bool, m: &str| if c { Ok(()) } else { Err(m.to_string()) };
        p(
            self.patch > 0 && self.dino_size.is_multiple_of(self.patch),
            "dino_size must be a multiple of patch",
        )?;
        p(self.grid() >= 2, "the patch grid must be at least 2x2")?;
        p(
            self.image_size.is_power_of_two() && self.image_size >= 8,
            "image_size must be a power of two >= 8",
        )?;
        p(
            self.vit_heads > 0 && self.vit_dim.is_multiple_of(self.vit_heads),
            "vit_dim must be a multiple of vit_heads",
        )?;
        p(
            self.vit_depth >= 4,
            "vit_depth must be at least 4 (the DPT head reads the last four blocks)",
        )?;
        p(
            self.color_dim >= 3,
            "color_dim must be at least 3 (RGB first)",
        )?;
        p(
            self.unet_channels(4) > 0 && self.unet_channels(self.image_size) > 0,
            "decoder channels too small",
        )?;
        p(
            self.style_mlp_layers > 0 && self.style_dim > 0,
            "style sizes must be positive",
        )?;
        Ok(())
    }
}

impl Default for ModelConfig {
    fn default() -> Self {
        Self::release()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn release_sizes_match_the_spec() {
        let c = ModelConfig::release();
        assert_eq!(c.grid(), 37);
        assert_eq!(c.plane_size(), 296);
        assert_eq!(c.n_gaussians(), 180_255);
        assert_eq!(c.renderer_levels(), 7);
        assert_eq!(
            [4, 32, 64, 128, 256, 512].map(|r| c.decoder_channels(r)),
            [512, 512, 256, 128, 64, 32]
        );
        assert_eq!(
            [4, 32, 64, 128, 256, 512].map(|r| c.unet_channels(r)),
            [256, 256, 128, 64, 32, 16]
        );
        assert_eq!(
            (0..4).map(|k| c.dpt_level_size(k)).collect::<Vec<_>>(),
            [148, 74, 37, 19]
        );
        for name in ModelConfig::PRESETS {
            ModelConfig::preset(name).unwrap().validate().unwrap();
        }
    }
}
