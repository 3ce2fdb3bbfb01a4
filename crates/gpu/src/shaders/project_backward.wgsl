// Splatting backward, step 4: per Gaussian, from its screen-space gradients (mean x, mean y,
// conic A, B, C, opacity) to those of its mean, opacity, scale and unnormalised quaternion
// (gagavatar_splat::project::project_backward_one, operation for operation): the forward's
// geometry again (project.wgsl), then the conic's inverse, the EWA product P Sigma P^T with
// the clamped Jacobian, the view transform and Sigma = (Rq S)(Rq S)^T backwards. Culled
// Gaussians (an empty tile rectangle) get zeros.

struct P {
    r00: f32, r01: f32, r02: f32, t0: f32,
    r10: f32, r11: f32, r12: f32, t1: f32,
    r20: f32, r21: f32, r22: f32, t2: f32,
    focal: f32, fx: f32, fy: f32, lim: f32,
    w: f32, h: f32, grid_x: u32, grid_y: u32,
    n: u32, n_vertices: u32, _p0: u32, _p1: u32,
}

const C: u32 = {{CHANNELS}}u;
// Per Gaussian in `grads`: C feature gradients, then the six screen-space ones.
const S: u32 = C + 6u;

@group(0) @binding(0) var<uniform> p: P;
@group(0) @binding(1) var<storage, read> head: array<f32>;
@group(0) @binding(2) var<storage, read> rest: array<f32>;
@group(0) @binding(3) var<storage, read> scales: array<f32>;
@group(0) @binding(4) var<storage, read> rotations: array<f32>;
@group(0) @binding(5) var<storage, read> rects: array<vec2<u32>>;
@group(0) @binding(6) var<storage, read> grads: array<f32>;
// [N, 11]: mean (3), opacity, scale (3), quaternion (r, x, y, z)
@group(0) @binding(7) var<storage, read_write> out: array<f32>;

