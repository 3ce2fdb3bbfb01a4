// Multi-head self-attention softmax(q k^T / sqrt(D)) v of a channel-major qkv activation
// [3 C, N] (rows h D + d of q, then of k, then of v) into [C, N], without materialising the
// N x N weights: one thread per query, keys in tiles of KT staged in workgroup memory, and the
// softmax kept as a running maximum and sum (the sum and the output rescaled when a key raises
// the maximum). The query and the output are D scalar variables each (generated, like the
// convolutions' accumulators): an array indexed in a loop may live in memory, where lavapipe
// gave wrong results once many workgroups ran at D = 64.

const D: u32 = {{D}}u;
const KT: u32 = {{KT}}u;
const WG: u32 = 64u;

struct P {
    n: u32,
    c: u32,
    in_off: u32,
    out_off: u32,
    scale: f32,
    _p0: u32,
    _p1: u32,
    _p2: u32,
}

@group(0) @binding(0) var<uniform> p: P;
@group(0) @binding(1) var<storage, read> x: array<f32>;
@group(0) @binding(2) var<storage, read_write> y: array<f32>;

var<workgroup> Ks: array<f32, KT * D>;
var<workgroup> Vs: array<f32, KT * D>;

fn q_at(row: u32, qi: u32, valid: bool) -> f32 {
    if (valid) {
        return x[row + qi] * p.scale;
    }
    return 0.0;
}

@compute @workgroup_size(64)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) t: u32) {
    let h = wid.y;
    let qi = wid.x * WG + t;
    let valid = qi < p.n;
    let q_row = p.in_off + h * D * p.n;
    let k_row = q_row + p.c * p.n;
    let v_row = k_row + p.c * p.n;
{{DECL}}
    var m = -3.0e38;
    var l = 0.0;
    for (var k0 = 0u; k0 < p.n; k0 = k0 + KT) {
        workgroupBarrier();
        for (var e = t; e < KT * D; e = e + WG) {
            let j = e % KT;
            let d = e / KT;
            let key = k0 + j;
            var kv = 0.0;
            var vv = 0.0;
            if (key < p.n) {
                kv = x[k_row + d * p.n + key];
                vv = x[v_row + d * p.n + key];
            }
            Ks[j * D + d] = kv;
            Vs[j * D + d] = vv;
        }
        workgroupBarrier();
        let kn = min(KT, p.n - k0);
        for (var j = 0u; j < kn; j = j + 1u) {
            let kb = j * D;
{{DOT}}
            if (s > m) {
                let corr = exp(m - s);
                l = l * corr;
{{RESCALE}}
                m = s;
            }
            let pj = exp(s - m);
            l = l + pj;
{{ACCUM}}
        }
    }
    if (valid) {
        let inv = 1.0 / l;
        let o_row = p.out_off + h * D * p.n + qi;
{{STORE}}
    }
}
