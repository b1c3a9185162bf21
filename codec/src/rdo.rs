//! Rate-distortion optimised quantisation (encoder only; the format and the decoder are
//! unchanged).
//!
//! The plain quantiser rounds each detail on its own. This one walks a matrix in the
//! coefficient coder's order ([`crate::entropy::write_matrix`]: 4x4 blocks in raster order, cells
//! in raster order) with the coder's own contexts and adaptive probabilities, starting
//! from a trained [`CodecModel`], and picks for each cell the index among the nearest,
//! one less and zero that minimises `squared error + lambda x bits`. Then each block as
//! a whole is compared with coding it as empty, and the whole matrix with coding none of
//! it. Reconstruction stays the uniform [`crate::encode::dequantize`].

use std::sync::OnceLock;

use crate::encode::dequantize;
use crate::entropy::range::{Prob, adapt};
use crate::entropy::{
    Causal, CodecModel, Decision, HIDDEN_SIGN_MIN, NONZERO, PER_GROUP, QUAD, SIGN, activity_class,
    magnitude_decisions, on_ring, rice, sig_ctx,
};

/// Cost in bits of a decision whose probability is `p / 2^16`, by `p >> 4`.
fn cost_table() -> &'static [f32; 4096] {
    static TABLE: OnceLock<[f32; 4096]> = OnceLock::new();
    TABLE.get_or_init(|| {
        let mut t = [0f32; 4096];
        for (k, c) in t.iter_mut().enumerate() {
            let p = (k as f64 * 16.0 + 8.0) / 65536.0;
            *c = -p.log2() as f32;
        }
        t
    })
}

/// The adaptive probabilities of one level group, with an undo log for trial codings.
struct Model<'a> {
    probs: Vec<Prob>,
    log: Vec<(u16, Prob)>,
    cost: &'a [f32; 4096],
}

impl Model<'_> {
    /// Cost of coding `bit` in context `c` (group-relative), without coding it.
    #[inline(always)]
    fn cost(&self, c: usize, bit: bool) -> f32 {
        let p = self.probs[c] as u32;
        let p = if bit { 65536 - p } else { p };
        self.cost[(p >> 4).min(4095) as usize]
    }

    /// Codes `bit` in context `c`: returns its cost and adapts (logged).
    #[inline(always)]
    fn code(&mut self, c: usize, bit: bool) -> f32 {
        let cost = self.cost(c, bit);
        self.log.push((c as u16, self.probs[c]));
        adapt(&mut self.probs[c], bit);
        cost
    }

    fn rollback(&mut self, to: usize) {
        while self.log.len() > to {
            if let Some((c, p)) = self.log.pop() {
                self.probs[c as usize] = p;
            }
        }
    }

    /// Bits of magnitude `mag = |q| - 1` in context set `set` with Rice parameter `kr`
    /// (coding it when `commit`).
    #[inline(always)]
    fn magnitude(&mut self, set: usize, kr: u32, mag: u32, commit: bool) -> f32 {
        let mut bits = 0.0;
        magnitude_decisions(set, kr, mag, |d| {
            bits += match d {
                Decision::Bit(c, bit) if commit => self.code(c, bit),
                Decision::Bit(c, bit) => self.cost(c, bit),
                Decision::Bypass(_, count) => count as f32,
            }
        });
        bits
    }
}

/// What the quantiser needs to know about one matrix.
#[derive(Clone, Copy, Debug)]
pub struct Matrix<'a> {
    /// Level group ([`crate::entropy::group`]).
    pub group: usize,
    /// Cells per side.
    pub n: usize,
    /// Coded cells (`None` = all); the details of the others must be 0.
    pub valid: Option<&'a [bool]>,
    /// Quantiser step in 1/256 of a detail unit ([`crate::blob::BlobContext::step`]):
    /// above 256 the level is quantised and hides signs; 256 is the identity.
    pub step: u32,
    /// Squared error (detail units) that one bit is worth.
    pub lambda: f32,
}

