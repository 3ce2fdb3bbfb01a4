//! Frames of several avatars in one batched pass, as a server gathers concurrent requests for
//! different avatars: FLAME with each avatar's identity, then one splatting call and one neural
//! renderer call over the whole batch (the renderer's batched convolutions are where batching
//! pays).

use std::sync::Arc;

use candle_core::Tensor;
use gagavatar_gpu::flame::FrameCodes;
use gagavatar_net::model::{render_fine, splat_coarse, Avatar as Gaussians};

use crate::avatar::Avatar;
use crate::convert::{to_rgb8, transforms_tensor};
use crate::drive::{check_camera, Camera};
use crate::error::{input_err, Result};

/// Renders `jobs` (`(avatar index, codes, camera)`) on the CPU in one batch; frames in job
/// order, as each avatar's own drive renders them (up to the batched sums' rounding). Every
/// avatar must come from the same [`crate::Engine`] (one model and FLAME); the renderer's
/// noise is the first avatar's.
pub fn render_many(
    avatars: &[&Avatar],
    jobs: &[(usize, FrameCodes, Camera)],
) -> Result<Vec<Vec<u8>>> {
    let Some(first) = avatars.first() else {
        return Err(input_err("render_many", "no avatars"));
    };
    if jobs.is_empty() {
        return Err(input_err("render_many", "no frames"));
    }
    if let Some(i) = avatars
        .iter()
        .position(|a| !Arc::ptr_eq(&a.model, &first.model) || !Arc::ptr_eq(&a.flame, &first.flame))
    {
        return Err(input_err(
            format!("avatar {i}"),
            "comes from another engine than avatar 0 (one batch needs one model and FLAME)",
        ));
    }
    let mut verts = Vec::with_capacity(jobs.len());
    let mut cams = Vec::with_capacity(jobs.len());
    let mut parts: [Vec<&Tensor>; 5] = Default::default();
    for (j, (index, codes, cam)) in jobs.iter().enumerate() {
        let avatar = avatars.get(*index).ok_or_else(|| {
            input_err(
                format!("frame {j}"),
                format!("avatar {index} of {}", avatars.len()),
            )
        })?;
        check_camera(cam, j)?;
        verts.push(avatar.vertices(codes)?);
        cams.push(*cam);
        let g = &avatar.gaussians;
        for (list, t) in parts.iter_mut().zip([
            &g.lifted_xyz,
            &g.colors,
            &g.opacities,
            &g.scales,
            &g.rotations,
        ]) {
            list.push(t);
        }
    }
    let [lifted_xyz, colors, opacities, scales, rotations] =
        parts.map(|list| Tensor::cat(&list, 0));
    let batch = Gaussians {
        lifted_xyz: lifted_xyz?,
        colors: colors?,
        opacities: opacities?,
        scales: scales?,
        rotations: rotations?,
    };
    let cfg = &first.model.cfg;
    let coarse = splat_coarse(
        cfg,
        &batch,
        &Tensor::cat(&verts, 0)?,
        &transforms_tensor(&cams)?,
    )?;
    let fine = render_fine(cfg, &first.model.renderer, &coarse, first.noise)?;
    to_rgb8(&fine)
}
