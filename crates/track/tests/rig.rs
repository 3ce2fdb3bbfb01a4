//! The landmark rig against the FLAME crate's forward pass and landmarks (candle, f64), and its
//! Jacobian against central differences.

use candle_core::{DType, Device, Tensor};
use gagavatar_flame::{synthesize, FlameConfig, FlameModel, FlameParams};
use gagavatar_track::rig::{FaceCodes, LandmarkRig, RigColumns, N_LANDMARKS};

fn codes(rig: &LandmarkRig, scale: f64) -> FaceCodes {
    FaceCodes {
        shape: (0..rig.n_shape)
            .map(|i| scale * ((i as f64) * 0.37).sin())
            .collect(),
        expression: (0..rig.n_exp)
            .map(|i| scale * ((i as f64) * 0.91).cos())
            .collect(),
        jaw: [0.25 * scale, 0.04, -0.03],
        eyes: [0.1, -0.25, 0.02, 0.15, 0.2, -0.01],
    }
}

/// The rig equals the full FLAME forward + `_with_eye` embedding (global pose 0), in f64.
#[test]
fn rig_matches_the_flame_forward_pass() {
    // Both are f64 sums of the same f32 data in different orders: ~1e-15 relative.
    const TOL: f64 = 1e-11;
    let asset = synthesize(0);
    let rig = LandmarkRig::from_asset(&asset).unwrap();
    let model = FlameModel::new(&asset, FlameConfig::default(), &Device::Cpu, DType::F64).unwrap();
    for scale in [0.0, 0.6] {
        let c = codes(&rig, scale);
        let t = |v: Vec<f64>| {
            let n = v.len();
            Tensor::from_vec(v, (1, n), &Device::Cpu).unwrap()
        };
        let p = FlameParams {
            shape: t(c.shape.clone()),
            expression: t(c.expression.clone()),
            pose: t(vec![0.0, 0.0, 0.0, c.jaw[0], c.jaw[1], c.jaw[2]]),
            eye: t(c.eyes.to_vec()),
        };
        let out = model.forward(&p).unwrap();
        let lm = model.landmarks(&out.vertices, &p.pose).unwrap();
        let want = lm.full.squeeze(0).unwrap().to_vec2::<f64>().unwrap();
        let got = rig.landmarks(&c).unwrap();
        assert_eq!(got.len(), N_LANDMARKS);
        for k in 0..N_LANDMARKS {
            for x in 0..3 {
                assert!(
                    (got[k][x] - want[k][x]).abs() <= TOL,
                    "scale {scale} landmark {k} axis {x}: FLAME {}, rig {}",
                    want[k][x],
                    got[k][x]
                );
            }
        }
    }
}

/// Every derivative column (shape, expression, jaw, eyes) against central differences.
#[test]
fn rig_jacobian_matches_finite_differences() {
    // Step 1e-6 on codes of size ~1, landmarks of size ~1: error ~1e-10.
    const TOL: f64 = 1e-7;
    let asset = synthesize(2);
    let rig = LandmarkRig::new(&asset, 40, 30).unwrap();
    let c = codes(&rig, 0.5);
    let cols = RigColumns { shape: true };
    let out = rig.evaluate(&c, Some(cols)).unwrap();
    let n = cols.count(&rig);
    assert_eq!(out.n_cols, n);
    let h = 1e-6;
    let perturb = |col: usize, d: f64| {
        let mut p = c.clone();
        let (ns, ne) = (rig.n_shape, rig.n_exp);
        if col < ns {
            p.shape[col] += d;
        } else if col < ns + ne {
            p.expression[col - ns] += d;
        } else if col < ns + ne + 3 {
            p.jaw[col - ns - ne] += d;
        } else {
            p.eyes[col - ns - ne - 3] += d;
        }
        rig.landmarks(&p).unwrap()
    };
    for col in 0..n {
        let (a, b) = (perturb(col, h), perturb(col, -h));
        for k in 0..N_LANDMARKS {
            for x in 0..3 {
                let fd = (a[k][x] - b[k][x]) / (2.0 * h);
                let an = out.jacobian[(k * 3 + x) * n + col];
                assert!(
                    (fd - an).abs() <= TOL,
                    "column {col} landmark {k} axis {x}: finite difference {fd}, analytic {an}"
                );
            }
        }
    }
    // Without the shape columns the rest is the same matrix minus its first block.
    let short = rig.evaluate(&c, Some(RigColumns { shape: false })).unwrap();
    let ns = rig.n_shape;
    for r in 0..N_LANDMARKS * 3 {
        for col in 0..short.n_cols {
            assert_eq!(
                short.jacobian[r * short.n_cols + col],
                out.jacobian[r * n + ns + col]
            );
        }
    }
}

#[test]
fn rig_rejects_bad_inputs() {
    let asset = synthesize(0);
    let rig = LandmarkRig::new(&asset, 10, 10).unwrap();
    let mut c = FaceCodes::zeros(&rig);
    c.shape.push(0.0);
    let err = rig.landmarks(&c).unwrap_err().to_string();
    assert!(err.contains("11 shape"), "{err}");
    let err = LandmarkRig::new(&asset, 301, 10).unwrap_err().to_string();
    assert!(err.contains("301"), "{err}");
    let mut small = asset.clone();
    small.landmarks.full_faces.truncate(68);
    small.landmarks.full_bary.truncate(68);
    let err = LandmarkRig::from_asset(&small).unwrap_err().to_string();
    assert!(err.contains("68 points"), "{err}");
}
