//! Strided reads and writes of one diamond's lattice in a raster: the index arithmetic
//! shared by the whole-raster transforms and the planet's slots.

/// The raster range holding `count` entries `base + j step` (`j = 0..count`), as
/// `(first, last)` indices in ascending order.
pub fn strided_span(base: isize, step: isize, count: usize) -> (usize, usize) {
    let end = base + (count as isize - 1) * step;
    (base.min(end) as usize, base.max(end) as usize)
}

/// The `m x m` sub-grid at `(o, o)` of a diamond's `w x w` lattice (buffer index
/// `i w + j`), whose point `(i, j)` is raster index `base + i si + j sj`.
///
/// [`Lattice::lines`] walks it along the lattice direction with the shortest raster
/// step. For a diamond rotated 45 degrees in the raster that is a diagonal of the
/// lattice, which runs along a raster row: its points are 2 (or 2^k) samples apart
/// instead of a raster row, so the accesses stream through cache lines and pages
/// instead of touching a new page per sample (korea RMS 9 m decoding went from 80 to
/// 89-93 M samples/s; docs/codec.md).
pub struct Lattice {
    m: usize,
    o: usize,
    w: usize,
    base: isize,
    si: isize,
    sj: isize,
}

impl Lattice {
    /// The `m x m` sub-grid at `(o, o)` of a `w x w` lattice at raster index
    /// `base + i si + j sj`.
    pub fn new(m: usize, o: usize, w: usize, base: isize, si: isize, sj: isize) -> Self {
        Lattice {
            m,
            o,
            w,
            base,
            si,
            sj,
        }
    }

    /// Calls `line(raster_start, raster_step, buffer_start, buffer_step, len)` for lines
    /// covering the sub-grid exactly once.
    pub fn lines(&self, mut line: impl FnMut(isize, isize, usize, usize, usize)) {
        let (m, w) = (self.m, self.w);
        if m == 0 {
            return;
        }
        let mut at = |i: usize, j: usize, rs: isize, bs: usize, len: usize| {
            let (i, j) = (self.o + i, self.o + j);
            line(
                self.base + i as isize * self.si + j as isize * self.sj,
                rs,
                i * w + j,
                bs,
                len,
            );
        };
        let (si, sj) = (self.si, self.sj);
        let steps = [sj, si, si + sj, si - sj].map(isize::unsigned_abs);
        let best = (0..4).min_by_key(|&k| steps[k]).unwrap_or(0);
        match best {
            0 => (0..m).for_each(|i| at(i, 0, sj, 1, m)),
            1 => (0..m).for_each(|j| at(0, j, si, w, m)),
            2 => {
                // Lines of constant j - i, from the corner (m - 1, 0) to (0, m - 1).
                for i in (1..m).rev() {
                    at(i, 0, si + sj, w + 1, m - i);
                }
                for j in 0..m {
                    at(0, j, si + sj, w + 1, m - j);
                }
            }
            _ => {
                // Lines of constant i + j, stepping (i + 1, j - 1).
                for j in 0..m {
                    at(0, j, si - sj, w - 1, j + 1);
                }
                for i in 1..m {
                    at(i, m - 1, si - sj, w - 1, m - i);
                }
            }
        }
    }
}

impl Lattice {
    /// Lowest and highest raster index of the sub-grid.
    pub fn span(&self) -> (isize, isize) {
        let e = self.m.saturating_sub(1) as isize;
        let b = self.base + self.o as isize * (self.si + self.sj);
        let c = [
            b,
            b + e * self.si,
            b + e * self.sj,
            b + e * (self.si + self.sj),
        ];
        (
            c.iter().copied().min().unwrap_or(b),
            c.iter().copied().max().unwrap_or(b),
        )
    }

    /// Writes the sub-grid of `buf` to the raster, as far as it falls in `part` (raster
    /// indices `start..start + part.len()`).
    pub fn write_part(&self, buf: &[i32], part: &mut [i32], start: usize) {
        let (lo, hi) = self.span();
        let (start, end) = (start as isize, (start + part.len()) as isize);
        if hi < start || lo >= end {
            return;
        }
        if lo >= start && hi < end {
            self.lines(|r, rs, b, bs, len| write_line(part, r - start, rs, buf, b, bs, len));
        } else {
            self.lines(|r, rs, b, bs, len| {
                let (t0, t1) = clip_line(r, rs, len, start, end);
                if t0 < t1 {
                    let r = r + t0 as isize * rs - start;
                    write_line(part, r, rs, buf, b + t0 * bs, bs, t1 - t0);
                }
            });
        }
    }
}

/// Reads the `side x side` lattice whose point `(i, j)` is `raster[base + i si + j sj]`
/// into `out` (row-major), walking the shortest raster step ([`Lattice`]).
pub fn read_lattice(
    raster: &[i32],
    side: usize,
    base: isize,
    si: isize,
    sj: isize,
    out: &mut [i32],
) {
    Lattice::new(side, 0, side, base, si, sj)
        .lines(|r, rs, b, bs, len| read_line(raster, r, rs, out, b, bs, len));
}

