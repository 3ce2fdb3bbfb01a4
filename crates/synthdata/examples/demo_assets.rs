//! Writes the demo's source and driving sequence (`assets/demo/`) from a synthetic dataset's
//! held-out identities: the source is frame 0 of identity S (exactly as in the dataset), the
//! driver a smooth sequence of identity D (its sampled expressions blended in turn, the camera
//! swinging around the front), with rendered frames for side-by-side videos.
//!
//! cargo run --release -p gagavatar-synthdata --example demo_assets -- \
//!     OUT_DIR IDENTITIES FRAMES SIZE SEED SOURCE_ID DRIVER_ID N_DRIVER_FRAMES

use std::path::PathBuf;

use gagavatar_flame::synthesize;
use gagavatar_splat::Camera;
use gagavatar_synthdata::{FrameSample, Generator, SynthConfig};

fn record_json(r: &gagavatar_flame::TrackedFrame, image: Option<&str>) -> serde_json::Value {
    let f32s = |v: &[f64]| v.iter().map(|&x| x as f32).collect::<Vec<_>>();
    let mut o = serde_json::json!({
        "shapecode": f32s(&r.shapecode),
        "expcode": f32s(&r.expcode),
        "posecode": f32s(&r.posecode),
        "eyecode": f32s(&r.eyecode),
        "transform_matrix": r.transform_matrix.map(|m| m.map(|row| row.map(|x| x as f32))),
        "bbox": r.bbox.map(|b| b.map(|x| x as f32)),
    });
    if let Some(img) = image {
        o["image"] = serde_json::json!(img);
    }
    o
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.len() != 8 {
        return Err("usage: OUT IDENTITIES FRAMES SIZE SEED SOURCE_ID DRIVER_ID N_DRIVER".into());
    }
    let out = PathBuf::from(&args[0]);
    let n: Vec<usize> = args[1..]
        .iter()
        .map(|a| a.parse())
        .collect::<Result<_, _>>()?;
    let (ids, frames, size, seed, src, drv, n_driver) =
        (n[0], n[1], n[2], n[3] as u64, n[4], n[5], n[6]);
    let gen = Generator::new(&synthesize(0), SynthConfig::new(ids, frames, size, seed))?;
    std::fs::create_dir_all(out.join("driver"))?;

    let shape = gen.shape(src);
    let s0 = gen.frame_sample(src, 0);
    let v = gen.pose(&shape, std::slice::from_ref(&s0))?;
    gen.shade(&gen.appearance(src), &s0.transform, &v[0])?
        .save(out.join("source.png"))?;
    let rec = gen.record(&shape, &s0, &v[0]);
    std::fs::write(
        out.join("source.json"),
        serde_json::to_string_pretty(&record_json(&rec, None))?,
    )?;

    // Driver: blend the identity's sampled frames in turn (smoothstep), camera on a loop.
    let keys: Vec<FrameSample> = (0..frames).map(|f| gen.frame_sample(drv, f)).collect();
    let dshape = gen.shape(drv);
    let look = gen.appearance(drv);
    let mut samples = Vec::with_capacity(n_driver);
    for i in 0..n_driver {
        let t = i as f64 / n_driver as f64;
        let pos = t * keys.len() as f64;
        let (k, u) = (pos.floor() as usize % keys.len(), pos.fract());
        let u = u * u * (3.0 - 2.0 * u);
        let (a, b) = (&keys[k], &keys[(k + 1) % keys.len()]);
        let mix = |x: f64, y: f64| x + (y - x) * u;
        let tau = std::f64::consts::TAU;
        let yaw = std::f64::consts::PI + 0.45 * (tau * t).sin();
        let pitch = 0.2 * (2.0 * tau * t).sin();
        samples.push(FrameSample {
            expression: a
                .expression
                .iter()
                .zip(&b.expression)
                .map(|(&x, &y)| mix(x, y))
                .collect(),
            pose: std::array::from_fn(|j| mix(a.pose[j], b.pose[j])),
            eye: std::array::from_fn(|j| mix(a.eye[j], b.eye[j])),
            transform: Camera::look_at_origin_matrix(9.0, yaw, pitch),
        });
    }
    let verts = gen.pose(&dshape, &samples)?;
    let mut frames_json = Vec::new();
    for (i, (s, v)) in samples.iter().zip(&verts).enumerate() {
        let name = format!("driver/frame_{i:04}.png");
        gen.shade(&look, &s.transform, v)?.save(out.join(&name))?;
        let mut r = gen.record(&dshape, s, v);
        // Only the driver's expression, jaw, eyes and camera are used; the identity is ours.
        r.shapecode.clear();
        frames_json.push(record_json(&r, Some(&name)));
    }
    std::fs::write(
        out.join("driver.json"),
        serde_json::to_string(&serde_json::json!({"fps": 25, "frames": frames_json}))?,
    )?;
    println!(
        "wrote {}: source = identity {src} frame 0, driver = identity {drv}, {n_driver} frames",
        out.display()
    );
    Ok(())
}
