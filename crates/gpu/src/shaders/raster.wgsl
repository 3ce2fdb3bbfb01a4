// Splatting step 8 (spec section 7): one workgroup per 16x16 tile, one thread per pixel,
// front to back through the tile's Gaussians in batches loaded into workgroup memory.
// Per pixel the decisions and the accumulation order are the CPU path's
// (gagavatar_splat::raster::forward): skip when power > 0 or alpha < 1/255, stop before a
// Gaussian that would take the transmittance below 1e-4, C += feature * (alpha T).
// With STATE (training) each pixel also keeps what the backward (raster_backward.wgsl) needs:
// its final transmittance and one past the list position of the last Gaussian it added.

struct P {
    width: u32,
    height: u32,
    grid_x: u32,
    _p0: u32,
}

const C: u32 = {{CHANNELS}}u;
const BATCH: u32 = 256u;
const STATE: bool = {{STATE}};

@group(0) @binding(0) var<uniform> p: P;
@group(0) @binding(1) var<storage, read> ranges: array<vec2<u32>>;
@group(0) @binding(2) var<storage, read> pair_vals: array<u32>;
@group(0) @binding(3) var<storage, read> splats: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read> features: array<f32>;
@group(0) @binding(5) var<storage, read> background: array<f32>;
// out: [C, H, W]
@group(0) @binding(6) var<storage, read_write> image: array<f32>;
// [H, W] each (a small stand-in without STATE)
@group(0) @binding(7) var<storage, read_write> state_t: array<f32>;
@group(0) @binding(8) var<storage, read_write> state_n: array<u32>;

var<workgroup> s_a: array<vec4<f32>, BATCH>;
var<workgroup> s_b: array<vec2<f32>, BATCH>;
var<workgroup> s_id: array<u32, BATCH>;
var<workgroup> n_done: atomic<u32>;

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
    let range = ranges[wid.y * p.grid_x + wid.x];
    if (t == 0u) {
        atomicStore(&n_done, 0u);
    }
    var acc: array<f32, C>;
    for (var c = 0u; c < C; c = c + 1u) {
        acc[c] = 0.0;
    }
    var tr = 1.0;
    var last = 0u;
    var done = !inside;
    workgroupBarrier();
    if (done) {
        atomicAdd(&n_done, 1u);
    }
    for (var start = range.x; start < range.y; start = start + BATCH) {
        // Stop once every pixel of the tile has stopped.
        if (workgroupUniformLoad(&n_done) == 256u) {
            break;
        }
        let k = start + t;
        if (k < range.y) {
            let g = pair_vals[k];
            s_id[t] = g;
            s_a[t] = splats[2u * g];
            s_b[t] = splats[2u * g + 1u].xy;
        }
        workgroupBarrier();
        if (!done) {
            let count = min(BATCH, range.y - start);
            for (var j = 0u; j < count; j = j + 1u) {
                let a = s_a[j];
                let dx = a.x - px;
                let dy = a.y - py;
                let inner = fma(a.z, dx, a.w * dy);
                let cdy = (s_b[j].x * dy) * dy;
                let power = fma(dx, inner, cdy);
                let alpha = min(s_b[j].y * exp_splat(power), 0.99);
                if (!(power <= 0.0) || !(alpha >= 1.0 / 255.0)) {
                    continue;
                }
                let test = tr * (1.0 - alpha);
                if (test < 1e-4) {
                    done = true;
                    atomicAdd(&n_done, 1u);
                    break;
                }
                let w = alpha * tr;
                let f = s_id[j] * C;
                for (var c = 0u; c < C; c = c + 1u) {
                    acc[c] = acc[c] + w * features[f + c];
                }
                tr = test;
                last = start + j + 1u;
            }
        }
        workgroupBarrier();
    }
    if (inside) {
        let plane = p.width * p.height;
        let o = y * p.width + x;
        for (var c = 0u; c < C; c = c + 1u) {
            image[c * plane + o] = acc[c] + tr * background[c];
        }
        if (STATE) {
            state_t[o] = tr;
            state_n[o] = last;
        }
    }
}
