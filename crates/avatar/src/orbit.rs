//! Views around the head: the source camera with the world (the head) turned about the origin.

use gagavatar_splat::Camera;

use crate::drive::Camera as Transform;

/// The source camera with the world (head) rotated about the origin, where tracked data puts
/// the head: by `yaw` about Y, then `pitch` about X, as in `Camera::look_at_origin_matrix`.
pub fn orbit_transform(base: &Transform, yaw: f64, pitch: f64) -> Transform {
    // A transform [R | T] maps p to R^T p + T; rotating the world by O first gives R^T O p,
    // i.e. R' = O^T R. The look-at matrix of distance 0 stores exactly O^T in its 3x3 block.
    let ot = Camera::look_at_origin_matrix(0.0, yaw, pitch);
    let mut out = *base;
    for i in 0..3 {
        for j in 0..3 {
            out[i][j] = (0..3).map(|k| ot[i][k] * base[k][j]).sum();
        }
    }
    out
}

/// The release's orbit as `gagavatar orbit` renders it: `frames` cameras from `base` on a
/// figure-eight, yaw = Y sin(2 pi t), pitch = P sin(4 pi t) (degrees), t in [0, 1).
pub fn orbit_cameras(
    base: &Transform,
    yaw_deg: f64,
    pitch_deg: f64,
    frames: usize,
) -> Vec<Transform> {
    let tau = std::f64::consts::TAU;
    (0..frames)
        .map(|i| {
            let t = i as f64 / frames as f64;
            orbit_transform(
                base,
                yaw_deg.to_radians() * (tau * t).sin(),
                pitch_deg.to_radians() * (2.0 * tau * t).sin(),
            )
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn orbit_of_zero_angles_is_the_base_and_keeps_the_distance() {
        let base = Camera::look_at_origin_matrix(9.0, 0.2, -0.1);
        let same = orbit_transform(&base, 0.0, 0.0);
        assert_eq!(same, base);
        // The camera centre stays at the same distance from the head for any orbit angle.
        let dist = |tm: &[[f64; 4]; 3]| {
            let c = Camera::from_transform_matrix(tm, 12.0, 64, 64)
                .unwrap()
                .center();
            (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt()
        };
        let moved = orbit_transform(&base, 0.5, 0.3);
        assert!((dist(&moved) - dist(&base)).abs() < 1e-9);
        assert!(moved != base);
    }

    #[test]
    fn orbit_matches_look_at_from_the_front() {
        // From the look-at camera with R = I (it faces the back of the head; the release's
        // frontal camera is yaw = pi), orbiting by (yaw, pitch) about the head is the look-at
        // camera with the same angles.
        let front = Camera::look_at_origin_matrix(9.0, 0.0, 0.0);
        for (yaw, pitch) in [(0.4, 0.0), (0.0, 0.3), (-0.5, 0.2)] {
            let want = Camera::look_at_origin_matrix(9.0, yaw, pitch);
            let got = orbit_transform(&front, yaw, pitch);
            for i in 0..3 {
                for j in 0..4 {
                    assert!(
                        (got[i][j] - want[i][j]).abs() < 1e-12,
                        "({yaw}, {pitch}) [{i}][{j}] expected {} got {}",
                        want[i][j],
                        got[i][j]
                    );
                }
            }
        }
    }
}
