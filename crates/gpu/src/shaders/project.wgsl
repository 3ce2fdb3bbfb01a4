// Splatting step 1 (spec section 7): per Gaussian, view transform, covariance from the
// unnormalised quaternion, EWA projection (tan ratios clamped to 1.3 tan(fov/2), 0.3
// dilation), conic, radius and tile rectangle, as gagavatar_splat::project computes them in
// f32, operation for operation. Culled Gaussians get the key 0xffffffff (sorted last).

struct P {
    r00: f32, r01: f32, r02: f32, t0: f32,
    r10: f32, r11: f32, r12: f32, t1: f32,
    r20: f32, r21: f32, r22: f32, t2: f32,
    focal: f32, fx: f32, fy: f32, lim: f32,
    w: f32, h: f32, grid_x: u32, grid_y: u32,
    n: u32, n_vertices: u32, _p0: u32, _p1: u32,
}

@group(0) @binding(0) var<uniform> p: P;
// Positions of the first n_vertices Gaussians (the FLAME vertices), then of the rest.
@group(0) @binding(1) var<storage, read> head: array<f32>;
@group(0) @binding(2) var<storage, read> rest: array<f32>;
@group(0) @binding(3) var<storage, read> opacities: array<f32>;
@group(0) @binding(4) var<storage, read> scales: array<f32>;
@group(0) @binding(5) var<storage, read> rotations: array<f32>;
// out: per Gaussian (mx, my, qa, qb), (qc, opacity, 0, 0): the power is
// dx (qa dx + qb dy) + qc dy^2 with d = mean - pixel.
@group(0) @binding(6) var<storage, read_write> splats: array<vec4<f32>>;
// out: depth bits (or 0xffffffff) and the Gaussian's index, for the depth sort
@group(0) @binding(7) var<storage, read_write> keys: array<u32>;
@group(0) @binding(8) var<storage, read_write> vals: array<u32>;
// out: tile rectangle (x0 | x1 << 16, y0 | y1 << 16)
@group(0) @binding(9) var<storage, read_write> rects: array<vec2<u32>>;

const TILE: f32 = 16.0;

// The CPU's tile_span (in f64 there) exactly: floor((c - r) / 16) and
// floor((c + r + 15) / 16), clamped to [0, grid]. The f32 sums may round onto a multiple of
// 16 from below; an exact integer comparison undoes that (exact while |c|, r < 2^22, beyond
// which the span is clamped away anyway).
fn span(c: f32, r: f32, grid: u32) -> vec2<u32> {
    let g = f32(grid);
    var lo = floor((c - r) / TILE);
    if (lo >= -2.0 && lo <= g + 2.0 && lo * TILE + r > c) {
        lo = lo - 1.0;
    }
    var hi = floor((c + r + (TILE - 1.0)) / TILE);
    if (hi >= -2.0 && hi <= g + 2.0 && hi * TILE - r - (TILE - 1.0) > c) {
        hi = hi - 1.0;
    }
    return vec2<u32>(u32(clamp(lo, 0.0, g)), u32(clamp(hi, 0.0, g)));
}

