//! AVX-512 versions of the f32 Winograd tile transforms: 16 tiles per vector, with the
//! stride-4 tile columns split out of (and merged back into) image rows by two rounds of
//! two-source permutes instead of scalar moves. Same arithmetic as the portable versions in
//! `winograd.rs` up to FMA contraction.

// The transforms index several small arrays with the same tile coordinates; ranges read
// closer to the matrix formulas than zipped iterators.
#![allow(clippy::needless_range_loop)]

use std::arch::x86_64::*;

const IDX_EVEN4_A: [i32; 16] = [0, 4, 8, 12, 16, 20, 24, 28, 1, 5, 9, 13, 17, 21, 25, 29];
const IDX_EVEN4_B: [i32; 16] = [2, 6, 10, 14, 18, 22, 26, 30, 3, 7, 11, 15, 19, 23, 27, 31];
const IDX_LO8: [i32; 16] = [0, 1, 2, 3, 4, 5, 6, 7, 16, 17, 18, 19, 20, 21, 22, 23];
const IDX_HI8: [i32; 16] = [8, 9, 10, 11, 12, 13, 14, 15, 24, 25, 26, 27, 28, 29, 30, 31];
const IDX_ZIP_LO: [i32; 16] = [0, 16, 1, 17, 2, 18, 3, 19, 4, 20, 5, 21, 6, 22, 7, 23];
const IDX_ZIP_HI: [i32; 16] = [8, 24, 9, 25, 10, 26, 11, 27, 12, 28, 13, 29, 14, 30, 15, 31];

#[inline(always)]
unsafe fn idx(v: &[i32; 16]) -> __m512i {
    // SAFETY: 16 i32 = 64 bytes, read unaligned.
    unsafe { _mm512_loadu_si512(v.as_ptr().cast()) }
}

/// `B^T a` on 16 lanes.
#[inline(always)]
unsafe fn bt6(a: [__m512; 6]) -> [__m512; 6] {
    unsafe {
        let (two, four, five) = (
            _mm512_set1_ps(2.0),
            _mm512_set1_ps(4.0),
            _mm512_set1_ps(5.0),
        );
        let s42 = _mm512_sub_ps(a[4], a[2]);
        let d31 = _mm512_sub_ps(a[3], a[1]);
        [
            _mm512_fmadd_ps(four, a[0], _mm512_fnmadd_ps(five, a[2], a[4])),
            _mm512_fnmadd_ps(four, _mm512_add_ps(a[1], a[2]), _mm512_add_ps(a[3], a[4])),
            _mm512_fmadd_ps(four, _mm512_sub_ps(a[1], a[2]), _mm512_sub_ps(a[4], a[3])),
            _mm512_fmadd_ps(two, d31, s42),
            _mm512_fnmadd_ps(two, d31, s42),
            _mm512_fmadd_ps(four, a[1], _mm512_fnmadd_ps(five, a[3], a[5])),
        ]
    }
}

/// `A^T m` on 16 lanes.
#[inline(always)]
unsafe fn at4(m: [__m512; 6]) -> [__m512; 4] {
    unsafe {
        let (p12, m12) = (_mm512_add_ps(m[1], m[2]), _mm512_sub_ps(m[1], m[2]));
        let (p34, m34) = (_mm512_add_ps(m[3], m[4]), _mm512_sub_ps(m[3], m[4]));
        [
            _mm512_add_ps(_mm512_add_ps(m[0], p12), p34),
            _mm512_fmadd_ps(_mm512_set1_ps(2.0), m34, m12),
            _mm512_fmadd_ps(_mm512_set1_ps(4.0), p34, p12),
            _mm512_add_ps(_mm512_fmadd_ps(_mm512_set1_ps(8.0), m34, m12), m[5]),
        ]
    }
}

/// Extra samples each padded row needs past the last 16-tile block (the loads at +64, +65).
pub(super) const ROW_SLACK: usize = 16;

