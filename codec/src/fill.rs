//! Smooth filling of nodata samples (push-pull), so holes create no spikes or cliffs.
//!
//! Valid samples are averaged down a pyramid of half-resolution levels; holes are then
//! filled from the coarser level by bilinear interpolation, coarse to fine. Filled values
//! are smooth continuations of their surroundings, which also makes them cheap to code.

use std::collections::HashMap;

use rayon::prelude::*;

/// Fills `values[k]` where `valid[k]` is false. Returns `false` if no sample is valid.
/// Rows are processed in parallel; the result does not depend on the thread count (each
/// pyramid cell sums its inputs in the same order).
pub fn push_pull(width: usize, height: usize, values: &mut [f64], valid: &[bool]) -> bool {
    match holes(width, height, values, valid) {
        Holes::NoData => false,
        Holes::None => true,
        Holes::Some(filler) => {
            filler.write(values, valid, |v| v);
            true
        }
    }
}

/// Writes `map(fill)` into `out[k]` for every `k` with `valid[k]` false, the fills of
/// [`push_pull`] computed from `values` (read at valid samples only). Returns `false`
/// (writing nothing) if no sample is valid.
pub(crate) fn fill_into<T: Send>(
    width: usize,
    height: usize,
    values: &[f64],
    valid: &[bool],
    out: &mut [T],
    map: impl Fn(f64) -> T + Sync,
) -> bool {
    match holes(width, height, values, valid) {
        Holes::NoData => false,
        Holes::None => true,
        Holes::Some(filler) => {
            filler.write(out, valid, map);
            true
        }
    }
}

/// What [`holes`] found.
enum Holes {
    /// No sample is valid.
    NoData,
    /// Every sample is valid.
    None,
    /// Some samples need filling, from this.
    Some(Filler),
}

/// The fill values of an image's holes: the filled half-resolution level of the push-pull
/// pyramid (bilinear interpolation gives each hole's value), or, for sparse holes, the
/// values themselves.
enum Filler {
    /// The whole pyramid was built.
    Pyramid {
        /// Image width.
        width: usize,
        /// Filled level 1.
        coarse: Vec<f64>,
        /// Its dimensions.
        dims: (usize, usize),
    },
    /// `(index, value)` of every hole, computed locally.
    Listed(Vec<(usize, f64)>),
}

impl Filler {
    /// Writes `map(fill)` into `out[k]` for every `k` with `valid[k]` false.
    fn write<T: Send>(&self, out: &mut [T], valid: &[bool], map: impl Fn(f64) -> T + Sync) {
        match self {
            Filler::Pyramid {
                width,
                coarse,
                dims,
            } => out
                .par_chunks_mut(*width)
                .zip(valid.par_chunks(*width))
                .enumerate()
                .for_each(|(y, (row, ok))| {
                    for (x, (o, &ok)) in row.iter_mut().zip(ok).enumerate() {
                        if !ok {
                            *o = map(sample_bilinear(
                                |i, j| coarse[j * dims.0 + i],
                                *dims,
                                half_position(x),
                                half_position(y),
                            ));
                        }
                    }
                }),
            Filler::Listed(fills) => {
                for &(k, v) in fills {
                    out[k] = map(v);
                }
            }
        }
    }
}

/// Push-pull evaluated only where holes need it: the same sums, in the same order, and the
/// same interpolations as the whole pyramid, so the fills are bit for bit the same. Each
/// pyramid cell a hole depends on is computed once (memoised per level).
struct Local<'a> {
    values: &'a [f64],
    valid: &'a [bool],
    /// Dimensions of every level, level 0 = the image.
    dims: Vec<(usize, usize)>,
    sums: Vec<HashMap<usize, (f64, f64)>>,
    filled: Vec<HashMap<usize, f64>>,
}

