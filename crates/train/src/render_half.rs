//! The rendering half of a training step on another device (`train --device gpu`): the
//! coarse splatting of the target's Gaussians, the neural renderer and the image and head-box
//! terms, forward and backward, for one sample at a time. The trainer keeps the master weights,
//! the reconstruction networks, the perceptual and lifting terms (unless the backend computes
//! them) and Adam; per step it uploads
//! the renderer's weights, per sample the Gaussians, the camera, the target and the noise, and
//! takes back the loss terms and the gradients of the Gaussians and of every renderer weight.
//!
//! A backend may also run the frozen backbone's forward (DINOv2 has no trained weight in the
//! release recipe, so its outputs enter the graph as constants), and the two lifting
//! generators (`gs_generator_l0` / `l1`, four convolutions over `F_local` at plane size each):
//! forward per sample to the lifted Gaussians, backward from their gradients to the gradient
//! of `F_local` (which the trainer carries into the DPT head) and the generators' weight
//! gradients, summed over the step on the device, and the lifting term on those points. With
//! the backbone there, it may run the DPT
//! head as well: `F_local` then never leaves the device, and only the head's weight gradients
//! come back.
//!
//! The split is where the cost is at release size (the renderer and the 512x512 splatting), and
//! it keeps checkpoints, the optimiser and the data-parallel averaging exactly as on the CPU,
//! so a run may move between devices at any checkpoint.

use std::collections::HashMap;

use gagavatar_splat::Camera;

use crate::head_box::HeadBox;

/// A backend's own error, kept whole (its source chain) for the run's error.
pub type BackendError = Box<dyn std::error::Error + Send + Sync>;

/// One sample's inputs (host values, row-major, f32).
#[derive(Debug, Clone, Copy)]
pub struct RenderSample<'a> {
    /// `[N, 3]`: the head vertices, then both lifted point sets.
    pub means: &'a [f32],
    /// `[N, C]`
    pub features: &'a [f32],
    pub channels: usize,
    /// `[N]`
    pub opacities: &'a [f32],
    /// `[N, 3]`
    pub scales: &'a [f32],
    /// `[N, 4]`, unnormalised
    pub rotations: &'a [f32],
    pub camera: &'a Camera,
    /// `[3, S, S]` in [0, 1].
    pub target: &'a [f32],
    pub head_box: HeadBox,
    /// The decoder's noise maps, map `i` `[noise_resolution(i)^2]`.
    pub noise: &'a [Vec<f32>],
}

/// The forward's image terms (means over the sample, as [`crate::TrainLosses`] defines them),
/// the perceptual term when the backend computes it ([`RenderHalf::has_percep`]; its
/// gradients are then part of the backward) and, when asked for, the two head-box crops
/// `[3, box, box]` (coarse RGB, fine).
#[derive(Debug, Clone)]
pub struct RenderForward {
    pub img: f64,
    pub box_l1: f64,
    pub percep: Option<f64>,
    pub crops: Option<[Vec<f32>; 2]>,
}

/// The sample's gradients of each Gaussian attribute (the layouts of [`RenderSample`]).
#[derive(Debug, Clone)]
pub struct RenderGrads {
    pub means: Vec<f32>,
    pub features: Vec<f32>,
    pub opacities: Vec<f32>,
    pub scales: Vec<f32>,
    pub rotations: Vec<f32>,
}

/// One sample's inputs of the lifting generators (host values, row-major, f32).
#[derive(Debug, Clone, Copy)]
pub struct LiftSample<'a> {
    /// `[F, S, S]`: the DPT head's local features; `None` when the backend's own DPT head
    /// computed them ([`RenderHalf::dpt_forward`]).
    pub f_local: Option<&'a [f32]>,
    /// `[27]`: the view direction's encoding.
    pub encoding: &'a [f32],
    /// `[S * S, 3]`: the plane's points.
    pub plane_points: &'a [f32],
    /// `[3]`: the view direction.
    pub plane_dir: &'a [f32],
    /// `[V, 3]`: the target's scaled FLAME vertices when the run has the lifting term; a
    /// backend may compute the term itself ([`LiftedGaussians::point`]).
    pub targets: Option<&'a [f32]>,
    /// The sample's share of the step's loss (`1 / B`): the scale of the term's gradient.
    pub term_scale: f32,
}

/// The lifted Gaussians of one sample, both planes (`l0` then `l1`; `l0` alone with the
/// `one_plane` ablation), in the layouts of [`RenderSample`]; their gradients come back to
/// [`RenderHalf::lift_backward`] in the same layouts.
#[derive(Debug, Clone, Default)]
pub struct LiftedGaussians {
    /// `[P S^2, 3]`
    pub means: Vec<f32>,
    /// `[P S^2, C]`
    pub features: Vec<f32>,
    /// `[P S^2]`
    pub opacities: Vec<f32>,
    /// `[P S^2, 3]`
    pub scales: Vec<f32>,
    /// `[P S^2, 4]`, normalised
    pub rotations: Vec<f32>,
    /// The lifting term of these points against [`LiftSample::targets`], when the backend
    /// computed it: its gradient (times [`LiftSample::term_scale`]) is then added in
    /// [`RenderHalf::lift_backward`], and the caller leaves the term out.
    pub point: Option<f64>,
}

