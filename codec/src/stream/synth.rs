//! Out-of-core synthesis of planar rasters: the streaming encoder's octave chain run
//! backwards, coarse to fine, so a raster is decoded a band of rows at a time in bounded
//! memory (the RMS rate control's verification decodes out of core).
//!
//! Octave `o` receives the rows of `R_{o+1}` (the even rows and columns of `R_o`), runs
//! level `B` (axis-aligned, band `j` spans rows `2Nj ..= 2N(j+1)` of `R_o`) as soon as its
//! rows are in, then level `A` (rotated, group `g` spans rows `gN - N ..= gN + N`) once
//! the `B` bands it reads are done, and hands the rows no later diamond changes to octave
//! `o - 1` (or, for `o = 0`, to the caller). Within a level no diamond touches another's
//! changed points, so this order gives the in-memory synthesis' values bit for bit.

use rayon::prelude::*;

use super::{Frame, octave_groups};
use crate::encode::EncodeError;
use crate::lifting;
use crate::raster::RasterGeometry;

/// Diamonds synthesised at once (in parallel).
const BATCH: usize = 16;

/// Fills diamond `(level, index)`'s dequantised details; whether any is nonzero.
pub(crate) type Details<'a> =
    dyn Fn(usize, usize, &mut [i32]) -> Result<bool, EncodeError> + Sync + 'a;

/// One synthesised diamond: `(level, index, coarse vertices, fine vertices, cells)`.
pub(crate) type Synthesised<'a> = (usize, usize, &'a [i32], &'a [i32], &'a [i32]);

/// A diamond synthesised in a batch: coarse vertices, fine vertices, cells, whether it
/// had details.
type Done = (Vec<i32>, Vec<i32>, Vec<i32>, bool);

/// One octave of the backwards chain (see the module docs).
struct SynthOctave {
    width: usize,
    height: usize,
    shift: u32,
    level_a: usize,
    level_b: usize,
    a_groups: Vec<Vec<usize>>,
    b_groups: Vec<Vec<usize>>,
    next_a: usize,
    next_b: usize,
    /// Rows `base .. base + rows.len() / width` of `R_o`.
    rows: Vec<i32>,
    base: usize,
    next_emit: usize,
    /// Rows of `R_{o+1}` received.
    received: usize,
}

impl SynthOctave {
    fn loaded(&self) -> usize {
        self.base + self.rows.len() / self.width
    }

    /// Appends row `m` of `R_{o+1}` as row `2m` of `R_o` (and the odd row before it).
    fn push(&mut self, coarse: &[i32]) {
        let w = self.width;
        if self.received > 0 {
            self.rows.resize(self.rows.len() + w, 0);
        }
        let start = self.rows.len();
        self.rows.resize(start + w, 0);
        for (x, &v) in coarse.iter().enumerate() {
            if 2 * x < w {
                self.rows[start + 2 * x] = v;
            }
        }
        self.received += 1;
        // An even height ends with an odd row that no coarse row precedes.
        if self.loaded() + 1 == self.height {
            self.rows.resize(self.rows.len() + w, 0);
        }
    }