impl Local<'_> {
    /// `(weighted sum, weight)` of cell `(x, y)` of level `k`.
    fn sum(&mut self, k: usize, x: usize, y: usize) -> (f64, f64) {
        let (w, _) = self.dims[k];
        if k == 0 {
            let i = y * w + x;
            return if self.valid[i] {
                (self.values[i], 1.0)
            } else {
                (0.0, 0.0)
            };
        }
        if let Some(&v) = self.sums[k].get(&(y * w + x)) {
            return v;
        }
        let (fw, fh) = self.dims[k - 1];
        let (mut s, mut wt) = (0.0, 0.0);
        for yy in 2 * y..(2 * y + 2).min(fh) {
            for xx in 2 * x..(2 * x + 2).min(fw) {
                let (a, b) = self.sum(k - 1, xx, yy);
                s += a;
                wt += b;
            }
        }
        self.sums[k].insert(y * w + x, (s, wt));
        (s, wt)
    }

    /// Filled value of cell `(x, y)` of level `k >= 1`.
    fn value(&mut self, k: usize, x: usize, y: usize) -> f64 {
        let (w, _) = self.dims[k];
        if let Some(&v) = self.filled[k].get(&(y * w + x)) {
            return v;
        }
        let (s, wt) = self.sum(k, x, y);
        let v = if wt > 0.0 || k + 1 == self.dims.len() {
            s / wt
        } else {
            self.interpolate(k + 1, x, y)
        };
        self.filled[k].insert(y * w + x, v);
        v
    }

    /// Bilinear value at the centre of cell `(x, y)` of level `k - 1`, from level `k`.
    fn interpolate(&mut self, k: usize, x: usize, y: usize) -> f64 {
        let (x0, y0, x1, y1, fx, fy) =
            bilinear_corners(self.dims[k], half_position(x), half_position(y));
        let corners = [
            self.value(k, x0, y0),
            self.value(k, x1, y0),
            self.value(k, x0, y1),
            self.value(k, x1, y1),
        ];
        blend(corners, fx, fy)
    }
}

/// Holes at most this fraction of the image are filled locally ([`Local`]).
const LOCAL_FRACTION: usize = 64;

/// The push-pull pyramid of `values` (read at valid samples only): valid samples are
/// averaged down half-resolution levels, then each level is filled coarse to fine.
fn holes(width: usize, height: usize, values: &[f64], valid: &[bool]) -> Holes {
    let invalid = valid.par_iter().filter(|&&v| !v).count();
    if invalid == valid.len() {
        return Holes::NoData;
    }
    if invalid == 0 {
        return Holes::None;
    }
    Holes::Some(if invalid * LOCAL_FRACTION <= valid.len() {
        local_fills(width, height, values, valid)
    } else {
        pyramid(width, height, values, valid)
    })
}

/// The fills of every hole, computed by [`Local`].
fn local_fills(width: usize, height: usize, values: &[f64], valid: &[bool]) -> Filler {
    let mut dims = vec![(width, height)];
    while dims[dims.len() - 1] != (1, 1) {
        let (w, h) = dims[dims.len() - 1];
        dims.push((w.div_ceil(2), h.div_ceil(2)));
    }
    let levels = dims.len();
    let mut local = Local {
        values,
        valid,
        dims,
        sums: vec![HashMap::new(); levels],
        filled: vec![HashMap::new(); levels],
    };
    let fills = (0..valid.len())
        .filter(|&k| !valid[k])
        .map(|k| (k, local.interpolate(1, k % width, k / width)))
        .collect();
    Filler::Listed(fills)
}

/// The whole push-pull pyramid (at least one sample valid, at least one not).
fn pyramid(width: usize, height: usize, values: &[f64], valid: &[bool]) -> Filler {
    // Pyramid of (weighted sum, weight), starting at half resolution.
    let mut levels: Vec<(usize, usize, Vec<f64>, Vec<f64>)> = Vec::new();
    levels.push(halve(width, height, |k| {
        if valid[k] {
            (values[k], 1.0)
        } else {
            (0.0, 0.0)
        }
    }));
    while levels[levels.len() - 1].0 > 1 || levels[levels.len() - 1].1 > 1 {
        let (w, h, s, wt) = &levels[levels.len() - 1];
        let next = halve(*w, *h, |k| (s[k], wt[k]));
        levels.push(next);
    }
    // Coarse to fine: a level's value is its mean where it has weight, else the
    // bilinear interpolation of the (already filled) coarser level.
    let mut coarse: Vec<f64> = Vec::new();
    let mut coarse_dims = (0usize, 0usize);
    for (w, h, s, wt) in levels.iter().rev() {
        let mut out = vec![0.0; w * h];
        out.par_chunks_mut(*w).enumerate().for_each(|(y, row)| {
            for (x, o) in row.iter_mut().enumerate() {
                let k = y * w + x;
                *o = if wt[k] > 0.0 {
                    s[k] / wt[k]
                } else {
                    sample_bilinear(
                        |i, j| coarse[j * coarse_dims.0 + i],
                        coarse_dims,
                        half_position(x),
                        half_position(y),
                    )
                };
            }
        });
        coarse = out;
        coarse_dims = (*w, *h);
    }
    Filler::Pyramid {
        width,
        coarse,
        dims: coarse_dims,
    }
}

/// Position on the half-resolution level of the centre of sample `x`.
fn half_position(x: usize) -> f64 {
    (x as f64 + 0.5) / 2.0 - 0.5
}

