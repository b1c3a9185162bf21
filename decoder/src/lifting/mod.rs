//! Integer wavelet lifting of one diamond (DESIGN section 3, the paper's section 3).
//!
//! A diamond at level `l` holds an `(N+1) x (N+1)` vertex grid `v` (row-major,
//! `v[i * (N+1) + j]`). Refining it produces the values of its `N x N` cell centres `c`
//! (`c[i * N + j]`, cell `(i, j)` between vertices `(i, j)` and `(i+1, j+1)`) and
//! updated vertex values: together the level `l+1` lattice inside its square.
//!
//! - Prediction `P`: order-4 Neville quincunx filter (the 4 corners at 10/32, the next 8
//!   lattice neighbours at -1/32) when all 12 support points are in the diamond and valid,
//!   else order 2 (mean of the 4 corners); at the edge of the valid region, the mean of
//!   the valid corners.
//! - Update `U/2`: the sum of the 4 neighbouring details / 8, only on interior vertices
//!   whose 4 cells are all valid. Boundary vertices are never changed, which is what
//!   makes every mixed-level cut seamless.
//!
//! All arithmetic wraps modulo 2^32: every lifting step adds a function of values the
//! step does not change, so synthesis inverts analysis exactly for *any* `i32` input.

mod gather;

use std::sync::Arc;

pub use gather::{child_half, scatter_to_child};

/// Which vertices and cells of a diamond are valid samples (inside the domain and the
/// valid extent). Invalid points are never read by prediction or update, and their
/// details are never coded. Cloning is cheap (shared storage), so one mask can serve many
/// diamonds.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct DiamondMask {
    /// One pointer: a planet's geometry holds an `Option` of this per diamond.
    bits: Arc<MaskBits>,
}

#[derive(Debug, PartialEq, Eq)]
struct MaskBits {
    n: usize,
    vertex: Box<[bool]>,
    cell: Box<[bool]>,
}

impl DiamondMask {
    /// A mask from predicates on vertex `(i, j)` and cell `(i, j)` indices.
    pub fn from_fn(
        n: usize,
        vertex: impl Fn(usize, usize) -> bool,
        cell: impl Fn(usize, usize) -> bool,
    ) -> Self {
        let w = n + 1;
        let vertex = (0..w * w).map(|k| vertex(k / w, k % w)).collect();
        let cell = (0..n * n).map(|k| cell(k / n, k % n)).collect();
        DiamondMask {
            bits: Arc::new(MaskBits { n, vertex, cell }),
        }
    }

    /// The mask of a diamond with no valid point.
    pub fn none(n: usize) -> Self {
        DiamondMask {
            bits: Arc::new(MaskBits {
                n,
                vertex: vec![false; (n + 1) * (n + 1)].into(),
                cell: vec![false; n * n].into(),
            }),
        }
    }

    /// Grid size `N`.
    pub fn n(&self) -> usize {
        self.bits.n
    }

    /// Whether vertex `(i, j)` is valid.
    pub fn vertex(&self, i: usize, j: usize) -> bool {
        self.bits.vertex[i * (self.bits.n + 1) + j]
    }

    /// Whether cell `(i, j)` is valid.
    pub fn cell(&self, i: usize, j: usize) -> bool {
        self.bits.cell[i * self.bits.n + j]
    }

    /// Cell validity, row-major.
    pub fn cells(&self) -> &[bool] {
        &self.bits.cell
    }

    /// Number of valid cells.
    pub fn valid_cells(&self) -> usize {
        self.bits.cell.iter().filter(|&&b| b).count()
    }
}

