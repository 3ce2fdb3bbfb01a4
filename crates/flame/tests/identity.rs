//! The cached-identity driving path (`identity` once, `forward_with_identity` per frame) against
//! the full forward: same vertices, joints and rotations, same gradients, clean input errors.

use candle_core::{DType, Device, Tensor, Var};
use gagavatar_flame::{synthesize, FlameConfig, FlameError, FlameModel, FlameOutput, FlameParams};

fn model(dtype: DType, config: FlameConfig) -> FlameModel {
    FlameModel::new(&synthesize(3), config, &Device::Cpu, dtype).unwrap()
}

/// Deterministic codes of realistic size (unit-variance shape/expression, small rotations).
fn codes(model: &FlameModel, batch: usize, n: usize, scale: f64, salt: u64) -> Tensor {
    let mut s = salt.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1;
    let v: Vec<f64> = (0..batch * n)
        .map(|_| {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            ((s >> 11) as f64 / (1u64 << 53) as f64 - 0.5) * 2.0 * scale
        })
        .collect();
    Tensor::from_vec(v, (batch, n), &model.device)
        .unwrap()
        .to_dtype(model.dtype)
        .unwrap()
}

fn frames(model: &FlameModel, batch: usize) -> FlameParams {
    let c = model.config;
    FlameParams {
        shape: codes(model, 1, c.n_shape, 1.5, 1)
            .repeat((batch, 1))
            .unwrap(),
        expression: codes(model, batch, c.n_exp, 1.5, 2),
        pose: codes(model, batch, 6, 0.3, 3),
        eye: codes(model, batch, 6, 0.2, 4),
    }
}

fn max_abs_diff(a: &Tensor, b: &Tensor) -> f64 {
    assert_eq!(a.dims(), b.dims());
    (a - b)
        .unwrap()
        .abs()
        .unwrap()
        .flatten_all()
        .unwrap()
        .max(0)
        .unwrap()
        .to_dtype(DType::F64)
        .unwrap()
        .to_scalar::<f64>()
        .unwrap()
}

fn assert_same(full: &FlameOutput, cached: &FlameOutput, tol: f64, label: &str) {
    for (name, a, b) in [
        ("vertices", &full.vertices, &cached.vertices),
        ("joints", &full.joints, &cached.joints),
        ("rotations", &full.rotations, &cached.rotations),
    ] {
        let d = max_abs_diff(a, b);
        assert!(d <= tol, "{label}: {name} differ by {d:e} (> {tol:e})");
    }
}

#[test]
fn one_cached_shape_matches_the_full_forward_for_every_frame() {
    let m = model(DType::F32, FlameConfig::default());
    for batch in [1, 7] {
        let p = frames(&m, batch);
        let full = m.forward(&p).unwrap();
        let id = m.identity(&p.shape.narrow(0, 0, 1).unwrap()).unwrap();
        assert_eq!(id.batch(), 1);
        let cached = m
            .forward_with_identity(&id, &p.expression, &p.pose, &p.eye)
            .unwrap();
        assert_same(&full, &cached, 1e-6, &format!("f32, batch {batch}"));
        // The check is meaningful: the frames really differ from each other.
        if batch > 1 {
            let v = &full.vertices;
            let d = max_abs_diff(&v.narrow(0, 0, 1).unwrap(), &v.narrow(0, 1, 1).unwrap());
            assert!(d > 1e-3, "frames barely differ ({d:e})");
        }
    }
}

#[test]
fn per_frame_identities_match_and_f64_agrees_tightly() {
    let m = model(DType::F64, FlameConfig::default());
    let mut p = frames(&m, 4);
    p.shape = codes(&m, 4, 300, 1.5, 9); // a different shape per frame
    let full = m.forward(&p).unwrap();
    let id = m.identity(&p.shape).unwrap();
    assert_eq!(id.batch(), 4);
    let cached = m
        .forward_with_identity(&id, &p.expression, &p.pose, &p.eye)
        .unwrap();
    assert_same(&full, &cached, 1e-12, "f64, per-frame shapes");
}

#[test]
fn reduced_and_empty_bases_work_on_both_paths() {
    for (ns, ne) in [(0, 0), (0, 5), (12, 0), (12, 5)] {
        let config = FlameConfig {
            n_shape: ns,
            n_exp: ne,
            ..FlameConfig::default()
        };
        let m = model(DType::F32, config);
        let p = frames(&m, 3);
        let full = m.forward(&p).unwrap();
        let id = m.identity(&p.shape.narrow(0, 0, 1).unwrap()).unwrap();
        let cached = m
            .forward_with_identity(&id, &p.expression, &p.pose, &p.eye)
            .unwrap();
        assert_same(&full, &cached, 1e-6, &format!("{ns} shape, {ne} exp"));
        assert_eq!(full.vertices.dims(), [3, m.n_vertices, 3]);
    }
}

