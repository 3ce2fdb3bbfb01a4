//! CSIM with a user's ArcFace model (the paper's identity network) from an ONNX file, e.g.
//! InsightFace's IResNet-50 / 100 exports. No weights ship with the project: users bring the
//! file. The graph is read by `gagavatar_formats::onnx` and run here node by node on candle, for the
//! operators such feed-forward face-recognition networks use: Conv (groups, dilations,
//! asymmetric pads), BatchNormalization, PRelu, Relu, Add, Sub, Mul, Div, Flatten, Gemm,
//! MatMul, Reshape, GlobalAveragePool, Identity, Dropout (inference) and Constant (folded at
//! load). Any other operator is
//! refused when the file is loaded, naming it.
//!
//! Input: the face aligned to ArcFace's 112 x 112 five-point template (eye centres, nose tip,
//! mouth corners: MediaPipe landmarks 468, 473, 1, 61, 291) by a least-squares similarity,
//! bilinear sampling with pixel centres at integer coordinates (OpenCV's `warpAffine`), RGB,
//! `(x - 127.5) / 127.5`, `[1, 3, 112, 112]`. Output: the descriptor; CSIM is its cosine.

use std::collections::HashMap;
use std::path::Path;

use candle_core::{Device, Tensor, D};
use gagavatar_track::observation::FaceLandmarks;
use image::RgbImage;

use crate::error::{input_err, Result};
use crate::geometry::similarity_transform;
use gagavatar_formats::onnx::{parse_model, Attribute, Data, Node, OnnxGraph};

/// ArcFace's input side.
pub const ARCFACE_SIZE: u32 = 112;

/// ArcFace's five-point template in the 112 x 112 crop (pixel-index coordinates): image-left
/// eye, image-right eye, nose tip, image-left and image-right mouth corners.
pub const ARCFACE_TEMPLATE: [[f64; 2]; 5] = [
    [38.2946, 51.6963],
    [73.5318, 51.5014],
    [56.0252, 71.7366],
    [41.5493, 92.3655],
    [70.7299, 92.2041],
];

/// MediaPipe mesh indices of the template's points (iris centres, nose tip, mouth corners).
pub const MEDIAPIPE_FIVE: [usize; 5] = [468, 473, 1, 61, 291];

const SUPPORTED: [&str; 16] = [
    "Constant",
    "Conv",
    "BatchNormalization",
    "PRelu",
    "Relu",
    "Add",
    "Sub",
    "Mul",
    "Div",
    "Flatten",
    "Gemm",
    "MatMul",
    "Reshape",
    "GlobalAveragePool",
    "Identity",
    "Dropout",
];

/// An ONNX face-recognition network.
#[derive(Debug, Clone)]
pub struct ArcFace {
    graph: OnnxGraph,
    consts: HashMap<String, Tensor>,
}

fn err(node: &Node, reason: impl Into<String>) -> crate::error::MetricsError {
    input_err(
        &format!("ONNX node `{}` ({})", node.name, node.op_type),
        reason,
    )
}

impl ArcFace {
    pub fn load(path: &Path) -> Result<Self> {
        let bytes = std::fs::read(path)
            .map_err(|e| input_err(&path.display().to_string(), format!("cannot read: {e}")))?;
        Self::from_bytes(&bytes).map_err(|e| input_err(&path.display().to_string(), e.to_string()))
    }

    pub fn from_bytes(bytes: &[u8]) -> Result<Self> {
        let mut graph = parse_model(bytes)?;
        // Constant nodes become initializers: their values are known before the run.
        let mut kept = Vec::with_capacity(graph.nodes.len());
        for node in std::mem::take(&mut graph.nodes) {
            if node.op_type != "Constant" {
                kept.push(node);
                continue;
            }
            let (Some(out), Some(Attribute::Tensor(t))) =
                (node.outputs.first(), node.attributes.get("value"))
            else {
                return Err(err(&node, "only `value` tensor constants are supported"));
            };
            let mut t = t.clone();
            t.name = out.clone();
            graph.initializers.insert(out.clone(), t);
        }
        graph.nodes = kept;
        let mut unsupported: Vec<&str> = graph
            .nodes
            .iter()
            .map(|n| n.op_type.as_str())
            .filter(|op| !SUPPORTED.contains(op))
            .collect();
        unsupported.sort_unstable();
        unsupported.dedup();
        if !unsupported.is_empty() {
            return Err(input_err(
                "ONNX model",
                format!("unsupported operators {unsupported:?} (supported: {SUPPORTED:?})"),
            ));
        }
        if graph.inputs.len() != 1 {
            return Err(input_err(
                "ONNX model",
                format!(
                    "{} data inputs, expected one image input",
                    graph.inputs.len()
                ),
            ));
        }
        let mut consts = HashMap::new();
        for (name, t) in &graph.initializers {
            if let Data::F32(v) = &t.data {
                consts.insert(
                    name.clone(),
                    Tensor::from_vec(v.clone(), t.dims.as_slice(), &Device::Cpu)?,
                );
            }
        }
        Ok(Self { graph, consts })
    }