/// See `winograd::input_tiles`; each row of `rows` must hold `4*16*ceil(tw/16) + 2 + ROW_SLACK`
/// samples.
///
/// # Safety
/// The CPU must support AVX-512F; `v` must hold `36*slab` values with `off + tw <= slab`.
#[target_feature(enable = "avx512f")]
pub(super) unsafe fn input_tiles(
    rows: &[f32],
    rowlen: usize,
    tw: usize,
    v: &mut [f32],
    slab: usize,
    off: usize,
) {
    assert!(rows.len() >= 6 * rowlen && rowlen >= 4 * tw.div_ceil(16) * 16 + 2 + ROW_SLACK);
    assert!(off + tw <= slab && v.len() >= 36 * slab);
    unsafe {
        let (ia, ib, ilo, ihi) = (
            idx(&IDX_EVEN4_A),
            idx(&IDX_EVEN4_B),
            idx(&IDX_LO8),
            idx(&IDX_HI8),
        );
        for tx0 in (0..tw).step_by(16) {
            let cnt = 16.min(tw - tx0);
            let mask: __mmask16 = if cnt == 16 { 0xffff } else { (1u16 << cnt) - 1 };
            // a[r][c]: column c (0..6) of the 16 tiles' row r.
            let mut a = [[_mm512_setzero_ps(); 6]; 6];
            for (r, ar) in a.iter_mut().enumerate() {
                let p = rows.as_ptr().add(r * rowlen + 4 * tx0);
                let (z0, z1) = (_mm512_loadu_ps(p), _mm512_loadu_ps(p.add(16)));
                let (z2, z3) = (_mm512_loadu_ps(p.add(32)), _mm512_loadu_ps(p.add(48)));
                let t0 = _mm512_permutex2var_ps(z0, ia, z1);
                let t1 = _mm512_permutex2var_ps(z0, ib, z1);
                let t2 = _mm512_permutex2var_ps(z2, ia, z3);
                let t3 = _mm512_permutex2var_ps(z2, ib, z3);
                ar[0] = _mm512_permutex2var_ps(t0, ilo, t2);
                ar[1] = _mm512_permutex2var_ps(t0, ihi, t2);
                ar[2] = _mm512_permutex2var_ps(t1, ilo, t3);
                ar[3] = _mm512_permutex2var_ps(t1, ihi, t3);
                let n4 = _mm512_castps_si512(_mm512_loadu_ps(p.add(64)));
                let n5 = _mm512_castps_si512(_mm512_loadu_ps(p.add(65)));
                ar[4] =
                    _mm512_castsi512_ps(_mm512_alignr_epi32::<1>(n4, _mm512_castps_si512(ar[0])));
                ar[5] =
                    _mm512_castsi512_ps(_mm512_alignr_epi32::<1>(n5, _mm512_castps_si512(ar[1])));
            }
            // b[c] = B^T (column c over the rows), then each row of b through B^T again.
            let b: [[__m512; 6]; 6] = std::array::from_fn(|c| {
                bt6([a[0][c], a[1][c], a[2][c], a[3][c], a[4][c], a[5][c]])
            });
            for i in 0..6 {
                let o = bt6([b[0][i], b[1][i], b[2][i], b[3][i], b[4][i], b[5][i]]);
                for (j, oj) in o.into_iter().enumerate() {
                    let at = v.as_mut_ptr().add((i * 6 + j) * slab + off + tx0);
                    _mm512_mask_storeu_ps(at, mask, oj);
                }
            }
        }
    }
}

/// See `winograd::output_tiles`.
///
/// # Safety
/// The CPU must support AVX-512F; `m` must hold `36*slab` values with `off + tw <= slab`;
/// `band` must hold `(row0 + nrows) * ow` values with `nrows <= 4` and `ow <= 4*tw`.
#[target_feature(enable = "avx512f")]
#[allow(clippy::too_many_arguments)]
pub(super) unsafe fn output_tiles(
    m: &[f32],
    slab: usize,
    off: usize,
    tw: usize,
    bias: f32,
    band: &mut [f32],
    ow: usize,
    row0: usize,
    nrows: usize,
) {
    assert!(off + tw <= slab && m.len() >= 36 * slab && nrows <= 4 && ow <= 4 * tw);
    assert!(band.len() >= (row0 + nrows) * ow);
    unsafe {
        let (zlo, zhi) = (idx(&IDX_ZIP_LO), idx(&IDX_ZIP_HI));
        let bias = _mm512_set1_ps(bias);
        for tx0 in (0..tw).step_by(16) {
            let cnt = 16.min(tw - tx0);
            let mask: __mmask16 = if cnt == 16 { 0xffff } else { (1u16 << cnt) - 1 };
            let a: [__m512; 36] = std::array::from_fn(|xi| {
                _mm512_maskz_loadu_ps(mask, m.as_ptr().add(xi * slab + off + tx0))
            });
            // s[r][j]: horizontal pass of transform row r.
            let s: [[__m512; 4]; 6] = std::array::from_fn(|r| {
                at4([
                    a[r * 6],
                    a[r * 6 + 1],
                    a[r * 6 + 2],
                    a[r * 6 + 3],
                    a[r * 6 + 4],
                    a[r * 6 + 5],
                ])
            });
            // o[j][i]: vertical pass of column j.
            let o: [[__m512; 4]; 4] = std::array::from_fn(|j| {
                at4([s[0][j], s[1][j], s[2][j], s[3][j], s[4][j], s[5][j]])
            });
            let x0 = 4 * tx0;
            for i in 0..nrows {
                let (o0, o1) = (_mm512_add_ps(o[0][i], bias), _mm512_add_ps(o[1][i], bias));
                let (o2, o3) = (_mm512_add_ps(o[2][i], bias), _mm512_add_ps(o[3][i], bias));
                let a_lo = _mm512_permutex2var_ps(o0, zlo, o2);
                let a_hi = _mm512_permutex2var_ps(o0, zhi, o2);
                let b_lo = _mm512_permutex2var_ps(o1, zlo, o3);
                let b_hi = _mm512_permutex2var_ps(o1, zhi, o3);
                let c = [
                    _mm512_permutex2var_ps(a_lo, zlo, b_lo),
                    _mm512_permutex2var_ps(a_lo, zhi, b_lo),
                    _mm512_permutex2var_ps(a_hi, zlo, b_hi),
                    _mm512_permutex2var_ps(a_hi, zhi, b_hi),
                ];
                let row = band.as_mut_ptr().add((row0 + i) * ow);
                for (k, ck) in c.into_iter().enumerate() {
                    let x = x0 + 16 * k;
                    if x + 16 <= ow {
                        _mm512_storeu_ps(row.add(x), ck);
                    } else if x < ow {
                        _mm512_mask_storeu_ps(row.add(x), (1u16 << (ow - x)) - 1, ck);
                    }
                }
            }
        }
    }
}

