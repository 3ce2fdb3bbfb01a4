// One layer of the perceptual distance (gagavatar_train::kernels::layer_distance) between a
// prediction's features `a` and the target's `b` (`[c, n]`), per position: the channel norms
// `|f| = sqrt(sum f^2 + 1e-20) + 1e-10`, `d = sum_c |a_c / |a| - b_c / |b||` into `d_out`, and
// `scale * dd/da` into `grad` (ACC: added to what it holds, the gradient arriving from the
// layers above), with sign(0) = 0. One thread per position.

const ACC: bool = {{ACC}};

struct P {
    c: u32,
    n: u32,
    a_off: u32,
    b_off: u32,
    scale: f32,
    _p0: u32,
    _p1: u32,
    _p2: u32,
}

@group(0) @binding(0) var<uniform> p: P;
@group(0) @binding(1) var<storage, read> a: array<f32>;
@group(0) @binding(2) var<storage, read> b: array<f32>;
@group(0) @binding(3) var<storage, read_write> d_out: array<f32>;
@group(0) @binding(4) var<storage, read_write> grad: array<f32>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let j = lin(gid, 256u);
    if (j >= p.n) {
        return;
    }
    var sa = 0.0;
    var sb = 0.0;
    for (var c = 0u; c < p.c; c++) {
        let x = a[p.a_off + c * p.n + j];
        let y = b[p.b_off + c * p.n + j];
        sa = sa + x * x;
        sb = sb + y * y;
    }
    let ra = sqrt(sa + 1e-20);
    let na = ra + 1e-10;
    let nb = sqrt(sb + 1e-20) + 1e-10;
    // d = sum |u - v|; dd/da_j = s_j / na - a_j (s . a) / (na^2 ra), s = sign(u - v).
    var d = 0.0;
    var sdota = 0.0;
    for (var c = 0u; c < p.c; c++) {
        let x = a[p.a_off + c * p.n + j];
        let e = x / na - b[p.b_off + c * p.n + j] / nb;
        d = d + abs(e);
        sdota = sdota + sign(e) * x;
    }
    d_out[j] = d;
    let k = sdota / (na * na * ra);
    for (var c = 0u; c < p.c; c++) {
        let x = a[p.a_off + c * p.n + j];
        let e = x / na - b[p.b_off + c * p.n + j] / nb;
        var g = p.scale * (sign(e) / na - x * k);
        if (ACC) {
            g = g + grad[c * p.n + j];
        }
        grad[c * p.n + j] = g;
    }
}