/// Analysis of one diamond: `v` holds the fine vertex values on entry and the coarse
/// ones on exit; `c` holds the fine cell-centre values; `h` receives the details (zero at
/// invalid cells).
pub fn analyze(n: usize, v: &mut [i32], c: &[i32], h: &mut [i32], mask: Option<&DiamondMask>) {
    debug_assert!(v.len() == (n + 1) * (n + 1) && c.len() == n * n && h.len() == n * n);
    predict(n, v, h, mask);
    for k in 0..n * n {
        let valid = mask.is_none_or(|m| m.bits.cell[k]);
        h[k] = if valid { c[k].wrapping_sub(h[k]) } else { 0 };
    }
    update(n, v, h, mask, false);
}

/// Synthesis of one diamond, the exact inverse of [`analyze`]: `v` holds the coarse
/// vertex values on entry and the fine ones on exit; `c` receives the cell centres
/// (zero at invalid cells).
pub fn synthesize(n: usize, v: &mut [i32], h: &[i32], c: &mut [i32], mask: Option<&DiamondMask>) {
    debug_assert!(v.len() == (n + 1) * (n + 1) && c.len() == n * n && h.len() == n * n);
    update(n, v, h, mask, true);
    predict(n, v, c, mask);
    for k in 0..n * n {
        let valid = mask.is_none_or(|m| m.bits.cell[k]);
        c[k] = if valid { c[k].wrapping_add(h[k]) } else { 0 };
    }
}

/// Synthesis of a diamond whose details are all zero: the update changes nothing, so
/// `v` is left as it is and the cells are the prediction (zero at invalid cells), exactly
/// what [`synthesize`] gives with a zero `h`.
pub fn synthesize_zero(n: usize, v: &[i32], c: &mut [i32], mask: Option<&DiamondMask>) {
    debug_assert!(v.len() == (n + 1) * (n + 1) && c.len() == n * n);
    predict(n, v, c, mask);
    if let Some(m) = mask {
        for (x, &ok) in c.iter_mut().zip(m.bits.cell.iter()) {
            if !ok {
                *x = 0;
            }
        }
    }
}

#[inline(always)]
fn p2(a: i32, b: i32, c: i32, d: i32) -> i32 {
    a.wrapping_add(b)
        .wrapping_add(c)
        .wrapping_add(d)
        .wrapping_add(2)
        >> 2
}

/// Writes the prediction of every cell centre into `p`.
fn predict(n: usize, v: &[i32], p: &mut [i32], mask: Option<&DiamondMask>) {
    match mask {
        None => predict_full(n, v, p),
        Some(m) => predict_masked(n, v, p, m),
    }
}

fn predict_full(n: usize, v: &[i32], p: &mut [i32]) {
    let w = n + 1;
    for i in 0..n {
        let r0 = &v[i * w..i * w + w];
        let r1 = &v[(i + 1) * w..(i + 1) * w + w];
        let prow = &mut p[i * n..i * n + n];
        if i == 0 || i == n - 1 || n < 4 {
            for j in 0..n {
                prow[j] = p2(r0[j], r0[j + 1], r1[j], r1[j + 1]);
            }
            continue;
        }
        let rm = &v[(i - 1) * w..(i - 1) * w + w];
        let r2 = &v[(i + 2) * w..(i + 2) * w + w];
        prow[0] = p2(r0[0], r0[1], r1[0], r1[1]);
        prow[n - 1] = p2(r0[n - 1], r0[n], r1[n - 1], r1[n]);
        for j in 1..n - 1 {
            let s4 = r0[j]
                .wrapping_add(r0[j + 1])
                .wrapping_add(r1[j])
                .wrapping_add(r1[j + 1]);
            let s8 = rm[j]
                .wrapping_add(rm[j + 1])
                .wrapping_add(r2[j])
                .wrapping_add(r2[j + 1])
                .wrapping_add(r0[j - 1])
                .wrapping_add(r1[j - 1])
                .wrapping_add(r0[j + 2])
                .wrapping_add(r1[j + 2]);
            prow[j] = s4.wrapping_mul(10).wrapping_sub(s8).wrapping_add(16) >> 5;
        }
    }
}