/// One pyramid step: the `(sum, weight)` of each 2x2 block of a `w x h` level whose
/// entry `k` is `at(k)`, summed row by row.
fn halve(
    w: usize,
    h: usize,
    at: impl Fn(usize) -> (f64, f64) + Sync,
) -> (usize, usize, Vec<f64>, Vec<f64>) {
    let (w2, h2) = (w.div_ceil(2), h.div_ceil(2));
    let mut s2 = vec![0.0; w2 * h2];
    let mut wt2 = vec![0.0; w2 * h2];
    s2.par_chunks_mut(w2)
        .zip(wt2.par_chunks_mut(w2))
        .enumerate()
        .for_each(|(y2, (srow, wrow))| {
            for y in 2 * y2..(2 * y2 + 2).min(h) {
                for x in 0..w {
                    let (v, weight) = at(y * w + x);
                    srow[x / 2] += v;
                    wrow[x / 2] += weight;
                }
            }
        });
    (w2, h2, s2, wt2)
}

/// The corners and weights of a bilinear sample at `(x, y)` of a `w x h` image (clamped
/// to the image): `(x0, y0, x1, y1, fx, fy)`.
fn bilinear_corners(
    (w, h): (usize, usize),
    x: f64,
    y: f64,
) -> (usize, usize, usize, usize, f64, f64) {
    let x = x.clamp(0.0, (w - 1) as f64);
    let y = y.clamp(0.0, (h - 1) as f64);
    let (x0, y0) = (x.floor() as usize, y.floor() as usize);
    let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
    (x0, y0, x1, y1, x - x0 as f64, y - y0 as f64)
}

/// Bilinear sample at `(x, y)` of a `dims` image whose pixel `(i, j)` is `img(i, j)`.
fn sample_bilinear(img: impl Fn(usize, usize) -> f64, dims: (usize, usize), x: f64, y: f64) -> f64 {
    let (x0, y0, x1, y1, fx, fy) = bilinear_corners(dims, x, y);
    blend([img(x0, y0), img(x1, y0), img(x0, y1), img(x1, y1)], fx, fy)
}

/// Bilinear blend of corners `[(x0, y0), (x1, y0), (x0, y1), (x1, y1)]`.
fn blend([c00, c10, c01, c11]: [f64; 4], fx: f64, fy: f64) -> f64 {
    let top = c00 * (1.0 - fx) + c10 * fx;
    let bottom = c01 * (1.0 - fx) + c11 * fx;
    top * (1.0 - fy) + bottom * fy
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use super::*;

    #[test]
    fn holes_are_filled_within_the_range_of_their_surroundings() {
        let (w, h) = (40, 30);
        let mut v: Vec<f64> = (0..w * h)
            .map(|k| (k % w) as f64 * 2.0 + (k / w) as f64)
            .collect();
        let valid: Vec<bool> = (0..w * h)
            .map(|k| !((10..20).contains(&(k % w)) && (5..15).contains(&(k / w))))
            .collect();
        for (k, x) in v.iter_mut().enumerate() {
            if !valid[k] {
                *x = -32768.0;
            }
        }
        assert!(push_pull(w, h, &mut v, &valid));
        for &x in &v {
            assert!((0.0..=120.0).contains(&x), "{x}");
        }
    }

    #[test]
    fn local_fills_equal_the_whole_pyramid_bit_for_bit() {
        // Odd sizes (clamped borders, odd last cells), single holes, a hole at a corner,
        // a wide hole that needs coarse levels, and holes along the image border.
        for (w, h) in [(37, 23), (64, 64), (5, 1), (1, 9), (130, 67)] {
            let values: Vec<f64> = (0..w * h)
                .map(|k| ((k * 7919) % 1013) as f64 * 0.37 - 100.0)
                .collect();
            let valid: Vec<bool> = (0..w * h)
                .map(|k| {
                    let (x, y) = (k % w, k / w);
                    !(k % 17 == 3
                        || (x, y) == (0, 0)
                        || (x + 1 == w && y + 1 == h)
                        || (x >= w / 3 && x < w / 3 + 9 && y >= h / 4 && y < h / 4 + 6))
                })
                .collect();
            if valid.iter().all(|&v| v) || !valid.iter().any(|&v| v) {
                continue;
            }
            let mut a = vec![f64::NAN; w * h];
            let mut b = vec![f64::NAN; w * h];
            local_fills(w, h, &values, &valid).write(&mut a, &valid, |v| v);
            pyramid(w, h, &values, &valid).write(&mut b, &valid, |v| v);
            for k in 0..w * h {
                assert_eq!(a[k].to_bits(), b[k].to_bits(), "{w}x{h} sample {k}");
                assert_eq!(a[k].is_nan(), valid[k], "{w}x{h} sample {k}");
            }
        }
    }
}
