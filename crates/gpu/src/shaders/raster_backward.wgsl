// Splatting backward, step 2: the compositing's gradient (gagavatar_splat::raster::backward's
// per-pixel arithmetic). One workgroup per 16x16 tile, one thread per pixel, through the tile's
// Gaussians back to front. Per pixel the transmittance in front of each Gaussian is recovered
// by division from the final one (kept by raster.wgsl with STATE), and what lies behind enters
// through one running sum, `s = sum over the Gaussians behind of w_i (dL/dpixel . f_i)`:
// `dL/dalpha = T (dL/dpixel . f) - (s + T_final (dL/dpixel . background)) / (1 - alpha)`.
// Each Gaussian's S sums over the tile's pixels (its C feature gradients, then mean x, mean y,
// conic A, B, C and opacity) go to its pair's slot (splat_pair_info.wgsl); tiles where no
// pixel took it write zeros. The background's sums per tile go after the pairs.

struct P {
    width: u32,
    height: u32,
    grid_x: u32,
    bg_off: u32,
}

const C: u32 = {{CHANNELS}}u;
const S: u32 = C + 6u;
const BATCH: u32 = 256u;

@group(0) @binding(0) var<uniform> p: P;
@group(0) @binding(1) var<storage, read> ranges: array<vec2<u32>>;
@group(0) @binding(2) var<storage, read> pair_vals: array<u32>;
@group(0) @binding(3) var<storage, read> splats: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read> features: array<f32>;
@group(0) @binding(5) var<storage, read> background: array<f32>;
@group(0) @binding(6) var<storage, read> state_t: array<f32>;
@group(0) @binding(7) var<storage, read> state_n: array<u32>;
// dL/dimage [C, H, W]
@group(0) @binding(8) var<storage, read> grad: array<f32>;
@group(0) @binding(9) var<storage, read> info: array<vec4<u32>>;
// [pair slot, S], then [tile, C] at bg_off
@group(0) @binding(10) var<storage, read_write> pairs: array<f32>;

var<workgroup> s_a: array<vec4<f32>, BATCH>;
var<workgroup> s_b: array<vec2<f32>, BATCH>;
var<workgroup> s_id: array<u32, BATCH>;
var<workgroup> red: array<f32, 2048>;
var<workgroup> red2: array<f32, 256>;
// The list position of the last Gaussian some pixel took (positions only decrease).
var<workgroup> taken: atomic<u32>;
var<workgroup> k_end: atomic<u32>;

// Eight quantities summed over the tile's 256 pixels in a fixed order: thread q < 8 gets
// quantity q's sum, the others 0.
fn reduce8(t: u32, v0: f32, v1: f32, v2: f32, v3: f32, v4: f32, v5: f32, v6: f32, v7: f32) -> f32 {
    red[t] = v0;
    red[256u + t] = v1;
    red[512u + t] = v2;
    red[768u + t] = v3;
    red[1024u + t] = v4;
    red[1280u + t] = v5;
    red[1536u + t] = v6;
    red[1792u + t] = v7;
    workgroupBarrier();
    let q = t / 32u;
    let lane = t % 32u;
    var s = 0.0;
    for (var k = 0u; k < 8u; k = k + 1u) {
        s = s + red[q * 256u + lane + 32u * k];
    }
    red2[q * 32u + lane] = s;
    workgroupBarrier();
    var total = 0.0;
    if (t < 8u) {
        for (var k = 0u; k < 32u; k = k + 1u) {
            total = total + red2[t * 32u + k];
        }
    }
    return total;
}

// This pixel's share of quantity v of the Gaussian it took with weight w and screen-space
// gradients g (zero where it took none).
fn share(v: u32, took: bool, w: f32, o: u32, plane: u32, g0: vec3<f32>, g1: vec3<f32>) -> f32 {
    if (!took || v >= S) {
        return 0.0;
    }
    if (v < C) {
        return w * grad[v * plane + o];
    }
    switch v - C {
        case 0u: { return g0.x; }
        case 1u: { return g0.y; }
        case 2u: { return g0.z; }
        case 3u: { return g1.x; }
        case 4u: { return g1.y; }
        default: { return g1.z; }
    }
}

// This pixel's share of channel c of the background's gradient.
fn bg_share(c: u32, inside: bool, o: u32, plane: u32, tfin: f32) -> f32 {
    if (!inside || c >= C) {
        return 0.0;
    }
    return grad[c * plane + o] * tfin;
}

