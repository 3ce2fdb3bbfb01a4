//! Filling and smoothing of per-frame fits.

use gagavatar_synthdata::sample::Rng;
use gagavatar_track::camera::{
    exp_so3, matmul, rotation_angle_between, rotation_from_6d, rotation_to_6d, CameraPose,
};
use gagavatar_track::fit::FrameState;
use gagavatar_track::smooth::{
    interpolate_states, release_ema, smooth_states, OfflineSmoothing, Smoothing,
};

fn state(yaw: f64, tz: f64, e: f64) -> FrameState {
    let mut cam = CameraPose::frontal(tz);
    cam.rotation = matmul(&cam.rotation, &exp_so3(&[0.0, yaw, 0.0]));
    FrameState {
        expression: vec![e, -e],
        jaw: [e, 0.0, 0.0],
        eyes: [e; 6],
        camera: cam,
    }
}

#[test]
fn gaps_are_filled_along_the_geodesic_and_held_at_the_ends() {
    let s = vec![
        None,
        Some(state(0.2, 9.0, 0.0)),
        None,
        None,
        Some(state(0.8, 10.5, 0.3)),
        None,
    ];
    let f = interpolate_states(&s).unwrap();
    assert_eq!(f.len(), 6);
    assert_eq!(f[0], f[1]);
    assert_eq!(f[5], f[4]);
    let want = state(0.4, 9.5, 0.1);
    assert!(rotation_angle_between(&f[2].camera.rotation, &want.camera.rotation) < 1e-12);
    assert!((f[2].camera.translation[2] - 9.5).abs() < 1e-12);
    assert!((f[2].expression[0] - 0.1).abs() < 1e-12 && (f[2].eyes[4] - 0.1).abs() < 1e-12);
    assert!(interpolate_states(&[None, None]).is_err());
}

#[test]
fn release_ema_is_the_causal_recursion_on_6d_rotations() {
    let s: Vec<FrameState> = [0.0, 0.5, 0.5, -0.2]
        .iter()
        .enumerate()
        .map(|(i, &y)| state(y, 9.0 + i as f64, 0.1 * i as f64))
        .collect();
    let out = release_ema(&s);
    // By hand: s0 = x0, s_i = a x_i + (1 - a) s_{i-1} on the 6D rows, translation and eyes.
    let mut r6 = rotation_to_6d(&s[0].camera.rotation);
    let mut tz = s[0].camera.translation[2];
    let mut eye = s[0].eyes[0];
    for i in 0..s.len() {
        if i > 0 {
            let x = rotation_to_6d(&s[i].camera.rotation);
            r6 = std::array::from_fn(|k| 0.6 * x[k] + 0.4 * r6[k]);
            tz = 0.6 * s[i].camera.translation[2] + 0.4 * tz;
            eye = 0.7 * s[i].eyes[0] + 0.3 * eye;
        }
        let r = rotation_from_6d(&r6).unwrap();
        assert!(
            rotation_angle_between(&r, &out[i].camera.rotation) < 1e-12,
            "frame {i}"
        );
        assert!(
            (out[i].camera.translation[2] - tz).abs() < 1e-12,
            "frame {i}"
        );
        assert!((out[i].eyes[0] - eye).abs() < 1e-12, "frame {i}");
        // Expression and jaw are never smoothed by the release.
        assert_eq!(out[i].expression, s[i].expression);
        assert_eq!(out[i].jaw, s[i].jaw);
    }
}

#[test]
fn offline_smoothing_removes_noise_without_lag() {
    let n = 60;
    let mut rng = Rng::stream(8, &[0]);
    let truth: Vec<FrameState> = (0..n)
        .map(|i| {
            state(
                0.4 * (i as f64 / 8.0).sin(),
                9.0,
                0.3 * (i as f64 / 6.0).sin(),
            )
        })
        .collect();
    let noisy: Vec<FrameState> = truth
        .iter()
        .map(|s| {
            let mut s = s.clone();
            let d = [
                0.02 * rng.normal(),
                0.02 * rng.normal(),
                0.02 * rng.normal(),
            ];
            s.camera.rotation = matmul(&s.camera.rotation, &exp_so3(&d));
            s.camera.translation[2] += 0.05 * rng.normal();
            s.expression[0] += 0.05 * rng.normal();
            s
        })
        .collect();
    let observed = vec![true; n];
    let err = |a: &[FrameState]| -> (f64, f64, f64) {
        let r = (0..n)
            .map(|i| rotation_angle_between(&a[i].camera.rotation, &truth[i].camera.rotation))
            .sum::<f64>()
            / n as f64;
        let t = (0..n)
            .map(|i| (a[i].camera.translation[2] - truth[i].camera.translation[2]).abs())
            .sum::<f64>()
            / n as f64;
        let e = (0..n)
            .map(|i| (a[i].expression[0] - truth[i].expression[0]).abs())
            .sum::<f64>()
            / n as f64;
        (r, t, e)
    };
    let raw = err(&noisy);
    let off = err(&smooth_states(&noisy, &observed, &Smoothing::default()).unwrap());
    let ema = err(&smooth_states(&noisy, &observed, &Smoothing::ReleaseEma).unwrap());
    println!(
        "mean errors (rotation rad, tz, expression): raw {raw:?}, offline {off:?}, EMA {ema:?}"
    );
    assert!(off.0 < 0.7 * raw.0 && off.1 < 0.7 * raw.1 && off.2 < raw.2);
    // Zero-lag: the two-sided smoother beats the causal EMA on a moving head.
    assert!(off.0 < ema.0, "offline {} vs EMA {}", off.0, ema.0);
    // Strength 0 leaves everything as it was.
    let none = Smoothing::Offline(OfflineSmoothing {
        camera: 0.0,
        eyes: 0.0,
        expression: 0.0,
    });
    assert_eq!(smooth_states(&noisy, &observed, &none).unwrap(), noisy);
}
