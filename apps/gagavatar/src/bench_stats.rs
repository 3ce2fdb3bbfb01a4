//! What the bench commands share: the median they report, dispatch times per kernel.

/// The median of `v` (sorted in place; the upper one of an even count).
pub fn median(v: &mut [f64]) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    v[v.len() / 2]
}

/// A kernel and grid's time summed over the dispatches of one pass: (label, stage, calls, ms).
pub type KernelTotal = (String, &'static str, usize, f64);

/// Dispatch times summed per kernel and grid (layers of one shape share both), costliest
/// first.
pub fn by_kernel(times: Vec<gagavatar_gpu::kernel::DispatchTime>) -> Vec<KernelTotal> {
    let mut out: Vec<KernelTotal> = Vec::new();
    for t in times {
        match out.iter_mut().find(|k| k.0 == t.label) {
            Some(k) => {
                k.2 += 1;
                k.3 += t.ms;
            }
            None => out.push((t.label, t.stage, 1, t.ms)),
        }
    }
    out.sort_by(|x, y| y.3.total_cmp(&x.3));
    out
}

/// Prints the `top` costliest kernels of `what` ("one frame", "one run").
pub fn print_dispatches(by: &[KernelTotal], what: &str, top: usize) {
    let total: f64 = by.iter().map(|k| k.3).sum();
    println!(
        "  dispatches of {what}, each timed alone ({} kernels and grids, {total:.2} ms in all; the {top} costliest):",
        by.len()
    );
    for (label, stage, calls, ms) in by.iter().take(top) {
        println!("    {label:<52} {calls:>3} x  {ms:>8.3} ms  ({stage})");
    }
}

/// The JSON of [`by_kernel`]'s rows.
pub fn dispatches_json(by: &[KernelTotal]) -> Vec<serde_json::Value> {
    by.iter()
        .map(|(label, stage, calls, ms)| {
            serde_json::json!({"kernel": label, "stage": stage, "calls": calls, "ms": ms})
        })
        .collect()
}