#[test]
fn cached_path_gradients_match_the_full_path() {
    let config = FlameConfig {
        n_shape: 20,
        n_exp: 10,
        ..FlameConfig::default()
    };
    let m = model(DType::F64, config);
    let p = frames(&m, 2);
    let w = codes(&m, 2 * m.n_vertices, 3, 1.0, 11).reshape((2, m.n_vertices, 3));
    let w = w.unwrap();
    let wj = codes(&m, 2 * 5, 3, 1.0, 12).reshape((2, 5, 3)).unwrap();
    let loss = |o: &FlameOutput| -> Tensor {
        let a = (&o.vertices * &w).unwrap().sum_all().unwrap();
        let b = (&o.joints * &wj).unwrap().sum_all().unwrap();
        (a + b).unwrap()
    };
    let vars = |p: &FlameParams| {
        [&p.shape, &p.expression, &p.pose, &p.eye].map(|t| Var::from_tensor(t).unwrap())
    };

    // Full path, shapes given per frame (the same code twice).
    let vf = vars(&p);
    let pf = FlameParams {
        shape: vf[0].as_tensor().clone(),
        expression: vf[1].as_tensor().clone(),
        pose: vf[2].as_tensor().clone(),
        eye: vf[3].as_tensor().clone(),
    };
    let gf = loss(&m.forward(&pf).unwrap()).backward().unwrap();

    // Cached path, one shape code for both frames.
    let vc = vars(&p);
    let shape1 = Var::from_tensor(&p.shape.narrow(0, 0, 1).unwrap()).unwrap();
    let id = m.identity(shape1.as_tensor()).unwrap();
    let out = m
        .forward_with_identity(&id, vc[1].as_tensor(), vc[2].as_tensor(), vc[3].as_tensor())
        .unwrap();
    let gc = loss(&out).backward().unwrap();

    for (i, name) in ["expression", "pose", "eye"].iter().enumerate() {
        let a = gf.get(vf[i + 1].as_tensor()).unwrap();
        let b = gc
            .get(vc[i + 1].as_tensor())
            .unwrap_or_else(|| panic!("cached path: no gradient for {name}"));
        let d = max_abs_diff(a, b);
        assert!(d <= 1e-10, "d/d{name} differs by {d:e}");
        let norm = max_abs_diff(a, &a.zeros_like().unwrap());
        assert!(norm > 1e-3, "d/d{name} is degenerate ({norm:e})");
    }
    // The shared shape code collects the sum of the per-frame shape gradients.
    let per_frame = gf.get(vf[0].as_tensor()).unwrap().sum_keepdim(0).unwrap();
    let shared = gc
        .get(shape1.as_tensor())
        .expect("cached path: no gradient for the shape code");
    let d = max_abs_diff(&per_frame, shared);
    assert!(d <= 1e-10, "d/dshape differs by {d:e}");
}

#[test]
fn mismatched_identities_are_rejected() {
    let m = model(DType::F32, FlameConfig::default());
    let p = frames(&m, 3);
    let input_err = |r: Result<FlameOutput, FlameError>| match r {
        Err(FlameError::Input { name, .. }) => name,
        other => panic!("expected an input error, got {other:?}"),
    };

    // Two shapes for three frames: neither broadcast nor per frame.
    let id2 = m.identity(&codes(&m, 2, 300, 1.0, 5)).unwrap();
    let r = m.forward_with_identity(&id2, &p.expression, &p.pose, &p.eye);
    assert_eq!(input_err(r), "identity");

    // An identity from a model with another dtype.
    let m64 = model(DType::F64, FlameConfig::default());
    let id64 = m64.identity(&codes(&m64, 1, 300, 1.0, 5)).unwrap();
    let r = m.forward_with_identity(&id64, &p.expression, &p.pose, &p.eye);
    assert_eq!(input_err(r), "identity");

    // Frame codes are checked as in the full forward.
    let id = m.identity(&p.shape.narrow(0, 0, 1).unwrap()).unwrap();
    let r = m.forward_with_identity(&id, &p.expression, &p.pose.narrow(0, 0, 2).unwrap(), &p.eye);
    assert_eq!(input_err(r), "pose");
    let r = m.forward_with_identity(&id, &p.pose, &p.pose, &p.eye);
    assert_eq!(input_err(r), "expression");
    assert!(matches!(
        m.identity(&p.expression),
        Err(FlameError::Input { name: "shape", .. })
    ));
}