fn put(i: u32, k: u32, v: f32) {
    out[i * 11u + k] = v;
}

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = lin(gid, 256u);
    if (i >= p.n) {
        return;
    }
    for (var k = 0u; k < 11u; k = k + 1u) {
        put(i, k, 0.0);
    }
    let rc = rects[i];
    if (rc.x == 0u && rc.y == 0u) {
        return;
    }
    let d_mx = grads[i * S + C];
    let d_my = grads[i * S + C + 1u];
    let d_ca = grads[i * S + C + 2u];
    let d_cb = grads[i * S + C + 3u];
    let d_cc = grads[i * S + C + 4u];
    put(i, 3u, grads[i * S + C + 5u]);

    // The forward's geometry (project.wgsl).
    var m: vec3<f32>;
    if (i < p.n_vertices) {
        m = vec3<f32>(head[3u * i], head[3u * i + 1u], head[3u * i + 2u]);
    } else {
        let j = i - p.n_vertices;
        m = vec3<f32>(rest[3u * j], rest[3u * j + 1u], rest[3u * j + 2u]);
    }
    let tx = p.r00 * m.x + p.r01 * m.y + p.r02 * m.z + p.t0;
    let ty = p.r10 * m.x + p.r11 * m.y + p.r12 * m.z + p.t1;
    let tz = p.r20 * m.x + p.r21 * m.y + p.r22 * m.z + p.t2;
    let qr = rotations[4u * i];
    let qx = rotations[4u * i + 1u];
    let qy = rotations[4u * i + 2u];
    let qz = rotations[4u * i + 3u];
    let a00 = 1.0 - 2.0 * (qy * qy + qz * qz);
    let a01 = 2.0 * (qx * qy - qr * qz);
    let a02 = 2.0 * (qx * qz + qr * qy);
    let a10 = 2.0 * (qx * qy + qr * qz);
    let a11 = 1.0 - 2.0 * (qx * qx + qz * qz);
    let a12 = 2.0 * (qy * qz - qr * qx);
    let a20 = 2.0 * (qx * qz - qr * qy);
    let a21 = 2.0 * (qy * qz + qr * qx);
    let a22 = 1.0 - 2.0 * (qx * qx + qy * qy);
    let rq = mat3x3<f32>(
        vec3<f32>(a00, a10, a20),
        vec3<f32>(a01, a11, a21),
        vec3<f32>(a02, a12, a22),
    );
    let sc = vec3<f32>(scales[3u * i], scales[3u * i + 1u], scales[3u * i + 2u]);
    // M = Rq diag(s) (columns scaled), Sigma = M M^T; mat3x3 is column-major: rq[k][i] is
    // row i, column k.
    let mm = mat3x3<f32>(rq[0] * sc.x, rq[1] * sc.y, rq[2] * sc.z);
    let sigma = mm * transpose(mm);
    var rx = tx / tz;
    var clamp_x = 0.0;
    if (rx < -p.lim) { rx = -p.lim; clamp_x = -1.0; } else if (rx > p.lim) { rx = p.lim; clamp_x = 1.0; }
    var ry = ty / tz;
    var clamp_y = 0.0;
    if (ry < -p.lim) { ry = -p.lim; clamp_y = -1.0; } else if (ry > p.lim) { ry = p.lim; clamp_y = 1.0; }
    let tcx = rx * tz;
    let tcy = ry * tz;
    let tz2 = tz * tz;
    let tz3 = tz2 * tz;
    // W, the view rotation: w[r][k] = W row r, column k.
    let wr0 = vec3<f32>(p.r00, p.r01, p.r02);
    let wr1 = vec3<f32>(p.r10, p.r11, p.r12);
    let wr2 = vec3<f32>(p.r20, p.r21, p.r22);
    // P = J W, rows.
    let j00 = p.fx / tz;
    let j02 = -(p.fx * tcx) / tz2;
    let j11 = p.fy / tz;
    let j12 = -(p.fy * tcy) / tz2;
    let p0 = j00 * wr0 + j02 * wr2;
    let p1 = j11 * wr1 + j12 * wr2;
    // cov2 + dilation, and its inverse Q.
    let ps0 = sigma * p0;
    let ps1 = sigma * p1;
    let a = dot(ps0, p0) + 0.3;
    let b = dot(ps0, p1);
    let c = dot(ps1, p1) + 0.3;
    let det = a * c - b * b;
    let q00 = c / det;
    let q01 = -b / det;
    let q11 = a / det;
    // dL/dcov2 = -Q G_Q Q with G_Q = [[dA, dB/2], [dB/2, dC]].
    let gq00 = d_ca;
    let gq01 = 0.5 * d_cb;
    let gq11 = d_cc;
    let qg00 = q00 * gq00 + q01 * gq01;
    let qg01 = q00 * gq01 + q01 * gq11;
    let qg10 = q01 * gq00 + q11 * gq01;
    let qg11 = q01 * gq01 + q11 * gq11;
    let gs00 = -(qg00 * q00 + qg01 * q01);
    let gs01 = -(qg00 * q01 + qg01 * q11);
    let gs10 = -(qg10 * q00 + qg11 * q01);
    let gs11 = -(qg10 * q01 + qg11 * q11);
    // G P (rows), dL/dSigma = P^T G P, dL/dP = 2 G P Sigma.
    let gp0 = gs00 * p0 + gs01 * p1;
    let gp1 = gs10 * p0 + gs11 * p1;
    // gsig[i][k] = p0[i] gp0[k] + p1[i] gp1[k]: as columns k.
    let gsig = mat3x3<f32>(
        p0 * gp0.x + p1 * gp1.x,
        p0 * gp0.y + p1 * gp1.y,
        p0 * gp0.z + p1 * gp1.z,
    );
    // dp[i][k] = 2 sum_j gp[i][j] sigma[j][k] (sigma symmetric: sigma * gp).
    let dp0 = 2.0 * (sigma * gp0);
    let dp1 = 2.0 * (sigma * gp1);
    // dL/dJ = dL/dP W^T: dj[i][k] = dot(dp[i], W row k).
    let dj00 = dot(dp0, wr0);
    let dj02 = dot(dp0, wr2);
    let dj11 = dot(dp1, wr1);
    let dj12 = dot(dp1, wr2);
    var dt = vec3<f32>(0.0);
    dt.z = dt.z - dj00 * p.fx / tz2;
    dt.z = dt.z - dj11 * p.fy / tz2;
    if (clamp_x == 0.0) {
        dt.x = dt.x - dj02 * p.fx / tz2;
        dt.z = dt.z + dj02 * 2.0 * p.fx * tx / tz3;
    } else {
        dt.z = dt.z + dj02 * p.fx * (clamp_x * p.lim) / tz2;
    }
    if (clamp_y == 0.0) {
        dt.y = dt.y - dj12 * p.fy / tz2;
        dt.z = dt.z + dj12 * 2.0 * p.fy * ty / tz3;
    } else {
        dt.z = dt.z + dj12 * p.fy * (clamp_y * p.lim) / tz2;
    }
    // The pixel centre: fx x / z + const.
    dt.x = dt.x + d_mx * p.fx / tz;
    dt.y = dt.y + d_my * p.fy / tz;
    dt.z = dt.z - (d_mx * p.fx * tx + d_my * p.fy * ty) / tz2;
    // t = W m + trans: dL/dm = W^T dL/dt.
    let dmean = wr0 * dt.x + wr1 * dt.y + wr2 * dt.z;
    put(i, 0u, dmean.x);
    put(i, 1u, dmean.y);
    put(i, 2u, dmean.z);
    // dL/dM = 2 G_Sigma M (G_Sigma symmetric).
    let dm = 2.0 * (gsig * mm);
    // Scale k: sum_i dm[i][k] rq[i][k] (column k of each); dr = dm diag(s).
    put(i, 4u, dot(dm[0], rq[0]));
    put(i, 5u, dot(dm[1], rq[1]));
    put(i, 6u, dot(dm[2], rq[2]));
    let dr = mat3x3<f32>(dm[0] * sc.x, dm[1] * sc.y, dm[2] * sc.z);
    // dr[row][col] is dr[col][row] here.
    let d00 = dr[0][0]; let d01 = dr[1][0]; let d02 = dr[2][0];
    let d10 = dr[0][1]; let d11 = dr[1][1]; let d12 = dr[2][1];
    let d20 = dr[0][2]; let d21 = dr[1][2]; let d22 = dr[2][2];
    put(i, 7u, 2.0 * (-qz * d01 + qy * d02 + qz * d10 - qx * d12 - qy * d20 + qx * d21));
    put(i, 8u, 2.0 * (qy * d01 + qz * d02 + qy * d10 - qr * d12 + qz * d20 + qr * d21)
        - 4.0 * qx * (d11 + d22));
    put(i, 9u, 2.0 * (qx * d01 + qr * d02 + qx * d10 + qz * d12 - qr * d20 + qz * d21)
        - 4.0 * qy * (d00 + d22));
    put(i, 10u, 2.0 * (-qr * d01 + qx * d02 + qr * d10 + qy * d12 + qx * d20 + qy * d21)
        - 4.0 * qz * (d00 + d11));
}