/// `A e` on 16 lanes (see `winograd::a6`).
#[inline(always)]
unsafe fn a6(e: [__m512; 4]) -> [__m512; 6] {
    unsafe {
        let p02 = _mm512_fmadd_ps(_mm512_set1_ps(4.0), e[2], e[0]);
        let p13 = _mm512_fmadd_ps(_mm512_set1_ps(8.0), e[3], _mm512_add_ps(e[1], e[1]));
        let (s02, s13) = (_mm512_add_ps(e[0], e[2]), _mm512_add_ps(e[1], e[3]));
        [
            e[0],
            _mm512_add_ps(s02, s13),
            _mm512_sub_ps(s02, s13),
            _mm512_add_ps(p02, p13),
            _mm512_sub_ps(p02, p13),
            e[3],
        ]
    }
}

/// See `winograd::grad_tiles`; rows as for [`input_tiles`].
///
/// # Safety
/// The CPU must support AVX-512F; `e` must hold `36*slab` values with `off + tw <= slab`.
#[target_feature(enable = "avx512f")]
pub(super) unsafe fn grad_tiles(
    rows: &[f32],
    rowlen: usize,
    tw: usize,
    e: &mut [f32],
    slab: usize,
    off: usize,
) {
    assert!(rows.len() >= 4 * rowlen && rowlen >= 4 * tw.div_ceil(16) * 16);
    assert!(off + tw <= slab && e.len() >= 36 * slab);
    unsafe {
        let (ia, ib, ilo, ihi) = (
            idx(&IDX_EVEN4_A),
            idx(&IDX_EVEN4_B),
            idx(&IDX_LO8),
            idx(&IDX_HI8),
        );
        for tx0 in (0..tw).step_by(16) {
            let cnt = 16.min(tw - tx0);
            let mask: __mmask16 = if cnt == 16 { 0xffff } else { (1u16 << cnt) - 1 };
            let mut a = [[_mm512_setzero_ps(); 4]; 4];
            for (r, ar) in a.iter_mut().enumerate() {
                let p = rows.as_ptr().add(r * rowlen + 4 * tx0);
                let (z0, z1) = (_mm512_loadu_ps(p), _mm512_loadu_ps(p.add(16)));
                let (z2, z3) = (_mm512_loadu_ps(p.add(32)), _mm512_loadu_ps(p.add(48)));
                let t0 = _mm512_permutex2var_ps(z0, ia, z1);
                let t1 = _mm512_permutex2var_ps(z0, ib, z1);
                let t2 = _mm512_permutex2var_ps(z2, ia, z3);
                let t3 = _mm512_permutex2var_ps(z2, ib, z3);
                ar[0] = _mm512_permutex2var_ps(t0, ilo, t2);
                ar[1] = _mm512_permutex2var_ps(t0, ihi, t2);
                ar[2] = _mm512_permutex2var_ps(t1, ilo, t3);
                ar[3] = _mm512_permutex2var_ps(t1, ihi, t3);
            }
            let b: [[__m512; 6]; 4] =
                std::array::from_fn(|c| a6([a[0][c], a[1][c], a[2][c], a[3][c]]));
            for i in 0..6 {
                let o = a6([b[0][i], b[1][i], b[2][i], b[3][i]]);
                for (j, oj) in o.into_iter().enumerate() {
                    _mm512_mask_storeu_ps(
                        e.as_mut_ptr().add((i * 6 + j) * slab + off + tx0),
                        mask,
                        oj,
                    );
                }
            }
        }
    }
}