    /// Runs every diamond whose rows are in, emitting the rows no later diamond changes.
    fn advance(
        &mut self,
        geom: &RasterGeometry,
        details: &Details<'_>,
        visit: &mut dyn FnMut(Synthesised<'_>),
        emit: &mut dyn FnMut(&[i32]) -> Result<(), EncodeError>,
    ) -> Result<(), EncodeError> {
        let n = geom.n();
        loop {
            if self.next_b < self.b_groups.len() {
                let j = self.next_b;
                if self.loaded() >= (2 * n * (j + 1) + 1).min(self.height) {
                    let group = std::mem::take(&mut self.b_groups[j]);
                    self.run(geom, self.level_b, &group, details, visit)?;
                    self.b_groups[j] = group;
                    self.next_b += 1;
                    continue;
                }
            }
            if self.next_a < self.a_groups.len() {
                let g = self.next_a;
                // The B bands meeting rows up to gN + N.
                let bands = (g + 1).div_ceil(2).min(self.b_groups.len());
                let rows = (n * (g + 1) + 1).min(self.height);
                if self.next_b >= bands && self.loaded() >= rows {
                    let group = std::mem::take(&mut self.a_groups[g]);
                    self.run(geom, self.level_a, &group, details, visit)?;
                    self.a_groups[g] = group;
                    self.next_a += 1;
                    continue;
                }
            }
            break;
        }
        // Rows no later B band (rows > 2N next_b) or A group (rows > next_a N - N) changes.
        let mut end = self.loaded();
        if self.next_b < self.b_groups.len() {
            end = end.min(2 * n * self.next_b + 1);
        }
        if self.next_a < self.a_groups.len() {
            end = end.min((n * self.next_a + 1).saturating_sub(n));
        }
        while self.next_emit < end {
            let start = (self.next_emit - self.base) * self.width;
            emit(&self.rows[start..start + self.width])?;
            self.next_emit += 1;
        }
        // Keep what the next B band, the next A group and the next emit read.
        let mut keep = self.next_emit;
        if self.next_b < self.b_groups.len() {
            keep = keep.min(2 * n * self.next_b);
        }
        if self.next_a < self.a_groups.len() {
            keep = keep.min((n * self.next_a).saturating_sub(n));
        }
        if keep > self.base {
            self.rows.drain(..(keep - self.base) * self.width);
            self.base = keep;
        }
        Ok(())
    }

    fn done(&self) -> bool {
        self.next_a == self.a_groups.len()
            && self.next_b == self.b_groups.len()
            && self.next_emit == self.height
    }

    fn run(
        &mut self,
        geom: &RasterGeometry,
        level: usize,
        group: &[usize],
        details: &Details<'_>,
        visit: &mut dyn FnMut(Synthesised<'_>),
    ) -> Result<(), EncodeError> {
        let n = geom.n();
        let slots = geom.level(level);
        for batch in group.chunks(BATCH) {
            let (rows, base, width, shift) = (&self.rows, self.base, self.width, self.shift);
            let done: Vec<Done> = batch
                .par_iter()
                .map(|&i| {
                    let s = &slots[i];
                    let mask = s.mask.as_ref();
                    let mut h = vec![0; n * n];
                    let has = details(level, i, &mut h)?;
                    let mut v = vec![0; (n + 1) * (n + 1)];
                    let mut c = vec![0; n * n];
                    Frame::of(s, shift).gather_vertices(n, mask, rows, base, width, &mut v);
                    let coarse = v.clone();
                    if has {
                        lifting::synthesize(n, &mut v, &h, &mut c, mask);
                    } else {
                        lifting::synthesize_zero(n, &v, &mut c, mask);
                    }
                    Ok((coarse, v, c, has))
                })
                .collect::<Result<_, EncodeError>>()?;
            for (&i, (coarse, v, c, has)) in batch.iter().zip(&done) {
                let s = &slots[i];
                let f = Frame::of(s, self.shift);
                if *has {
                    f.scatter_interior(
                        n,
                        s.mask.as_ref(),
                        v,
                        &mut self.rows,
                        self.base,
                        self.width,
                    );
                }
                f.scatter_cells(n, s.mask.as_ref(), c, &mut self.rows, self.base, self.width);
                visit((level, i, coarse, v, c));
            }
        }
        Ok(())
    }
}

/// Synthesises a planar raster from its root grid and per-diamond details, a band of rows
/// at a time: `details(level, index, h)` fills a diamond's dequantised details (returning
/// whether any is nonzero), `visit` sees every diamond's coarse and fine vertices and
/// cells (in no particular order), and `emit` receives the rows of the raster in order.
/// Memory: a few diamond heights of rows per octave.
pub(crate) fn synthesize_rows(
    geom: &RasterGeometry,
    root: &[i32],
    details: &Details<'_>,
    visit: &mut dyn FnMut(Synthesised<'_>),
    emit: &mut dyn FnMut(&[i32]) -> Result<(), EncodeError>,
) -> Result<(), EncodeError> {
    let n = geom.n();
    let octaves = geom.detail_levels() / 2;
    let mut dims = vec![(geom.width(), geom.height())];
    for o in 0..octaves {
        let (w, h) = dims[o];
        dims.push((w.div_ceil(2), h.div_ceil(2)));
    }
    let mut octs: Vec<SynthOctave> = (0..octaves)
        .map(|o| {
            let (level_a, level_b, a_groups, b_groups) = octave_groups(geom, n, o)?;
            let (width, height) = dims[o];
            Ok(SynthOctave {
                width,
                height,
                shift: o as u32,
                level_a,
                level_b,
                a_groups,
                b_groups,
                next_a: 0,
                next_b: 0,
                rows: Vec::new(),
                base: 0,
                next_emit: 0,
                received: 0,
            })
        })
        .collect::<Result<_, EncodeError>>()?;
    // `R_k`, the root grid's points.
    let (wk, hk) = dims[octaves];
    let mut top = vec![0; wk * hk];
    let root_slot = geom.root_slot();
    let f = Frame::of(&root_slot, octaves as u32);
    f.scatter_all(n, root_slot.mask.as_ref(), root, &mut top, wk);
    if octaves == 0 {
        for row in top.chunks_exact(wk) {
            emit(row)?;
        }
        return Ok(());
    }
    // Rows flow from octave k - 1 down to 0; each push may release rows to the next.
    let mut pending: Vec<Vec<i32>> = top.chunks_exact(wk).map(<[i32]>::to_vec).collect();
    pending.reverse();
    feed(&mut octs, octaves - 1, pending, geom, details, visit, emit)?;
    if octs.iter().any(|o| !o.done()) {
        return Err(EncodeError::Internal("rows left unsynthesised"));
    }
    Ok(())
}

/// Pushes `rows` (last = first to push) into octave `o` and everything it releases down
/// the chain.
#[allow(clippy::too_many_arguments)]
fn feed(
    octs: &mut [SynthOctave],
    o: usize,
    mut rows: Vec<Vec<i32>>,
    geom: &RasterGeometry,
    details: &Details<'_>,
    visit: &mut dyn FnMut(Synthesised<'_>),
    emit: &mut dyn FnMut(&[i32]) -> Result<(), EncodeError>,
) -> Result<(), EncodeError> {
    while let Some(row) = rows.pop() {
        octs[o].push(&row);
        let mut out: Vec<Vec<i32>> = Vec::new();
        if o == 0 {
            octs[0].advance(geom, details, visit, emit)?;
        } else {
            octs[o].advance(geom, details, visit, &mut |r: &[i32]| {
                out.push(r.to_vec());
                Ok(())
            })?;
            out.reverse();
            feed(octs, o - 1, out, geom, details, visit, emit)?;
        }
    }
    Ok(())
}