fn culled(i: u32) {
    splats[2u * i] = vec4<f32>(0.0);
    splats[2u * i + 1u] = vec4<f32>(0.0);
    keys[i] = 0xffffffffu;
    rects[i] = vec2<u32>(0u);
}

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = lin(gid, 256u);
    if (i >= p.n) {
        return;
    }
    vals[i] = i;
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
    if (!(tz > 0.2)) {
        culled(i);
        return;
    }
    let qr = rotations[4u * i];
    let qx = rotations[4u * i + 1u];
    let qy = rotations[4u * i + 2u];
    let qz = rotations[4u * i + 3u];
    // Rq (rows), not normalised.
    let a00 = 1.0 - 2.0 * (qy * qy + qz * qz);
    let a01 = 2.0 * (qx * qy - qr * qz);
    let a02 = 2.0 * (qx * qz + qr * qy);
    let a10 = 2.0 * (qx * qy + qr * qz);
    let a11 = 1.0 - 2.0 * (qx * qx + qz * qz);
    let a12 = 2.0 * (qy * qz - qr * qx);
    let a20 = 2.0 * (qx * qz - qr * qy);
    let a21 = 2.0 * (qy * qz + qr * qx);
    let a22 = 1.0 - 2.0 * (qx * qx + qy * qy);
    let s0 = scales[3u * i];
    let s1 = scales[3u * i + 1u];
    let s2 = scales[3u * i + 2u];
    // M = Rq diag(s); Sigma = M M^T
    let m00 = a00 * s0; let m01 = a01 * s1; let m02 = a02 * s2;
    let m10 = a10 * s0; let m11 = a11 * s1; let m12 = a12 * s2;
    let m20 = a20 * s0; let m21 = a21 * s1; let m22 = a22 * s2;
    let x00 = m00 * m00 + m01 * m01 + m02 * m02;
    let x01 = m00 * m10 + m01 * m11 + m02 * m12;
    let x02 = m00 * m20 + m01 * m21 + m02 * m22;
    let x10 = m10 * m00 + m11 * m01 + m12 * m02;
    let x11 = m10 * m10 + m11 * m11 + m12 * m12;
    let x12 = m10 * m20 + m11 * m21 + m12 * m22;
    let x20 = m20 * m00 + m21 * m01 + m22 * m02;
    let x21 = m20 * m10 + m21 * m11 + m22 * m12;
    let x22 = m20 * m20 + m21 * m21 + m22 * m22;
    // Clamped tan ratios.
    var rx = tx / tz;
    if (rx < -p.lim) { rx = -p.lim; } else if (rx > p.lim) { rx = p.lim; }
    var ry = ty / tz;
    if (ry < -p.lim) { ry = -p.lim; } else if (ry > p.lim) { ry = p.lim; }
    let tcx = rx * tz;
    let tcy = ry * tz;
    let tz2 = tz * tz;
    let j00 = p.fx / tz;
    let j02 = -(p.fx * tcx) / tz2;
    let j11 = p.fy / tz;
    let j12 = -(p.fy * tcy) / tz2;
    // P = J W (W = the view rotation), 2x3.
    let p00 = j00 * p.r00 + 0.0 * p.r10 + j02 * p.r20;
    let p01 = j00 * p.r01 + 0.0 * p.r11 + j02 * p.r21;
    let p02 = j00 * p.r02 + 0.0 * p.r12 + j02 * p.r22;
    let p10 = 0.0 * p.r00 + j11 * p.r10 + j12 * p.r20;
    let p11 = 0.0 * p.r01 + j11 * p.r11 + j12 * p.r21;
    let p12 = 0.0 * p.r02 + j11 * p.r12 + j12 * p.r22;
    // cov2 = P Sigma P^T
    let ps00 = p00 * x00 + p01 * x10 + p02 * x20;
    let ps01 = p00 * x01 + p01 * x11 + p02 * x21;
    let ps02 = p00 * x02 + p01 * x12 + p02 * x22;
    let ps10 = p10 * x00 + p11 * x10 + p12 * x20;
    let ps11 = p10 * x01 + p11 * x11 + p12 * x21;
    let ps12 = p10 * x02 + p11 * x12 + p12 * x22;
    let a = ps00 * p00 + ps01 * p01 + ps02 * p02 + 0.3;
    let b = ps00 * p10 + ps01 * p11 + ps02 * p12;
    let c = ps10 * p10 + ps11 * p11 + ps12 * p12 + 0.3;
    let det = a * c - b * b;
    if (det == 0.0) {
        culled(i);
        return;
    }
    let ca = c / det;
    let cb = -b / det;
    let cc = a / det;
    let mid = 0.5 * (a + c);
    let lambda = mid + sqrt(max(mid * mid - det, 0.1));
    let radius = ceil(3.0 * sqrt(lambda));
    let ndc_x = p.focal * (tx / tz);
    let ndc_y = p.focal * (ty / tz);
    let mx = ((ndc_x + 1.0) * p.w - 1.0) * 0.5;
    let my = ((ndc_y + 1.0) * p.h - 1.0) * 0.5;
    if (!(abs(mx) <= 3.0e38) || !(abs(my) <= 3.0e38) || !(radius <= 3.0e38)) {
        culled(i);
        return;
    }
    let sx = span(mx, radius, p.grid_x);
    let sy = span(my, radius, p.grid_y);
    if ((sx.y - sx.x) * (sy.y - sy.x) == 0u) {
        culled(i);
        return;
    }
    splats[2u * i] = vec4<f32>(mx, my, -0.5 * ca, -cb);
    splats[2u * i + 1u] = vec4<f32>(-0.5 * cc, opacities[i], 0.0, 0.0);
    keys[i] = bitcast<u32>(tz);
    rects[i] = vec2<u32>(sx.x | (sx.y << 16u), sy.x | (sy.y << 16u));
}