    fn int64s(&self, name: &str) -> Option<&[i64]> {
        match &self.graph.initializers.get(name)?.data {
            Data::I64(v) => Some(v),
            Data::F32(_) => None,
        }
    }

    /// Runs the graph on `x` (`[N, 3, 112, 112]`, normalised); the first output.
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        self.run(x, &mut |_, _| {})
    }

    /// [`Self::forward`], calling `trace(output name, value)` after each node (to compare a
    /// model's intermediate values with another runtime's).
    pub fn run(&self, x: &Tensor, trace: &mut dyn FnMut(&str, &Tensor)) -> Result<Tensor> {
        let mut values: HashMap<&str, Tensor> = HashMap::new();
        values.insert(self.graph.inputs[0].as_str(), x.clone());
        for node in &self.graph.nodes {
            let get = |i: usize| -> Result<Tensor> {
                let name = node
                    .inputs
                    .get(i)
                    .filter(|n| !n.is_empty())
                    .ok_or_else(|| err(node, format!("input {i} missing")))?;
                values
                    .get(name.as_str())
                    .or_else(|| self.consts.get(name))
                    .cloned()
                    .ok_or_else(|| err(node, format!("input `{name}` is not computed yet")))
            };
            let has = |i: usize| node.inputs.get(i).is_some_and(|n| !n.is_empty());
            let y = match node.op_type.as_str() {
                "Conv" => self.conv(
                    node,
                    &get(0)?,
                    &get(1)?,
                    if has(2) { Some(get(2)?) } else { None },
                )?,
                "BatchNormalization" => {
                    let x = get(0)?;
                    let eps = node.float("epsilon").unwrap_or(1e-5) as f64;
                    let (scale, bias, mean, var) = (get(1)?, get(2)?, get(3)?, get(4)?);
                    let a = (scale / (var + eps)?.sqrt()?)?;
                    let b = (bias - (mean * &a)?)?;
                    let shape = channel_shape(&x, a.elem_count());
                    x.broadcast_mul(&a.reshape(shape.as_slice())?)?
                        .broadcast_add(&b.reshape(shape.as_slice())?)?
                }
                "PRelu" => {
                    let x = get(0)?;
                    let slope = get(1)?;
                    let slope = if slope.rank() == 1 && x.rank() > 2 {
                        slope.reshape(channel_shape(&x, slope.elem_count()).as_slice())?
                    } else {
                        slope
                    };
                    let neg = x.neg()?.relu()?;
                    (x.relu()? - neg.broadcast_mul(&slope)?)?
                }
                "Relu" => get(0)?.relu()?,
                "Add" => get(0)?.broadcast_add(&get(1)?)?,
                "Sub" => get(0)?.broadcast_sub(&get(1)?)?,
                "Mul" => get(0)?.broadcast_mul(&get(1)?)?,
                "Div" => get(0)?.broadcast_div(&get(1)?)?,
                "Flatten" => {
                    let x = get(0)?;
                    let axis = node.int("axis").unwrap_or(1);
                    let axis = if axis < 0 {
                        axis + x.rank() as i64
                    } else {
                        axis
                    };
                    let axis = usize::try_from(axis)
                        .ok()
                        .filter(|&a| a <= x.rank())
                        .ok_or_else(|| err(node, format!("axis {axis}")))?;
                    let d = x.dims();
                    let a: usize = d[..axis].iter().product();
                    let b: usize = d[axis..].iter().product();
                    x.reshape((a, b))?
                }
                "Gemm" => {
                    let (mut a, mut b) = (get(0)?, get(1)?);
                    if node.int("transA").unwrap_or(0) != 0 {
                        a = a.t()?;
                    }
                    if node.int("transB").unwrap_or(0) != 0 {
                        b = b.t()?;
                    }
                    let alpha = node.float("alpha").unwrap_or(1.0) as f64;
                    let beta = node.float("beta").unwrap_or(1.0) as f64;
                    let mut y = (a.contiguous()?.matmul(&b.contiguous()?)? * alpha)?;
                    if has(2) {
                        y = y.broadcast_add(&(get(2)? * beta)?)?;
                    }
                    y
                }
                "MatMul" => get(0)?
                    .contiguous()?
                    .broadcast_matmul(&get(1)?.contiguous()?)?,
                "Reshape" => {
                    let x = get(0)?;
                    let name = node.inputs.get(1).map(String::as_str).unwrap_or("");
                    let spec = self
                        .int64s(name)
                        .ok_or_else(|| err(node, "the shape must be an int64 initializer"))?;
                    x.reshape(reshape_dims(x.dims(), spec).map_err(|r| err(node, r))?)?
                }
                "GlobalAveragePool" => get(0)?.mean_keepdim(D::Minus1)?.mean_keepdim(D::Minus2)?,
                "Identity" | "Dropout" => get(0)?,
                other => return Err(err(node, format!("operator {other} is not supported"))),
            };
            let out = node.outputs.first().ok_or_else(|| err(node, "no output"))?;
            trace(out, &y);
            values.insert(out.as_str(), y);
        }
        let name = &self.graph.outputs[0];
        values
            .remove(name.as_str())
            .ok_or_else(|| input_err("ONNX model", format!("output `{name}` was never computed")))
    }

    fn conv(&self, node: &Node, x: &Tensor, w: &Tensor, b: Option<Tensor>) -> Result<Tensor> {
        let ints = |k: &str, d: &[i64]| node.ints(k).map(<[i64]>::to_vec).unwrap_or(d.to_vec());
        let strides = ints("strides", &[1, 1]);
        let dil = ints("dilations", &[1, 1]);
        let pads = ints("pads", &[0, 0, 0, 0]);
        let group = node.int("group").unwrap_or(1);
        if node
            .attributes
            .get("auto_pad")
            .is_some_and(|a| !matches!(a, Attribute::Bytes(b) if b == b"NOTSET"))
        {
            return Err(err(
                node,
                "auto_pad is not supported; export with explicit pads",
            ));
        }
        if strides.len() != 2 || strides[0] != strides[1] || dil.len() != 2 || dil[0] != dil[1] {
            return Err(err(
                node,
                format!("strides {strides:?} / dilations {dil:?}: 2-D, equal per axis"),
            ));
        }
        if pads.len() != 4 || pads.iter().any(|&p| p < 0) || group < 1 {
            return Err(err(node, format!("pads {pads:?}, group {group}")));
        }
        let p = |i: usize| pads[i] as usize;
        let (x, pad) = if p(0) == p(2) && p(1) == p(3) && p(0) == p(1) {
            (x.clone(), p(0))
        } else {
            (
                x.pad_with_zeros(2, p(0), p(2))?
                    .pad_with_zeros(3, p(1), p(3))?,
                0,
            )
        };
        let y = x.conv2d(w, pad, strides[0] as usize, dil[0] as usize, group as usize)?;
        Ok(match b {
            Some(b) => y.broadcast_add(&b.reshape((1, b.elem_count(), 1, 1))?)?,
            None => y,
        })
    }

    /// The face aligned to the template, 112 x 112.
    pub fn align(img: &RgbImage, lm: &FaceLandmarks) -> Result<RgbImage> {
        if !lm.has_irises() {
            return Err(input_err(
                "face landmarks",
                "ArcFace alignment needs the 478-point mesh",
            ));
        }
        let pts = lm.points();
        // Landmarks are in the corner convention; the template in pixel indices.
        let five: Vec<[f64; 2]> = MEDIAPIPE_FIVE
            .iter()
            .map(|&i| [pts[i][0] - 0.5, pts[i][1] - 0.5])
            .collect();
        let to_image = similarity_transform(&ARCFACE_TEMPLATE, &five);
        Ok(warp_bilinear(
            img,
            |x, y| to_image.apply([x, y]),
            ARCFACE_SIZE,
        ))
    }

    /// The descriptor of the face with these landmarks.
    pub fn embed(&self, img: &RgbImage, lm: &FaceLandmarks) -> Result<Vec<f32>> {
        let chip = Self::align(img, lm)?;
        let s = ARCFACE_SIZE as usize;
        let x = Tensor::from_vec(chip.into_raw(), (s, s, 3), &Device::Cpu)?
            .permute((2, 0, 1))?
            .unsqueeze(0)?
            .to_dtype(candle_core::DType::F32)?;
        let x = ((x - 127.5)? / 127.5)?;
        let y = self.forward(&x)?.flatten_all()?.to_vec1::<f32>()?;
        if y.is_empty() || y.iter().any(|v| !v.is_finite()) {
            return Err(input_err(
                "ArcFace",
                "the descriptor is empty or not finite",
            ));
        }
        Ok(y)
    }
}

