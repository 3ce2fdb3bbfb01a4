// acc = scale * g (first sample of a step) or acc + scale * g (the others) over n values: a
// batch's mean gradient summed on the device, read back once per step.

struct P {
    n: u32,
    _p0: u32,
    _p1: u32,
    _p2: u32,
}

struct S {
    scale: f32,
    // 1: overwrite, 0: add
    first: u32,
    _p0: u32,
    _p1: u32,
}

@group(0) @binding(0) var<uniform> p: P;
@group(0) @binding(1) var<uniform> s: S;
@group(0) @binding(2) var<storage, read> g: array<f32>;
@group(0) @binding(3) var<storage, read_write> acc: array<f32>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = lin(gid, 256u);
    if (i >= p.n) {
        return;
    }
    var v = s.scale * g[i];
    if (s.first == 0u) {
        v = v + acc[i];
    }
    acc[i] = v;
}
