// Sums each row of a [rows, cols] block over a slice of its columns, optionally times a vector
// of `cols` values (WEIGHTED): one workgroup per (row, slice), a tree in workgroup memory. A
// bias's gradient is the row sums of the output gradient [cout, pixels], a noise weight's the
// sum of all rows weighted by the noise map; the slices' partial sums go through
// `conv_wgrad_sum.wgsl`.

const WEIGHTED: bool = {{WEIGHTED}};

struct P {
    rows: u32,
    cols: u32,
    in_off: u32,
    // columns per slice
    slice: u32,
    w_off: u32,
    _p0: u32,
    _p1: u32,
    _p2: u32,
}

@group(0) @binding(0) var<uniform> p: P;
@group(0) @binding(1) var<storage, read> a: array<f32>;
// [slices, rows]
// WEIGHTED: [cols]
@group(0) @binding(2) var<storage, read> weight: array<f32>;
@group(0) @binding(3) var<storage, read_write> part: array<f32>;

var<workgroup> sums: array<f32, 256>;

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) t: u32) {
    let row = wid.x;
    let lo = wid.y * p.slice;
    let hi = min(p.cols, lo + p.slice);
    var v = 0.0;
    for (var c = lo + t; c < hi; c = c + 256u) {
        var e = a[p.in_off + row * p.cols + c];
        if (WEIGHTED) {
            e = e * weight[p.w_off + c];
        }
        v = v + e;
    }
    sums[t] = v;
    workgroupBarrier();
    for (var s = 128u; s > 0u; s = s >> 1u) {
        if (t < s) {
            sums[t] = sums[t] + sums[t + s];
        }
        workgroupBarrier();
    }
    if (t == 0u) {
        part[wid.y * p.rows + row] = sums[0];
    }
}