/// Quantises one matrix of `details` into `q` (both `n x n`), choosing each index among
/// the nearest, one less and zero by squared error plus `lambda` times its bits under
/// `model`'s probabilities (adapted as the coder would), then each 4x4 block and the
/// whole matrix against coding them empty. Blocks that hide a sign are given the right
/// parity by `fix_parity(block indices, block details)` (the valid cells of one block,
/// in coding order). Every index keeps the sign of its detail.
pub fn quantize_matrix(
    model: &CodecModel,
    matrix: &Matrix<'_>,
    details: &[i32],
    q: &mut [i32],
    fix_parity: impl Fn(&mut [i32], &[i32]),
) {
    let (g, n, valid, s) = (matrix.group, matrix.n, matrix.valid, matrix.step);
    if s <= 256 {
        q.copy_from_slice(details);
        return;
    }
    q.iter_mut().for_each(|x| *x = 0);
    // Index nearest to `|d|`: the quotient estimated in `f64`, corrected by one.
    let (step, inverse) = (i64::from(s), 1.0 / f64::from(s));
    let nearest = |d: i32| -> u32 {
        // `x < 2^40`: exact in `f64`, and the estimate is within one of the quotient.
        let x = i64::from(d.unsigned_abs()) * 256 + step / 2;
        let mut q = (x as f64 * inverse) as i64;
        if q * step > x {
            q -= 1;
        } else if (q + 1) * step <= x {
            q += 1;
        }
        q.min(i64::from(i32::MAX)) as u32
    };
    // `nearest(d) == 0` exactly when `2 |d| 256 < s` (`s` odd or even alike).
    let zero_limit = u64::from(s);
    let rounds_to_zero = |d: i32| u64::from(d.unsigned_abs()) * 512 < zero_limit;
    if details.iter().all(|&d| rounds_to_zero(d)) {
        return;
    }
    let is_valid = |k: usize| valid.is_none_or(|v| v[k]);
    let base = g * PER_GROUP;
    let lambda = matrix.lambda;
    let mut m = Model {
        probs: model.probs()[base..base + PER_GROUP].to_vec(),
        log: Vec::with_capacity(256),
        cost: cost_table(),
    };
    let b = n.min(4);
    let nb = n / b;
    let mut block_sig = vec![false; nb * nb];
    let mut rec = Causal::new(n);
    let mut cells = [(0usize, 0usize, 0usize); 16];
    let mut near = [0u32; 16];
    let mut block_q = [0i32; 16];
    let mut block_d = [0i32; 16];
    let mut total_j = 0f64;
    let mut zero_j = 0f64;
    for by in 0..nb {
        for bx in 0..nb {
            let mut nc = 0;
            let mut any = false;
            let mut d2 = 0f64;
            for i in by * b..(by + 1) * b {
                for j in bx * b..(bx + 1) * b {
                    let k = i * n + j;
                    if is_valid(k) {
                        cells[nc] = (k, i, j);
                        any |= !rounds_to_zero(details[k]);
                        let x = i64::from(details[k]);
                        d2 += (x * x) as f64;
                        nc += 1;
                    }
                }
            }
            zero_j += d2;
            if nc == 0 {
                continue;
            }
            let left = bx > 0 && block_sig[by * nb + bx - 1];
            let up = by > 0 && block_sig[(by - 1) * nb + bx];
            let quad = QUAD + left as usize + up as usize;
            let j_empty = d2 as f32 + lambda * m.cost(quad, false);
            if !any {
                total_j += f64::from(j_empty);
                continue;
            }
            for (c, &(k, _, _)) in cells[..nc].iter().enumerate() {
                near[c] = nearest(details[k]);
            }
            // Trial: code the block greedily.
            let mark = m.log.len();
            let mut j_coded = lambda * m.cost(quad, true);
            let mut seen = false;
            let mut count = 0;
            // The block's first nonzero: (row, column, index, sign context). Its sign is
            // hidden, or coded after the block's last cell.
            let mut first: Option<(usize, usize, i32, usize)> = None;
            for (idx, &(k, i, j)) in cells[..nc].iter().enumerate() {
                let a = rec.activity(i, j);
                let class = activity_class(a);
                let ring = on_ring(n, i, j);
                let d = details[k];
                let ad = i64::from(d.unsigned_abs());
                let mh = near[idx];
                let inferred = idx + 1 == nc && !seen;
                let sc = sig_ctx(class, ring);
                let (kr, set) = rice(a, class, ring);
                let sign_ctx = SIGN + rec.sign_context(i, j);
                let err = |c: u32| {
                    // The decoder's reconstruction (`c` is at most `i32::MAX`).
                    let e = ad - i64::from(dequantize(c as i32, s));
                    (e * e) as f32
                };
                let cand = if mh >= 3 {
                    // Same significance and sign either way: the magnitudes decide, and
                    // with a Rice parameter they often cost the same.
                    let (e_hi, e_lo) = (err(mh), err(mh - 1));
                    let pick = if (mh - 1) >> kr == (mh - 2) >> kr {
                        mh
                    } else {
                        let r_hi = m.magnitude(set, kr, mh - 1, false);
                        let r_lo = m.magnitude(set, kr, mh - 2, false);
                        if e_lo + lambda * r_lo < e_hi + lambda * r_hi {
                            mh - 1
                        } else {
                            mh
                        }
                    };
                    j_coded += if pick == mh { e_hi } else { e_lo };
                    pick
                } else {
                    let mut best = (f32::INFINITY, 0u32);
                    let sig_bits = [m.cost(sc, false), m.cost(sc, true)];
                    let sign_bits = m.cost(sign_ctx, d < 0);
                    for c in (0..=mh).rev() {
                        if c == 0 && inferred {
                            continue;
                        }
                        let mut bits = if inferred {
                            0.0
                        } else {
                            sig_bits[(c != 0) as usize]
                        };
                        if c != 0 {
                            bits += sign_bits + m.magnitude(set, kr, c - 1, false);
                        }
                        let jc = err(c) + lambda * bits;
                        if jc < best.0 {
                            best = (jc, c);
                        }
                    }
                    // The coded bits are counted below.
                    j_coded += err(best.1);
                    best.1
                };
                if !inferred {
                    j_coded += lambda * m.code(sc, cand != 0);
                }
                if cand == 0 {
                    continue;
                }
                let v = if d < 0 { -(cand as i32) } else { cand as i32 };
                q[k] = v;
                count += 1;
                if !seen {
                    // Counted as coded (hiding, which needs 8 nonzeros, is not foreseen);
                    // it reads as + until the block ends.
                    first = Some((i, j, v, sign_ctx));
                    j_coded += lambda * m.cost(sign_ctx, d < 0);
                    rec.set(i, j, cand as i32);
                } else {
                    j_coded += lambda * m.code(sign_ctx, d < 0);
                    rec.set(i, j, v);
                }
                seen = true;
                j_coded += lambda * m.magnitude(set, kr, cand - 1, true);
            }
            if let Some((i, j, v, sign_ctx)) = first {
                if count < HIDDEN_SIGN_MIN {
                    m.code(sign_ctx, v < 0);
                }
                rec.set(i, j, v);
            }
            if !seen || j_empty <= j_coded {
                m.rollback(mark);
                for &(k, i, j) in &cells[..nc] {
                    q[k] = 0;
                    rec.set(i, j, 0);
                }
                total_j += f64::from(j_empty);
                continue;
            }
            block_sig[by * nb + bx] = true;
            total_j += f64::from(j_coded);
            for (c, &(k, _, _)) in cells[..nc].iter().enumerate() {
                block_q[c] = q[k];
                block_d[c] = details[k];
            }
            fix_parity(&mut block_q[..nc], &block_d[..nc]);
            for (c, &(k, i, j)) in cells[..nc].iter().enumerate() {
                q[k] = block_q[c];
                rec.set(i, j, block_q[c]);
            }
        }
    }
    let coded = total_j + f64::from(lambda * m.cost(NONZERO, true));
    let empty = zero_j + f64::from(lambda * m.cost(NONZERO, false));
    if empty <= coded {
        q.iter_mut().for_each(|x| *x = 0);
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use super::*;
    use crate::encode::{Quantizer, fix_parity, quantize_pruned};
    use crate::entropy::{ContextCounts, ModelDecoder, ModelEncoder, read_matrix, write_matrix};

    struct Rng(u64);

    impl Rng {
        fn next(&mut self) -> u64 {
            self.0 = self
                .0
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            self.0 >> 33
        }
    }

    /// Laplacian-like details with smooth regions: most small, a few large.
    fn details(rng: &mut Rng, n: usize, scale: f64) -> Vec<i32> {
        (0..n * n)
            .map(|k| {
                let (i, j) = (k / n, k % n);
                let u = (rng.next() % 1_000_000) as f64 / 1_000_000.0 + 1e-9;
                let sign = if rng.next().is_multiple_of(2) {
                    -1.0
                } else {
                    1.0
                };
                let local = if (i / 8 + j / 8) % 3 == 0 { 4.0 } else { 1.0 };
                (sign * -u.ln() * scale * local).round() as i32
            })
            .collect()
    }

    fn nearest(d: i32, s: u32) -> i64 {
        (i64::from(d.unsigned_abs()) * 256 + i64::from(s / 2)) / i64::from(s)
    }

    fn code(model: &CodecModel, n: usize, q: &[i32], valid: Option<&[bool]>) -> Vec<u8> {
        let mut e = ModelEncoder::new(model);
        write_matrix(&mut e, 1, n, q, valid, true);
        e.finish()
    }

    #[test]
    fn indices_decode_exactly_keep_their_signs_and_stay_near_the_details() {
        let model = CodecModel::default();
        let mut rng = Rng(11);
        for round in 0..120 {
            let n = [4usize, 16, 32][round % 3];
            let s = [257u32, 300, 700, 2560, 25_600][round % 5];
            let scale = [0.5, 2.0, 8.0, 40.0][round % 4] * f64::from(s) / 256.0;
            let valid: Option<Vec<bool>> =
                (round % 4 == 1).then(|| (0..n * n).map(|k| (k * 7 + round) % 5 != 0).collect());
            let mut d = details(&mut rng, n, scale);
            if round == 7 {
                d[0] = i32::MIN;
                d[1] = i32::MAX;
            }
            if let Some(v) = &valid {
                d.iter_mut().zip(v).for_each(|(x, &ok)| *x *= i32::from(ok));
            }
            let matrix = Matrix {
                group: 1,
                n,
                valid: valid.as_deref(),
                step: s,
                lambda: 0.1 * (s as f32 / 256.0).powi(2),
            };
            let mut q = vec![0; n * n];
            quantize_matrix(&model, &matrix, &d, &mut q, |b, bd| fix_parity(b, bd, s));
            for (k, (&x, &v)) in d.iter().zip(&q).enumerate() {
                assert!(
                    v == 0 || v.signum() == x.signum(),
                    "round {round} cell {k}: {x} -> {v}"
                );
                let (m, near) = (i64::from(v.unsigned_abs()), nearest(x, s));
                // Nearest, one less or zero, then at most one parity move.
                assert!(
                    m <= near + 1 && (m == 0 || m + 2 >= near),
                    "round {round}: {x} -> {v}"
                );
                if valid.as_ref().is_some_and(|vs| !vs[k]) {
                    assert_eq!(v, 0);
                }
            }
            // The sign-hiding rule holds in every block: decoding gives the indices back.
            let bytes = code(&model, n, &q, valid.as_deref());
            let mut dec = ModelDecoder::new(&model, &bytes);
            let mut back = vec![7; n * n];
            read_matrix(&mut dec, 1, n, &mut back, valid.as_deref(), true).unwrap();
            assert_eq!(back, q, "round {round}");
        }
    }

    #[test]
    fn identity_at_the_lossless_step() {
        let d = vec![
            5,
            -3,
            0,
            i32::MIN,
            i32::MAX,
            1,
            2,
            3,
            4,
            5,
            6,
            7,
            8,
            9,
            10,
            11,
        ];
        let mut q = vec![0; 16];
        let matrix = Matrix {
            group: 0,
            n: 4,
            valid: None,
            step: 256,
            lambda: 0.1,
        };
        quantize_matrix(&CodecModel::default(), &matrix, &d, &mut q, |_, _| {});
        assert_eq!(q, d);
    }

    /// Against rounding (pruned, sign hiding) under the same trained model: less squared
    /// error plus lambda times the real coded bits, summed over many matrices, at sparse
    /// and dense scales. (On independent synthetic details the margin is small, 0.02-0.3 %:
    /// rounding with its offset and pruning is close to the best single choices; real
    /// data gains more through the contexts, see `codec/tests/real_data.rs`.)
    #[test]
    fn costs_less_than_rounding_in_error_plus_weighted_bits() {
        let (n, s) = (32usize, 2048u32);
        let lambda = 0.1 * (s as f32 / 256.0).powi(2);
        let quantizer = Quantizer::new(s, 112);
        for scale in [1.0, 2.0, 8.0, 24.0] {
            let mut rng = Rng(3);
            let all: Vec<Vec<i32>> = (0..60).map(|_| details(&mut rng, n, scale)).collect();
            let plain: Vec<Vec<i32>> = all
                .iter()
                .map(|d| {
                    let mut q = d.clone();
                    quantize_pruned(n, &mut q, &quantizer, s);
                    q
                })
                .collect();
            let mut counts = ContextCounts::default();
            for q in &plain {
                write_matrix(&mut counts, 1, n, q, None, true);
            }
            let model = CodecModel::from_counts(&counts);
            let matrix = Matrix {
                group: 1,
                n,
                valid: None,
                step: s,
                lambda,
            };
            let cost = |d: &[i32], q: &[i32]| -> f64 {
                let err: f64 = d
                    .iter()
                    .zip(q)
                    .map(|(&x, &v)| (f64::from(x) - f64::from(dequantize(v, s))).powi(2))
                    .sum();
                err + f64::from(lambda) * 8.0 * code(&model, n, q, None).len() as f64
            };
            let (mut j_plain, mut j_rdo) = (0.0, 0.0);
            for (d, p) in all.iter().zip(&plain) {
                let mut q = vec![0; n * n];
                quantize_matrix(&model, &matrix, d, &mut q, |b, bd| fix_parity(b, bd, s));
                j_plain += cost(d, p);
                j_rdo += cost(d, &q);
            }
            assert!(
                j_rdo < j_plain,
                "scale {scale}: rdo {j_rdo} against rounding {j_plain}"
            );
        }
    }
}