fn predict_masked(n: usize, v: &[i32], p: &mut [i32], m: &DiamondMask) {
    let w = n + 1;
    let val = |i: usize, j: usize| v[i * w + j];
    for i in 0..n {
        for j in 0..n {
            if !m.cell(i, j) {
                p[i * n + j] = 0;
                continue;
            }
            let corners = [(i, j), (i, j + 1), (i + 1, j), (i + 1, j + 1)];
            let all4 = corners.iter().all(|&(a, b)| m.vertex(a, b));
            let order4 = all4
                && (1..=n - 2).contains(&i)
                && (1..=n - 2).contains(&j)
                && [
                    (i - 1, j),
                    (i - 1, j + 1),
                    (i + 2, j),
                    (i + 2, j + 1),
                    (i, j - 1),
                    (i + 1, j - 1),
                    (i, j + 2),
                    (i + 1, j + 2),
                ]
                .iter()
                .all(|&(a, b)| m.vertex(a, b));
            p[i * n + j] = if order4 {
                let s4 = val(i, j)
                    .wrapping_add(val(i, j + 1))
                    .wrapping_add(val(i + 1, j))
                    .wrapping_add(val(i + 1, j + 1));
                let s8 = [
                    (i - 1, j),
                    (i - 1, j + 1),
                    (i + 2, j),
                    (i + 2, j + 1),
                    (i, j - 1),
                    (i + 1, j - 1),
                    (i, j + 2),
                    (i + 1, j + 2),
                ]
                .iter()
                .fold(0i32, |acc, &(a, b)| acc.wrapping_add(val(a, b)));
                s4.wrapping_mul(10).wrapping_sub(s8).wrapping_add(16) >> 5
            } else if all4 {
                p2(val(i, j), val(i, j + 1), val(i + 1, j), val(i + 1, j + 1))
            } else {
                let (sum, k) = corners
                    .iter()
                    .filter(|&&(a, b)| m.vertex(a, b))
                    .fold((0i64, 0i64), |(s, k), &(a, b)| {
                        (s + val(a, b) as i64, k + 1)
                    });
                if k == 0 {
                    0
                } else {
                    (2 * sum + k).div_euclid(2 * k) as i32
                }
            };
        }
    }
}