/// A device that runs the rendering half (see the module's text).
pub trait RenderHalf {
    /// The device, in words, for the run's log.
    fn describe(&self) -> String;

    /// Whether the backend computes the perceptual term itself (with the trainer's networks
    /// and factor, given at its construction).
    fn has_percep(&self) -> bool;

    /// Whether the backend runs the frozen backbone (DINOv2) for the reconstruction
    /// ([`RenderHalf::backbone`]).
    fn has_backbone(&self) -> bool {
        false
    }

    /// The frozen backbone's four outputs for one source photo `[3, S, S]` in [0, 1] with its
    /// camera `[3, 4]`, as `gagavatar_net::dino::Dinov2::forward` returns them
    /// (`[grid^2, vit_dim]` each).
    fn backbone(
        &mut self,
        _image: &[f32],
        _transform: &[f32],
    ) -> Result<[Vec<f32>; 4], BackendError> {
        Err("this device does not run the backbone".into())
    }

    /// Whether the backend runs the lifting generators ([`RenderHalf::lift_forward`]).
    fn has_lifting(&self) -> bool {
        false
    }

    /// The lifting generators' weights for the coming samples, by checkpoint key
    /// (`gs_generator_l0.gaussian_conv.0.weight`, ...); their gradient sums start again.
    fn set_lifting_weights(
        &mut self,
        _weights: &HashMap<String, Vec<f32>>,
    ) -> Result<(), BackendError> {
        Err("this device does not run the lifting generators".into())
    }

    /// The lifted Gaussians of one sample.
    fn lift_forward(&mut self, _sample: &LiftSample) -> Result<LiftedGaussians, BackendError> {
        Err("this device does not run the lifting generators".into())
    }

    /// The backward of the last [`RenderHalf::lift_forward`] from the gradients of its
    /// Gaussians (already weighted as the sample's share of the step's loss): returns the
    /// gradient of `f_local` `[F, S, S]` and adds the generators' weight gradients to the
    /// step's sums on the device. When the backend's DPT head computed `f_local`, that
    /// gradient goes on into the head's backward there and the returned one is empty.
    fn lift_backward(&mut self, _grads: &LiftedGaussians) -> Result<Vec<f32>, BackendError> {
        Err("this device does not run the lifting generators".into())
    }

    /// The lifting generators' weight gradients summed since [`RenderHalf::set_lifting_weights`],
    /// by checkpoint key, flattened in the checkpoint's layout.
    fn lifting_grads(&mut self) -> Result<Vec<(String, Vec<f32>)>, BackendError> {
        Err("this device does not run the lifting generators".into())
    }

    /// Whether the backend runs the DPT head ([`RenderHalf::dpt_forward`]); it needs the
    /// backbone and the lifting generators here too.
    fn has_dpt(&self) -> bool {
        false
    }

    /// The DPT head's weights for the coming samples, by checkpoint key
    /// (`base_model.projects.0.weight`, ...); their gradient sums start again.
    fn set_dpt_weights(
        &mut self,
        _weights: &HashMap<String, Vec<f32>>,
    ) -> Result<(), BackendError> {
        Err("this device does not run the DPT head".into())
    }

    /// One sample's DPT head, from the backbone's four outputs (`[grid^2, vit_dim]` each, as
    /// [`RenderHalf::backbone`] returns them) and the normalised DINO input `[3, D, D]`:
    /// `F_local` stays on the device for the next [`RenderHalf::lift_forward`] (given no
    /// `f_local`), and its gradient for the head's backward.
    fn dpt_forward(&mut self, _tokens: [&[f32]; 4], _image: &[f32]) -> Result<(), BackendError> {
        Err("this device does not run the DPT head".into())
    }

    /// The DPT head's weight gradients summed since [`RenderHalf::set_dpt_weights`], by
    /// checkpoint key, flattened in the checkpoint's layout.
    fn dpt_grads(&mut self) -> Result<Vec<(String, Vec<f32>)>, BackendError> {
        Err("this device does not run the DPT head".into())
    }

    /// The renderer's weights for the coming samples, by key relative to `upsampler.`.
    fn set_renderer_weights(
        &mut self,
        weights: &HashMap<String, Vec<f32>>,
    ) -> Result<(), BackendError>;

    /// Splats and renders `sample`, evaluates the image terms at head-box size `box_size`;
    /// `crops`: also return the two crops (for a term computed on them by the caller).
    fn forward(
        &mut self,
        sample: &RenderSample,
        box_size: usize,
        crops: bool,
    ) -> Result<RenderForward, BackendError>;

    /// The backward of the last forward, with `crop_grads` (the caller's own term's gradients
    /// of the two crops) added to the box terms'. Returns the Gaussians' gradients of the
    /// sample's own terms; the renderer weights' gradients, times `renderer_scale`, are added
    /// to the step's sums on the device ([`RenderHalf::renderer_grads`]).
    fn backward(
        &mut self,
        crop_grads: Option<[&[f32]; 2]>,
        renderer_scale: f32,
    ) -> Result<RenderGrads, BackendError>;

    /// The renderer weights' gradients summed (each sample's times its `renderer_scale`) over
    /// the backward calls since the last call, by key relative to `upsampler.`, flattened in
    /// the checkpoint's layout; the sums then start again.
    fn renderer_grads(&mut self) -> Result<Vec<(String, Vec<f32>)>, BackendError>;
}
