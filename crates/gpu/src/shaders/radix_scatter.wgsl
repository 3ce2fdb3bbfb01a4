// Stable LSD radix sort, pass step 3 of 3: each block sorts its keys by the digit at `shift`
// in workgroup memory (one stable 1-bit split per digit bit, so equal digits keep their
// order) and writes each key to its block's slot for its digit (`offsets`: the scanned
// histogram) plus its rank among the block's keys of that digit.

struct P {
    shift: u32,
    n: u32,
    size_at: u32,
    _p0: u32,
}

const ITEMS: u32 = {{ITEMS}}u;
const BLOCK: u32 = 256u * ITEMS;
const RADIX: u32 = {{RADIX}}u;
const BITS: u32 = {{BITS}}u;

@group(0) @binding(0) var<uniform> p: P;
@group(0) @binding(1) var<storage, read> sizes: array<u32>;
@group(0) @binding(2) var<storage, read> keys_in: array<u32>;
@group(0) @binding(3) var<storage, read> vals_in: array<u32>;
@group(0) @binding(4) var<storage, read> offsets: array<u32>;
@group(0) @binding(5) var<storage, read_write> keys_out: array<u32>;
@group(0) @binding(6) var<storage, read_write> vals_out: array<u32>;

var<workgroup> sk: array<u32, BLOCK>;
var<workgroup> sv: array<u32, BLOCK>;
var<workgroup> part: array<u32, 256>;
var<workgroup> first: array<atomic<u32>, RADIX>;

fn digit_of(k: u32, valid: bool) -> u32 {
    if (!valid) {
        // Keys past the end (only in the last block, where they already come last) take the
        // largest digit: the stable sort keeps them after every real key.
        return RADIX - 1u;
    }
    return (k >> p.shift) & (RADIX - 1u);
}

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) t: u32) {
    var n = p.n;
    if (p.size_at != 0xffffffffu) {
        n = sizes[p.size_at];
    }
    let blocks = (n + BLOCK - 1u) / BLOCK;
    let start = wid.x * BLOCK;
    let valid_here = min(n - start, BLOCK);
    var k: array<u32, ITEMS>;
    var v: array<u32, ITEMS>;
    for (var i = 0u; i < ITEMS; i = i + 1u) {
        let at = start + t * ITEMS + i;
        if (at < n) {
            k[i] = keys_in[at];
            v[i] = vals_in[at];
        } else {
            k[i] = 0u;
            v[i] = 0u;
        }
    }
    for (var b = 0u; b < BITS; b = b + 1u) {
        // Split on bit b of the digit: zeros first, then ones, each in order.
        var ones = 0u;
        for (var i = 0u; i < ITEMS; i = i + 1u) {
            let pos = t * ITEMS + i;
            ones = ones + ((digit_of(k[i], pos < valid_here) >> b) & 1u);
        }
        part[t] = ones;
        workgroupBarrier();
        for (var w = 1u; w < 256u; w = w << 1u) {
            var add = 0u;
            if (t >= w) {
                add = part[t - w];
            }
            workgroupBarrier();
            part[t] = part[t] + add;
            workgroupBarrier();
        }
        let total_ones = part[255];
        var ones_before = 0u;
        if (t > 0u) {
            ones_before = part[t - 1u];
        }
        let total_zeros = BLOCK - total_ones;
        for (var i = 0u; i < ITEMS; i = i + 1u) {
            let pos = t * ITEMS + i;
            let bit = (digit_of(k[i], pos < valid_here) >> b) & 1u;
            var dst = pos - ones_before;
            if (bit == 1u) {
                dst = total_zeros + ones_before;
            }
            ones_before = ones_before + bit;
            sk[dst] = k[i];
            sv[dst] = v[i];
        }
        workgroupBarrier();
        // Remember which positions were valid: a valid key never moves behind an invalid one,
        // so the first `valid_here` positions stay the valid keys.
        for (var i = 0u; i < ITEMS; i = i + 1u) {
            let pos = t * ITEMS + i;
            k[i] = sk[pos];
            v[i] = sv[pos];
        }
        workgroupBarrier();
    }
    // First sorted position of each digit in the block.
    for (var d = t; d < RADIX; d = d + 256u) {
        atomicStore(&first[d], BLOCK);
    }
    workgroupBarrier();
    for (var i = 0u; i < ITEMS; i = i + 1u) {
        let pos = t * ITEMS + i;
        if (pos < valid_here) {
            atomicMin(&first[digit_of(k[i], true)], pos);
        }
    }
    workgroupBarrier();
    for (var i = 0u; i < ITEMS; i = i + 1u) {
        let pos = t * ITEMS + i;
        if (pos < valid_here) {
            let d = digit_of(k[i], true);
            let dst = offsets[d * blocks + wid.x] + (pos - atomicLoad(&first[d]));
            keys_out[dst] = k[i];
            vals_out[dst] = v[i];
        }
    }
}