/// Writes rows and columns `margin..side - margin` of the `side x side` grid `v` back to
/// the lattice of [`read_lattice`], as far as it falls in `part`, the raster entries from
/// index `start` (the whole raster: `start` 0).
#[allow(clippy::too_many_arguments)]
pub fn write_lattice(
    part: &mut [i32],
    start: usize,
    side: usize,
    margin: usize,
    base: isize,
    si: isize,
    sj: isize,
    v: &[i32],
) {
    Lattice::new(side - 2 * margin, margin, side, base, si, sj).write_part(v, part, start);
}

/// The range `t0..t1` of `t < len` with `start <= base + t step < end`.
fn clip_line(base: isize, step: isize, len: usize, start: isize, end: isize) -> (usize, usize) {
    let len = len as isize;
    let (lo, hi) = match step.signum() {
        0 if (start..end).contains(&base) => (0, len),
        0 => (0, 0),
        // ceil((start - base) / step) ..= floor((end - 1 - base) / step)
        1 => (
            -(base - start).div_euclid(step),
            (end - 1 - base).div_euclid(step) + 1,
        ),
        _ => (
            -(end - 1 - base).div_euclid(-step),
            (base - start).div_euclid(-step) + 1,
        ),
    };
    let (lo, hi) = (lo.clamp(0, len), hi.clamp(0, len));
    (lo as usize, hi.max(lo) as usize)
}

/// `buf[b0 + t bstep] = raster[base + t step]` for `t < len`: the raster bounds are
/// checked once per line (plain index loops: `step_by` divides to find its length, which
/// costs more than the copy on the short diagonal lines).
fn read_line(
    raster: &[i32],
    base: isize,
    step: isize,
    buf: &mut [i32],
    b0: usize,
    bstep: usize,
    len: usize,
) {
    if len == 0 {
        return;
    }
    let (lo, hi) = strided_span(base, step, len);
    let span = &raster[lo..=hi];
    let out = &mut buf[b0..=b0 + (len - 1) * bstep];
    let mut r = base - lo as isize;
    for t in 0..len {
        out[t * bstep] = span[r as usize];
        r += step;
    }
}

/// `raster[base + t step] = buf[b0 + t bstep]` for `t < len`.
fn write_line(
    raster: &mut [i32],
    base: isize,
    step: isize,
    buf: &[i32],
    b0: usize,
    bstep: usize,
    len: usize,
) {
    if len == 0 {
        return;
    }
    let (lo, hi) = strided_span(base, step, len);
    let span = &mut raster[lo..=hi];
    let src = &buf[b0..=b0 + (len - 1) * bstep];
    let mut r = base - lo as isize;
    for t in 0..len {
        span[r as usize] = src[t * bstep];
        r += step;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lattice_lines_cover_each_point_once_in_every_orientation() {
        let w_raster = 1000isize;
        // Axis-aligned, transposed and both 45-degree rotations, at several spacings.
        for (si, sj) in [
            (w_raster, 1),
            (1, w_raster),
            (2 * w_raster, -2),
            (w_raster + 1, -w_raster + 1),
            (w_raster + 1, w_raster - 1),
            (-w_raster - 1, w_raster - 1),
            (2 * w_raster - 2, -2 * w_raster - 2),
        ] {
            for (m, o, w) in [(33, 0, 33), (32, 0, 32), (31, 1, 33), (1, 0, 1), (2, 0, 2)] {
                let base = 400 * w_raster + 400;
                let mut seen = Vec::new();
                Lattice::new(m, o, w, base, si, sj).lines(|r, rs, b, bs, len| {
                    for t in 0..len {
                        seen.push((r + t as isize * rs, b + t * bs));
                    }
                });
                let mut want: Vec<(isize, usize)> = (o..o + m)
                    .flat_map(|i| {
                        (o..o + m)
                            .map(move |j| (base + i as isize * si + j as isize * sj, i * w + j))
                    })
                    .collect();
                seen.sort_unstable();
                want.sort_unstable();
                assert_eq!(seen, want, "si {si} sj {sj} m {m} o {o}");
                // Written part by part (cut anywhere), the raster is what one write gives.
                let lat = Lattice::new(m, o, w, base, si, sj);
                let buf: Vec<i32> = (0..(w * w) as i32).map(|x| x + 1).collect();
                let len = (1000 * w_raster) as usize;
                let mut whole = vec![0; len];
                lat.write_part(&buf, &mut whole, 0);
                for part_len in [1usize, 7, 999, 1000, 4093, 65536] {
                    let mut parts = vec![0; len];
                    for (p, part) in parts.chunks_mut(part_len).enumerate() {
                        lat.write_part(&buf, part, p * part_len);
                    }
                    assert!(parts == whole, "si {si} sj {sj} m {m} parts of {part_len}");
                }
                let (lo, hi) = lat.span();
                assert_eq!(whole.iter().position(|&x| x != 0), usize::try_from(lo).ok());
                assert_eq!(
                    whole.iter().rposition(|&x| x != 0),
                    usize::try_from(hi).ok()
                );
            }
        }
    }
}
