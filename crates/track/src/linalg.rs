//! Small dense linear algebra for the normal equations of the fit (a few hundred unknowns):
//! products through the `gemm` crate (the workspace's matrix kernel), Cholesky solves,
//! row-major `Vec<f64>`.

/// `c[m x n] (+)= a^T b` for row-major `a [k x m]` and `b [k x n]`: the normal-equation
/// products `J^T J` and `J^T K`. `accumulate` adds to `c` instead of overwriting it.
pub fn matmul_tn(
    a: &[f64],
    b: &[f64],
    k: usize,
    m: usize,
    n: usize,
    c: &mut [f64],
    accumulate: bool,
) {
    assert!(
        a.len() == k * m && b.len() == k * n && c.len() == m * n,
        "matmul_tn: operand sizes {} {} {} for k {k}, m {m}, n {n}",
        a.len(),
        b.len(),
        c.len()
    );
    if m == 0 || n == 0 {
        return;
    }
    if k == 0 {
        if !accumulate {
            c.fill(0.0);
        }
        return;
    }
    // SAFETY: the three slices hold exactly the strided extents given (checked above), and `c`
    // is a distinct `&mut` borrow, so it cannot alias `a` or `b`.
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            c.as_mut_ptr(),
            1,
            n as isize,
            accumulate,
            a.as_ptr(),
            m as isize,
            1,
            b.as_ptr(),
            1,
            n as isize,
            1.0,
            1.0,
            false,
            false,
            false,
            gemm::Parallelism::None,
        )
    }
}

/// `J^T r` for row-major `J [k x n]`.
pub fn matvec_tn(j: &[f64], r: &[f64], n: usize) -> Vec<f64> {
    let mut g = vec![0.0; n];
    for (row, &ri) in j.chunks_exact(n).zip(r) {
        if ri != 0.0 {
            for (gi, &x) in g.iter_mut().zip(row) {
                *gi += x * ri;
            }
        }
    }
    g
}

/// In-place Cholesky `a = L L^T` (lower triangle holds L). `false` if not positive definite.
pub fn cholesky(a: &mut [f64], n: usize) -> bool {
    for j in 0..n {
        let mut d = a[j * n + j];
        for k in 0..j {
            d -= a[j * n + k] * a[j * n + k];
        }
        if !(d > 0.0) || !d.is_finite() {
            return false;
        }
        let d = d.sqrt();
        a[j * n + j] = d;
        for i in j + 1..n {
            let (ri, rj) = (i * n, j * n);
            let mut s = a[ri + j];
            for k in 0..j {
                s -= a[ri + k] * a[rj + k];
            }
            a[ri + j] = s / d;
        }
    }
    true
}

/// Solves `L L^T x = b` in place for one right-hand side.
pub fn cholesky_solve(l: &[f64], n: usize, b: &mut [f64]) {
    for i in 0..n {
        let mut s = b[i];
        for k in 0..i {
            s -= l[i * n + k] * b[k];
        }
        b[i] = s / l[i * n + i];
    }
    for i in (0..n).rev() {
        let mut s = b[i];
        for k in i + 1..n {
            s -= l[k * n + i] * b[k];
        }
        b[i] = s / l[i * n + i];
    }
}

/// Solves `L L^T X = B` for `B` `[n][m]` row-major (m right-hand sides), in place.
pub fn cholesky_solve_many(l: &[f64], n: usize, b: &mut [f64], m: usize) {
    for i in 0..n {
        for k in 0..i {
            let lik = l[i * n + k];
            if lik == 0.0 {
                continue;
            }
            let (head, tail) = b.split_at_mut(i * m);
            let bk = &head[k * m..(k + 1) * m];
            for (x, y) in tail[..m].iter_mut().zip(bk) {
                *x -= lik * y;
            }
        }
        let d = 1.0 / l[i * n + i];
        for x in &mut b[i * m..(i + 1) * m] {
            *x *= d;
        }
    }
    for i in (0..n).rev() {
        for k in i + 1..n {
            let lki = l[k * n + i];
            if lki == 0.0 {
                continue;
            }
            let (head, tail) = b.split_at_mut(k * m);
            let bk = &tail[..m];
            for (x, y) in head[i * m..(i + 1) * m].iter_mut().zip(bk) {
                *x -= lki * y;
            }
        }
        let d = 1.0 / l[i * n + i];
        for x in &mut b[i * m..(i + 1) * m] {
            *x *= d;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn matmul_tn_matches_loops() {
        let (k, m, n) = (7, 5, 3);
        let a: Vec<f64> = (0..k * m).map(|i| (i as f64 * 0.37).sin()).collect();
        let b: Vec<f64> = (0..k * n).map(|i| (i as f64 * 0.91).cos()).collect();
        let mut c = vec![1.0; m * n];
        matmul_tn(&a, &b, k, m, n, &mut c, true);
        for i in 0..m {
            for j in 0..n {
                let want: f64 = 1.0 + (0..k).map(|t| a[t * m + i] * b[t * n + j]).sum::<f64>();
                assert!((c[i * n + j] - want).abs() < 1e-12, "[{i}][{j}]");
            }
        }
        let g = matvec_tn(&a, &[1.0; 7], m);
        for i in 0..m {
            let want: f64 = (0..k).map(|t| a[t * m + i]).sum();
            assert!((g[i] - want).abs() < 1e-12);
        }
    }

    #[test]
    fn solves_a_small_spd_system() {
        // A = M M^T + I for a fixed M.
        let n = 5;
        let m: Vec<f64> = (0..n * n)
            .map(|i| ((i * 7 % 11) as f64 - 5.0) / 3.0)
            .collect();
        let mut a = vec![0.0; n * n];
        matmul_tn(&m, &m, n, n, n, &mut a, false);
        for i in 0..n {
            a[i * n + i] += 1.0;
        }
        let a0 = a.clone();
        let x_true: Vec<f64> = (0..n).map(|i| i as f64 - 1.5).collect();
        let b: Vec<f64> = (0..n)
            .map(|i| (0..n).map(|j| a0[i * n + j] * x_true[j]).sum())
            .collect();
        assert!(cholesky(&mut a, n));
        let mut x = b.clone();
        cholesky_solve(&a, n, &mut x);
        for i in 0..n {
            assert!(
                (x[i] - x_true[i]).abs() < 1e-10,
                "{i}: {} vs {}",
                x[i],
                x_true[i]
            );
        }
        // Two right-hand sides at once: b and 2b.
        let mut bb: Vec<f64> = b.iter().flat_map(|&v| [v, 2.0 * v]).collect();
        cholesky_solve_many(&a, n, &mut bb, 2);
        for i in 0..n {
            assert!((bb[2 * i] - x_true[i]).abs() < 1e-10);
            assert!((bb[2 * i + 1] - 2.0 * x_true[i]).abs() < 1e-10);
        }
        let mut not_pd = vec![1.0, 2.0, 2.0, 1.0];
        assert!(!cholesky(&mut not_pd, 2));
    }
}