/// `[1, C, 1, 1]` (rank 4) or `[1, C]` (rank 2) to broadcast per-channel values.
fn channel_shape(x: &Tensor, c: usize) -> Vec<usize> {
    let mut s = vec![1; x.rank().max(2)];
    s[1] = c;
    s
}

/// ONNX Reshape's shape: 0 copies the input's dimension, one -1 is inferred.
pub fn reshape_dims(input: &[usize], spec: &[i64]) -> std::result::Result<Vec<usize>, String> {
    let total: usize = input.iter().product();
    let mut out = Vec::with_capacity(spec.len());
    let mut infer = None;
    for (i, &d) in spec.iter().enumerate() {
        match d {
            0 => out.push(
                *input
                    .get(i)
                    .ok_or_else(|| format!("shape {spec:?}: no dim {i} to copy"))?,
            ),
            -1 if infer.is_none() => {
                infer = Some(i);
                out.push(1);
            }
            d if d > 0 => out.push(d as usize),
            _ => return Err(format!("shape {spec:?} is not valid")),
        }
    }
    let known: usize = out.iter().product();
    if let Some(i) = infer {
        if known == 0 || !total.is_multiple_of(known) {
            return Err(format!("shape {spec:?} does not divide {total} values"));
        }
        out[i] = total / known;
    }
    if out.iter().product::<usize>() != total {
        return Err(format!("shape {spec:?} does not hold {total} values"));
    }
    Ok(out)
}

