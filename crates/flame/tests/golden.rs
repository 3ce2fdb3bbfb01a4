//! The Rust forward pass, landmarks and projection against the independent NumPy reference
//! (tools/reference/flame_reference.py). Regenerate the goldens with the commands in
//! tools/reference/README.md.

mod common;

use candle_core::{DType, Device, Tensor};
use common::*;
use gagavatar_flame::landmarks::project_point;
use gagavatar_flame::{
    project_points, synthesize, BasisLayout, FlameAsset, FlameConfig, FlameModel, FlameParams,
    LoadOptions,
};

/// f32 forward vs f64 reference on x5-scaled coordinates (|x| < ~1): a few hundred f32
/// roundings (400-term blendshape sums, 5-joint chains) stay well below this.
const GOLDEN_TOL: f64 = 1e-5;
/// The f64 forward against the f64 reference: only the order of f64 sums (a few hundred terms
/// of |x| < ~1) differs, ~1e-14 at worst; measured 2.2e-16.
const GOLDEN_F64_TOL: f64 = 1e-12;
/// Pixels are ~340x the NDC-scaled camera coordinates (focal 12 * 512 / 2 / depth ~9), so the
/// same f32 error becomes a few 1e-4 px.
const PIXEL_TOL: f64 = 2e-3;

fn params_from(
    g: &std::collections::HashMap<String, Tensor>,
    prefix: &str,
    n: Option<(usize, usize, usize)>,
) -> FlameParams {
    let f = |k: &str| {
        get(g, &format!("{prefix}{k}"))
            .to_dtype(DType::F32)
            .unwrap()
    };
    let (mut shape, mut exp) = (f("shape"), f("expression"));
    let (mut pose, mut eye) = (f("pose"), f("eye"));
    if let Some((b, ns, ne)) = n {
        shape = shape.narrow(0, 0, b).unwrap().narrow(1, 0, ns).unwrap();
        exp = exp.narrow(0, 0, b).unwrap().narrow(1, 0, ne).unwrap();
        pose = pose.narrow(0, 0, b).unwrap();
        eye = eye.narrow(0, 0, b).unwrap();
    }
    FlameParams {
        shape,
        expression: exp,
        pose,
        eye,
    }
}

fn check_fingerprint(asset: &FlameAsset, g: &std::collections::HashMap<String, Tensor>) {
    let sums = [
        (
            "asset.v_template_sum",
            asset.v_template.iter().map(|&x| x as f64).sum::<f64>(),
        ),
        (
            "asset.shapedirs_abs_sum",
            asset
                .shapedirs
                .iter()
                .map(|&x| (x as f64).abs())
                .sum::<f64>(),
        ),
        (
            "asset.posedirs_abs_sum",
            asset
                .posedirs
                .iter()
                .map(|&x| (x as f64).abs())
                .sum::<f64>(),
        ),
    ];
    for (k, actual) in sums {
        let expected = flat_f64(get(g, k))[0];
        assert!(
            (expected - actual).abs() <= 1e-9 * expected.abs().max(1.0),
            "{k}: golden {expected}, generated {actual}: the synthetic asset changed; regenerate the goldens (tools/reference/README.md)"
        );
    }
}

#[test]
fn synthetic_asset_matches_numpy_reference() {
    let g = load_golden("flame_synth_golden.safetensors");
    let asset = synthesize(0);
    check_fingerprint(&asset, &g);
    let model = FlameModel::new(&asset, FlameConfig::default(), &Device::Cpu, DType::F32).unwrap();
    let p = params_from(&g, "", None);
    let out = model.forward(&p).unwrap();
    let ev = assert_close(
        "vertices",
        &flat_f64(get(&g, "vertices")),
        &flat_f64(&out.vertices),
        GOLDEN_TOL,
    );
    let ej = assert_close(
        "joints",
        &flat_f64(get(&g, "joints")),
        &flat_f64(&out.joints),
        GOLDEN_TOL,
    );

    let lm = model.landmarks(&out.vertices, &p.pose).unwrap();
    let rows: Vec<usize> = flat_f64(get(&g, "dynamic_rows"))
        .iter()
        .map(|&r| r as usize)
        .collect();
    assert_eq!(lm.dynamic_rows, rows, "dynamic contour rows");
    let el = assert_close(
        "lmk68",
        &flat_f64(get(&g, "lmk68")),
        &flat_f64(&lm.lmk68),
        GOLDEN_TOL,
    );
    let ef = assert_close(
        "full",
        &flat_f64(get(&g, "full")),
        &flat_f64(&lm.full),
        GOLDEN_TOL,
    );

    // Projection: the f64 host function on the reference landmarks is exact; the tensor version
    // on our f32 landmarks carries the f32 error magnified to pixels.
    let tm = get(&g, "transform");
    let tm_host = flat_f64(tm);
    let lmk_ref = flat_f64(get(&g, "lmk68"));
    let px_ref = flat_f64(get(&g, "pixels68"));
    let nl = 68;
    let mut px_host = Vec::new();
    for b in 0..4 {
        let m: [[f64; 4]; 3] =
            std::array::from_fn(|r| std::array::from_fn(|c| tm_host[b * 12 + r * 4 + c]));
        for l in 0..nl {
            let o = (b * nl + l) * 3;
            let p = project_point([lmk_ref[o], lmk_ref[o + 1], lmk_ref[o + 2]], &m, 512, 512)
                .expect("landmark in front of the camera");
            px_host.extend(p);
        }
    }
    assert_close("pixels (host, f64)", &px_ref, &px_host, 1e-9);
    let px = project_points(&lm.lmk68, &tm.to_dtype(DType::F32).unwrap(), 512, 512).unwrap();
    let ep = assert_close("pixels (tensor, f32)", &px_ref, &flat_f64(&px), PIXEL_TOL);
    // Landmarks of a centred head land inside the image.
    assert!(px_ref.iter().all(|&x| (0.0..512.0).contains(&x)));
    println!("max |err|: vertices {ev:e}, joints {ej:e}, lmk68 {el:e}, full {ef:e}, pixels {ep:e}");
}

