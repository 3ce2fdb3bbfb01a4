// Exclusive scan, step 2 of 3: one workgroup scans the block sums in place (any count, in
// chunks of 256 * ITEMS) and writes the grand total to `sizes[total_at]`.

struct P {
    n_blocks: u32,
    total_at: u32,
    _p0: u32,
    _p1: u32,
}

const ITEMS: u32 = {{ITEMS}}u;
const CHUNK: u32 = 256u * ITEMS;

@group(0) @binding(0) var<uniform> p: P;
@group(0) @binding(1) var<storage, read_write> sums: array<u32>;
@group(0) @binding(2) var<storage, read_write> sizes: array<u32>;

var<workgroup> part: array<u32, 256>;

@compute @workgroup_size(256)
fn main(@builtin(local_invocation_index) t: u32) {
    var carry = 0u;
    for (var c = 0u; c < p.n_blocks; c = c + CHUNK) {
        let base = c + t * ITEMS;
        var v: array<u32, ITEMS>;
        var s = 0u;
        for (var i = 0u; i < ITEMS; i = i + 1u) {
            var x = 0u;
            if (base + i < p.n_blocks) {
                x = sums[base + i];
            }
            v[i] = s;
            s = s + x;
        }
        part[t] = s;
        workgroupBarrier();
        // Hillis-Steele inclusive scan of the 256 thread sums.
        for (var w = 1u; w < 256u; w = w << 1u) {
            var add = 0u;
            if (t >= w) {
                add = part[t - w];
            }
            workgroupBarrier();
            part[t] = part[t] + add;
            workgroupBarrier();
        }
        var before = carry;
        if (t > 0u) {
            before = before + part[t - 1u];
        }
        for (var i = 0u; i < ITEMS; i = i + 1u) {
            if (base + i < p.n_blocks) {
                sums[base + i] = before + v[i];
            }
        }
        carry = carry + part[255];
        workgroupBarrier();
    }
    if (t == 0u && p.total_at != 0xffffffffu) {
        sizes[p.total_at] = carry;
    }
}