@compute @workgroup_size(16, 16)
fn main(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(local_invocation_id) lid: vec3<u32>,
    @builtin(local_invocation_index) t: u32,
) {
    let x = wid.x * 16u + lid.x;
    let y = wid.y * 16u + lid.y;
    let inside = x < p.width && y < p.height;
    let px = f32(x);
    let py = f32(y);
    let plane = p.width * p.height;
    let tile = wid.y * p.grid_x + wid.x;
    let range = ranges[tile];
    let o = y * p.width + x;
    var tfin = 0.0;
    var ncon = 0u;
    var bgdot = 0.0;
    if (inside) {
        tfin = state_t[o];
        ncon = state_n[o];
        for (var c = 0u; c < C; c = c + 1u) {
            bgdot = fma(grad[c * plane + o], background[c], bgdot);
        }
    }
    if (t == 0u) {
        atomicStore(&taken, 0xffffffffu);
        atomicStore(&k_end, 0u);
    }
    workgroupBarrier();
    atomicMax(&k_end, ncon);
    let kend = workgroupUniformLoad(&k_end);

    // The background's gradient: sum over pixels of dL/dpixel T_final.
    for (var b = 0u; b < C; b = b + 8u) {
        let tot = reduce8(
            t,
            bg_share(b, inside, o, plane, tfin),
            bg_share(b + 1u, inside, o, plane, tfin),
            bg_share(b + 2u, inside, o, plane, tfin),
            bg_share(b + 3u, inside, o, plane, tfin),
            bg_share(b + 4u, inside, o, plane, tfin),
            bg_share(b + 5u, inside, o, plane, tfin),
            bg_share(b + 6u, inside, o, plane, tfin),
            bg_share(b + 7u, inside, o, plane, tfin),
        );
        if (t < 8u && b + t < C) {
            pairs[p.bg_off + tile * C + b + t] = tot;
        }
    }

    var tr = tfin;
    var behind_sum = 0.0;
    var end = range.y;
    loop {
        if (end <= range.x) {
            break;
        }
        var lo = range.x;
        if (end - range.x > BATCH) {
            lo = end - BATCH;
        }
        let count = end - lo;
        workgroupBarrier();
        if (t < count) {
            let g = pair_vals[lo + t];
            s_id[t] = g;
            s_a[t] = splats[2u * g];
            s_b[t] = splats[2u * g + 1u].xy;
        }
        workgroupBarrier();
        for (var jj = count; jj > 0u; jj = jj - 1u) {
            let j = jj - 1u;
            let k = lo + j;
            let g = s_id[j];
            var took = false;
            var w = 0.0;
            var g0 = vec3<f32>(0.0);
            var g1 = vec3<f32>(0.0);
            if (k < kend && inside && k < ncon) {
                let a = s_a[j];
                let sb = s_b[j];
                let dx = a.x - px;
                let dy = a.y - py;
                let inner = fma(a.z, dx, a.w * dy);
                let cdy = (sb.x * dy) * dy;
                let power = fma(dx, inner, cdy);
                let ge = exp_splat(power);
                let oa = sb.y * ge;
                let alpha = min(oa, 0.99);
                if (power <= 0.0 && alpha >= 1.0 / 255.0) {
                    took = true;
                    let one_m = 1.0 - alpha;
                    let tt = tr / one_m;
                    tr = tt;
                    w = alpha * tt;
                    var dot = 0.0;
                    for (var c = 0u; c < C; c = c + 1u) {
                        dot = fma(grad[c * plane + o], features[g * C + c], dot);
                    }
                    let behind = (behind_sum + tfin * bgdot) / one_m;
                    let dalpha = dot * tt - behind;
                    behind_sum = behind_sum + w * dot;
                    // alpha = min(0.99, o G): no gradient where the clamp holds.
                    var dal = 0.0;
                    if (oa < 0.99) {
                        dal = dalpha;
                    }
                    let dpow = ge * sb.y * dal;
                    // power = -0.5 (A dx^2 + C dy^2) - B dx dy, stored as (-A/2, -B, -C/2).
                    let ca = -2.0 * a.z;
                    let cb = -a.w;
                    let cc = -2.0 * sb.x;
                    g0 = vec3<f32>(
                        -dpow * (ca * dx + cb * dy),
                        -dpow * (cc * dy + cb * dx),
                        -0.5 * dpow * dx * dx,
                    );
                    g1 = vec3<f32>(-dpow * dx * dy, -0.5 * dpow * dy * dy, ge * dal);
                    atomicMin(&taken, k);
                }
            }
            let inf = info[g];
            let x0 = inf.x & 0xffffu;
            let x1 = inf.x >> 16u;
            let y0 = inf.y & 0xffffu;
            let slot = inf.z + (wid.y - y0) * (x1 - x0) + (wid.x - x0);
            if (workgroupUniformLoad(&taken) == k) {
                for (var b = 0u; b < S; b = b + 8u) {
                    let tot = reduce8(
                        t,
                        share(b, took, w, o, plane, g0, g1),
                        share(b + 1u, took, w, o, plane, g0, g1),
                        share(b + 2u, took, w, o, plane, g0, g1),
                        share(b + 3u, took, w, o, plane, g0, g1),
                        share(b + 4u, took, w, o, plane, g0, g1),
                        share(b + 5u, took, w, o, plane, g0, g1),
                        share(b + 6u, took, w, o, plane, g0, g1),
                        share(b + 7u, took, w, o, plane, g0, g1),
                    );
                    if (t < 8u && b + t < S) {
                        pairs[slot * S + b + t] = tot;
                    }
                }
            } else if (t < S) {
                pairs[slot * S + t] = 0.0;
            }
        }
        end = lo;
    }
}