#[test]
fn fewer_components_match_numpy_reference() {
    let g = load_golden("flame_synth_golden.safetensors");
    let asset = synthesize(0);
    let config = FlameConfig {
        n_shape: 100,
        n_exp: 50,
        ..FlameConfig::default()
    };
    let model = FlameModel::new(&asset, config, &Device::Cpu, DType::F32).unwrap();
    let out = model
        .forward(&params_from(&g, "", Some((2, 100, 50))))
        .unwrap();
    assert_close(
        "reduced vertices",
        &flat_f64(get(&g, "reduced.vertices")),
        &flat_f64(&out.vertices),
        GOLDEN_TOL,
    );
    assert_close(
        "reduced joints",
        &flat_f64(get(&g, "reduced.joints")),
        &flat_f64(&out.joints),
        GOLDEN_TOL,
    );
}

#[test]
fn torch_pickle_asset_matches_numpy_reference() {
    let path = golden_dir().join("tiny_flame.pt");
    let layout = BasisLayout {
        shape: 6,
        expression: 4,
    };
    let asset = FlameAsset::load(
        &path,
        &LoadOptions {
            layout: Some(layout),
        },
    )
    .unwrap();
    assert_eq!(asset.n_vertices, 40);
    assert_eq!(asset.n_faces(), 60);
    assert_eq!(asset.parents, [0, 0, 1, 1, 1]);
    assert_eq!(asset.landmarks.full_faces.len(), 7);
    let g = load_golden("tiny_golden.safetensors");
    let config = FlameConfig {
        n_shape: 6,
        n_exp: 4,
        ..FlameConfig::default()
    };
    for (dtype, tol) in [(DType::F32, GOLDEN_TOL), (DType::F64, GOLDEN_F64_TOL)] {
        let model = FlameModel::new(&asset, config, &Device::Cpu, dtype).unwrap();
        let f = |k: &str| get(&g, k).to_dtype(dtype).unwrap();
        let p = FlameParams {
            shape: f("shape"),
            expression: f("expression"),
            pose: f("pose"),
            eye: f("eye"),
        };
        let out = model.forward(&p).unwrap();
        let lm = model.landmarks(&out.vertices, &p.pose).unwrap();
        let rows: Vec<usize> = flat_f64(get(&g, "dynamic_rows"))
            .iter()
            .map(|&r| r as usize)
            .collect();
        assert_eq!(lm.dynamic_rows, rows);
        let mut worst = 0.0f64;
        for (key, got) in [
            ("vertices", &out.vertices),
            ("joints", &out.joints),
            ("lmk68", &lm.lmk68),
            ("full", &lm.full),
        ] {
            let what = format!("tiny {key} ({dtype:?})");
            let d = assert_close(&what, &flat_f64(get(&g, key)), &flat_f64(got), tol);
            worst = worst.max(d);
        }
        eprintln!("tiny asset, {dtype:?}: max abs error {worst:e} (tolerance {tol:e})");
    }
    // The release layout (400 columns) is the default; a reduced file needs it spelled out.
    let err = FlameAsset::load(&path, &LoadOptions::default()).unwrap_err();
    assert!(err.to_string().contains("flame_model.shapedirs"), "{err}");
    // Asking the model for more components than the file has is a clear error.
    let err =
        FlameModel::new(&asset, FlameConfig::default(), &Device::Cpu, DType::F32).unwrap_err();
    assert!(
        matches!(
            err,
            gagavatar_flame::FlameError::Components {
                available: 6,
                requested: 300,
                ..
            }
        ),
        "{err}"
    );
}

#[test]
fn safetensors_round_trip_preserves_the_asset() {
    let asset = synthesize(3);
    let bytes = asset.to_safetensors_bytes().unwrap();
    let dir = std::env::temp_dir().join(format!("gagavatar-flame-rt-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("a.safetensors");
    std::fs::write(&path, bytes).unwrap();
    let back = FlameAsset::load(&path, &LoadOptions::default()).unwrap();
    assert!(back == asset, "asset changed through safetensors");
    let _ = std::fs::remove_dir_all(&dir);
}