/// Adds (analysis) or subtracts (synthesis) the update to interior vertices.
fn update(n: usize, v: &mut [i32], h: &[i32], mask: Option<&DiamondMask>, inverse: bool) {
    let w = n + 1;
    for i in 1..n {
        let (ha, hb) = (&h[(i - 1) * n..i * n], &h[i * n..(i + 1) * n]);
        let row = &mut v[i * w..i * w + w];
        match mask {
            None => {
                for j in 1..n {
                    let s = ha[j - 1]
                        .wrapping_add(ha[j])
                        .wrapping_add(hb[j - 1])
                        .wrapping_add(hb[j]);
                    let u = s.wrapping_add(4) >> 3;
                    row[j] = if inverse {
                        row[j].wrapping_sub(u)
                    } else {
                        row[j].wrapping_add(u)
                    };
                }
            }
            Some(m) => {
                for j in 1..n {
                    if !(m.cell(i - 1, j - 1)
                        && m.cell(i - 1, j)
                        && m.cell(i, j - 1)
                        && m.cell(i, j))
                    {
                        continue;
                    }
                    let s = ha[j - 1]
                        .wrapping_add(ha[j])
                        .wrapping_add(hb[j - 1])
                        .wrapping_add(hb[j]);
                    let u = s.wrapping_add(4) >> 3;
                    row[j] = if inverse {
                        row[j].wrapping_sub(u)
                    } else {
                        row[j].wrapping_add(u)
                    };
                }
            }
        }
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use super::*;

    fn lcg(seed: &mut u64) -> u64 {
        *seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        *seed >> 16
    }

    #[test]
    fn synthesis_inverts_analysis_exactly_over_the_full_i32_range() {
        let mut seed = 7;
        for n in [2, 4, 8, 32, 64] {
            for _ in 0..20 {
                let v0: Vec<i32> = (0..(n + 1) * (n + 1))
                    .map(|_| lcg(&mut seed) as i32)
                    .collect();
                let c0: Vec<i32> = (0..n * n).map(|_| lcg(&mut seed) as i32).collect();
                let mut v = v0.clone();
                let mut h = vec![0; n * n];
                analyze(n, &mut v, &c0, &mut h, None);
                let mut c = vec![0; n * n];
                synthesize(n, &mut v, &h, &mut c, None);
                assert_eq!(v, v0);
                assert_eq!(c, c0);
            }
        }
    }

    #[test]
    fn zero_detail_synthesis_equals_synthesis_of_zeros() {
        let mut seed = 7;
        let n = 16;
        let masks = [
            None,
            Some(DiamondMask::from_fn(
                n,
                |i, j| i + 3 >= j,
                |i, j| i + 3 > j && (i + j) % 7 != 3,
            )),
        ];
        for mask in &masks {
            for _ in 0..20 {
                let v: Vec<i32> = (0..(n + 1) * (n + 1))
                    .map(|_| (lcg(&mut seed) >> 40) as i32 - (1 << 23))
                    .collect();
                let (mut v1, mut c1) = (v.clone(), vec![1; n * n]);
                synthesize(n, &mut v1, &vec![0; n * n], &mut c1, mask.as_ref());
                let mut c2 = vec![2; n * n];
                synthesize_zero(n, &v, &mut c2, mask.as_ref());
                assert_eq!(v1, v, "zero details leave the vertices unchanged");
                assert_eq!(c1, c2);
            }
        }
    }

    #[test]
    fn masked_synthesis_inverts_analysis_on_valid_points() {
        let mut seed = 11;
        let n = 32;
        let mask = DiamondMask::from_fn(n, |i, j| i + 3 >= j, |i, j| i + 3 > j && (i + j) % 7 != 3);
        let v0: Vec<i32> = (0..(n + 1) * (n + 1))
            .map(|_| (lcg(&mut seed) % 5000) as i32)
            .collect();
        let c0: Vec<i32> = (0..n * n)
            .map(|k| {
                if mask.cells()[k] {
                    (lcg(&mut seed) % 5000) as i32
                } else {
                    0
                }
            })
            .collect();
        let mut v = v0.clone();
        let mut h = vec![0; n * n];
        analyze(n, &mut v, &c0, &mut h, Some(&mask));
        let mut c = vec![0; n * n];
        synthesize(n, &mut v, &h, &mut c, Some(&mask));
        assert_eq!(c, c0);
        for i in 0..=n {
            for j in 0..=n {
                if mask.vertex(i, j) {
                    assert_eq!(v[i * (n + 1) + j], v0[i * (n + 1) + j]);
                }
            }
        }
    }

    #[test]
    fn order_four_prediction_reproduces_cubic_surfaces() {
        let n = 16;
        let f = |x: f64, y: f64| (x * x * x - 3.0 * x * y * y + 7.0 * y) as i64;
        // Values scaled by 64 so that centre values at half-integer points are integers.
        let v: Vec<i32> = (0..(n + 1) * (n + 1))
            .map(|k| f((2 * (k / (n + 1))) as f64, (2 * (k % (n + 1))) as f64) as i32)
            .collect();
        let c: Vec<i32> = (0..n * n)
            .map(|k| f((2 * (k / n) + 1) as f64, (2 * (k % n) + 1) as f64) as i32)
            .collect();
        let mut p = vec![0; n * n];
        predict_full(n, &v, &mut p);
        for i in 1..n - 1 {
            for j in 1..n - 1 {
                assert!((p[i * n + j] - c[i * n + j]).abs() <= 1, "cell ({i},{j})");
            }
        }
    }
}