/// Cosine of two descriptors.
pub fn cosine(a: &[f32], b: &[f32]) -> Result<f64> {
    if a.len() != b.len() || a.is_empty() {
        return Err(input_err(
            "descriptors",
            format!("lengths {} and {}", a.len(), b.len()),
        ));
    }
    let (mut ab, mut aa, mut bb) = (0f64, 0f64, 0f64);
    for (x, y) in a.iter().zip(b) {
        let (x, y) = (*x as f64, *y as f64);
        ab += x * y;
        aa += x * x;
        bb += y * y;
    }
    let d = (aa * bb).sqrt();
    if !(d > 0.0 && d.is_finite()) {
        return Err(input_err("descriptors", "zero or non-finite descriptor"));
    }
    Ok((ab / d).clamp(-1.0, 1.0))
}

/// `size x size` image whose pixel `(x, y)` samples `img` at `map(x, y)` (pixel indices),
/// bilinear, black outside.
fn warp_bilinear(img: &RgbImage, map: impl Fn(f64, f64) -> [f64; 2], size: u32) -> RgbImage {
    let (w, h) = (img.width() as i64, img.height() as i64);
    let px = |x: i64, y: i64, c: usize| -> f64 {
        if x < 0 || y < 0 || x >= w || y >= h {
            0.0
        } else {
            img.get_pixel(x as u32, y as u32)[c] as f64
        }
    };
    RgbImage::from_fn(size, size, |x, y| {
        let [sx, sy] = map(x as f64, y as f64);
        if !(sx.is_finite() && sy.is_finite()) {
            return image::Rgb([0, 0, 0]);
        }
        let (x0, y0) = (sx.floor(), sy.floor());
        let (fx, fy) = (sx - x0, sy - y0);
        let (x0, y0) = (x0 as i64, y0 as i64);
        let mut out = [0u8; 3];
        for (c, o) in out.iter_mut().enumerate() {
            let v = px(x0, y0, c) * (1.0 - fx) * (1.0 - fy)
                + px(x0 + 1, y0, c) * fx * (1.0 - fy)
                + px(x0, y0 + 1, c) * (1.0 - fx) * fy
                + px(x0 + 1, y0 + 1, c) * fx * fy;
            *o = v.round().clamp(0.0, 255.0) as u8;
        }
        image::Rgb(out)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reshape_rules() {
        assert_eq!(reshape_dims(&[2, 3, 4], &[0, -1]).unwrap(), [2, 12]);
        assert_eq!(reshape_dims(&[2, 3, 4], &[4, 6]).unwrap(), [4, 6]);
        assert!(reshape_dims(&[2, 3, 4], &[5, -1]).is_err());
        assert!(reshape_dims(&[2, 3, 4], &[-1, -1]).is_err());
        assert!(reshape_dims(&[2, 3, 4], &[7, 7]).is_err());
    }

    #[test]
    fn template_points_align_onto_themselves() {
        // A mesh whose five points sit on the template (+0.5: corner convention): the chip is
        // the image itself.
        let mut pts = vec![[60.0, 60.0]; 478];
        for (k, &i) in MEDIAPIPE_FIVE.iter().enumerate() {
            pts[i] = [ARCFACE_TEMPLATE[k][0] + 0.5, ARCFACE_TEMPLATE[k][1] + 0.5];
        }
        let lm = FaceLandmarks::new(pts).unwrap();
        let img = RgbImage::from_fn(112, 112, |x, y| {
            image::Rgb([x as u8, y as u8, (x ^ y) as u8])
        });
        let chip = ArcFace::align(&img, &lm).unwrap();
        assert_eq!(chip.as_raw(), img.as_raw());
    }

    #[test]
    fn cosine_checks() {
        assert!((cosine(&[1.0, 0.0], &[2.0, 0.0]).unwrap() - 1.0).abs() < 1e-12);
        assert!(cosine(&[0.0], &[1.0]).is_err());
        assert!(cosine(&[1.0], &[1.0, 2.0]).is_err());
    }
}
