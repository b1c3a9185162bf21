//! The RMS rate control out of core: the in-memory search ([`search_scale`]) over passes
//! of the streaming analysis and synthesis instead of a raster in memory.
//!
//! - One analysis pass collects the details' magnitude histograms per level (the
//!   search's estimates).
//! - With the rate-distortion quantiser, one analysis pass trains its cost model.
//! - Each verification decode is an analysis pass that quantises every diamond into a
//!   compact in-memory spill of its nonzero indices, then a synthesis pass
//!   ([`super::synth`]) from the spill that measures every diamond and the errors against
//!   the source rows, read again in order.
//! - The kept attempt's spill gives the side information and the blobs, so no pass
//!   follows the search.
//!
//! Every step computes what the in-memory encoder computes, in the same order where
//! floating point is involved (the error sums are per 64 K-sample piece in sample order),
//! so the result is the in-memory encoder's bit for bit where the nodata fills agree.

use std::borrow::Cow;
use std::collections::BTreeMap;

use rayon::prelude::*;

use super::{
    BlobSink, DetailVisitor, Fill, IndexSpill, Meter, Plan, RowSource, StreamEncoded, Work,
    run_pass, synth,
};
use crate::encode::{
    Attempt, EncodeError, EncodeReport, Measure, PASS_CHUNK, Quantise, RdoMode, Tally, ValueMap,
    Verifier, blob_model, code_blob, dequantize, histogram_entries, measure, rms_of_pieces,
    search_scale, side_information, trains_on,
};
use crate::entropy::{CodecModel, ContextCounts};
use crate::raster::RasterGeometry;

/// What the passes read and hold.
pub(crate) struct Passes<'a> {
    pub(crate) source: &'a mut dyn RowSource,
    pub(crate) plan: &'a Plan,
    pub(crate) geom: &'a RasterGeometry,
    pub(crate) map: &'a ValueMap,
    pub(crate) fill: &'a Fill,
    pub(crate) meter: &'a mut Meter,
}

impl Passes<'_> {
    /// One streamed analysis, every batch of details to `visitor`; the root grid.
    fn analyse(&mut self, visitor: &mut dyn DetailVisitor) -> Result<Vec<i32>, EncodeError> {
        run_pass(
            self.source,
            self.plan,
            self.geom,
            self.map,
            self.fill,
            &mut Work::Visit(visitor),
            self.meter,
        )
    }
}

/// Diamonds coded at once at the end.
const CODE_PIECE: usize = 4096;

/// Magnitudes below this are counted in a table per level, the rest in a map.
const DENSE: usize = 1 << 12;

/// Counts of each detail magnitude per level.
pub(super) struct Histograms {
    dense: Vec<Vec<u64>>,
    sparse: Vec<BTreeMap<u32, u64>>,
}

impl DetailVisitor for Histograms {
    fn visit(
        &mut self,
        _: &RasterGeometry,
        level: usize,
        _: &[usize],
        details: &[&[i32]],
    ) -> Result<(), EncodeError> {
        for h in details {
            self.add(level, h);
        }
        Ok(())
    }
}

impl Histograms {
    pub(super) fn new(levels: usize) -> Self {
        Histograms {
            dense: vec![vec![0; DENSE]; levels],
            sparse: vec![BTreeMap::new(); levels],
        }
    }

    /// Counts the magnitudes of one diamond's details.
    pub(super) fn add(&mut self, level: usize, h: &[i32]) {
        let (dense, sparse) = (&mut self.dense[level], &mut self.sparse[level]);
        for &x in h {
            let a = x.unsigned_abs();
            match dense.get_mut(a as usize) {
                Some(c) => *c += 1,
                None => *sparse.entry(a).or_insert(0) += 1,
            }
        }
    }

    /// `(|h|, count)` ascending per level, as the in-memory encoder's histograms.
    pub(super) fn finish(self) -> Vec<Vec<(u32, u64)>> {
        self.dense
            .into_iter()
            .zip(self.sparse)
            .map(|(dense, sparse)| histogram_entries(dense, sparse))
            .collect()
    }
}

/// Training counts of the rounded details (the rate-distortion cost model).
struct RoundCounts<'a> {
    quantise: &'a Quantise,
    steps: &'a [u32],
    counts: ContextCounts,
}

impl DetailVisitor for RoundCounts<'_> {
    fn visit(
        &mut self,
        geom: &RasterGeometry,
        level: usize,
        batch: &[usize],
        details: &[&[i32]],
    ) -> Result<(), EncodeError> {
        let (len, s) = (geom.level(level).len(), self.steps[level]);
        let counts = batch
            .par_iter()
            .zip(details)
            .filter(|(i, _)| trains_on(len, **i))
            .fold(ContextCounts::default, |mut acc, (&i, h)| {
                self.quantise
                    .count_rounded(&mut acc, geom, (level, i), s, &mut h.to_vec());
                acc
            })
            .reduce(ContextCounts::default, |mut a, b| {
                a.merge(&b);
                a
            });
        self.counts.merge(&counts);
        Ok(())
    }
}

/// The nonzero index matrices of one attempt, each as LEB128 pairs (zeros before, zigzag
/// value), in slot `slot` of an [`IndexSpill`]; the index is in memory.
#[derive(Default)]
pub(super) struct Spill {
    n: usize,
    slot: usize,
    /// Per level and diamond: `(offset, length)` in the slot.
    index: Vec<Vec<Option<(u64, u32)>>>,
}

impl Spill {
    fn new(geom: &RasterGeometry, slot: usize) -> Self {
        Self::with_levels(
            geom.n(),
            slot,
            (0..geom.detail_levels()).map(|l| geom.level(l).len()),
        )
    }

    /// An empty spill in slot `slot` of levels of `lens` diamonds of `N = n`.
    pub(super) fn with_levels(
        n: usize,
        slot: usize,
        lens: impl IntoIterator<Item = usize>,
    ) -> Self {
        Spill {
            n,
            slot,
            index: lens.into_iter().map(|len| vec![None; len]).collect(),
        }
    }

    pub(super) fn clear(&mut self, store: &mut dyn IndexSpill) -> Result<(), EncodeError> {
        store.clear(self.slot).map_err(EncodeError::writing)?;
        self.index.iter_mut().flatten().for_each(|e| *e = None);
        Ok(())
    }

    pub(super) fn held(&self) -> usize {
        self.index.iter().map(|l| l.capacity() * 16).sum()
    }

    /// Stores the matrices of diamonds `(level, index)` of one batch.
    pub(super) fn put_batch(
        &mut self,
        store: &mut dyn IndexSpill,
        level: usize,
        matrices: &[(usize, &[i32])],
    ) -> Result<(), EncodeError> {
        let mut bytes = Vec::new();
        let mut spans = Vec::with_capacity(matrices.len());
        for &(index, q) in matrices {
            let start = bytes.len();
            let mut zeros = 0u64;
            for &x in q {
                if x == 0 {
                    zeros += 1;
                    continue;
                }
                put_varint(&mut bytes, zeros);
                put_varint(&mut bytes, ((x << 1) ^ (x >> 31)) as u32 as u64);
                zeros = 0;
            }
            spans.push((index, start, bytes.len() - start));
        }
        let base = store
            .append(self.slot, &bytes)
            .map_err(EncodeError::writing)?;
        for (index, start, len) in spans {
            self.index[level][index] = Some((base + start as u64, len as u32));
        }
        Ok(())
    }

    pub(super) fn has(&self, level: usize, index: usize) -> bool {
        self.index[level][index].is_some()
    }

    /// Diamond `(level, index)`'s indices into `out` (zeros when it has none); whether
    /// it has any.
    pub(super) fn get(
        &self,
        store: &dyn IndexSpill,
        level: usize,
        index: usize,
        out: &mut [i32],
    ) -> Result<bool, EncodeError> {
        out.iter_mut().for_each(|x| *x = 0);
        let Some((offset, len)) = self.index[level][index] else {
            return Ok(false);
        };
        let data = store
            .read(self.slot, offset, len as usize)
            .map_err(EncodeError::reading)?;
        let mut bytes = &data[..];
        let mut k = 0usize;
        while !bytes.is_empty() {
            k += get_varint(&mut bytes)? as usize;
            let z = get_varint(&mut bytes)? as u32;
            let x = ((z >> 1) as i32) ^ -((z & 1) as i32);
            *out.get_mut(k)
                .ok_or(EncodeError::Internal("index spill overrun"))? = x;
            k += 1;
        }
        Ok(true)
    }

    pub(super) fn matrix(
        &self,
        store: &dyn IndexSpill,
        level: usize,
        index: usize,
    ) -> Result<Vec<i32>, EncodeError> {
        let mut q = vec![0; self.n * self.n];
        self.get(store, level, index, &mut q)?;
        Ok(q)
    }
}

fn put_varint(out: &mut Vec<u8>, mut v: u64) {
    while v >= 0x80 {
        out.push((v as u8) | 0x80);
        v >>= 7;
    }
    out.push(v as u8);
}

fn get_varint(bytes: &mut &[u8]) -> Result<u64, EncodeError> {
    let mut v = 0u64;
    for shift in (0..64).step_by(7) {
        let (&b, rest) = bytes
            .split_first()
            .ok_or(EncodeError::Internal("spill cut short"))?;
        *bytes = rest;
        v |= u64::from(b & 0x7f) << shift;
        if b < 0x80 {
            return Ok(v);
        }
    }
    Err(EncodeError::Internal("spill varint too long"))
}

/// Quantises every diamond of an attempt into a spill.
struct QuantiseInto<'a> {
    quantise: &'a Quantise,
    cost_model: Option<&'a CodecModel>,
    steps: &'a [u32],
    spill: &'a mut Spill,
    store: &'a mut dyn IndexSpill,
    coded: bool,
}

impl DetailVisitor for QuantiseInto<'_> {
    fn visit(
        &mut self,
        geom: &RasterGeometry,
        level: usize,
        batch: &[usize],
        details: &[&[i32]],
    ) -> Result<(), EncodeError> {
        let n = geom.n();
        let quantised: Vec<Vec<i32>> = batch
            .par_iter()
            .zip(details)
            .map(|(&i, h)| {
                let mut q = vec![0; n * n];
                self.quantise.matrix(
                    self.cost_model,
                    &geom.blob_context(level, i),
                    self.steps[level],
                    h,
                    &mut q,
                );
                q
            })
            .collect();
        let nonzero: Vec<(usize, &[i32])> = batch
            .iter()
            .zip(&quantised)
            .filter(|(_, q)| q.iter().any(|&x| x != 0))
            .map(|(&i, q)| (i, &q[..]))
            .collect();
        if !nonzero.is_empty() {
            self.coded = true;
            self.spill.put_batch(self.store, level, &nonzero)?;
        }
        Ok(())
    }
}

/// A verification decode's measures per diamond and `(rms, max)`.
type Verified = (Vec<Vec<Measure>>, (f64, f64));

/// The out-of-core verifier: analysis into a spill, synthesis from it.
struct StreamVerifier<'a> {
    passes: Passes<'a>,
    store: &'a mut dyn IndexSpill,
    valid_count: usize,
    root: Vec<i32>,
    last: Spill,
    kept: Spill,
}

impl StreamVerifier<'_> {
    /// Synthesises from `spill` at `steps`, measuring every diamond and the errors
    /// against the source rows.
    fn verify(&mut self, steps: &[u32], spill: &Spill) -> Result<Verified, EncodeError> {
        let geom = self.passes.geom;
        let store: &dyn IndexSpill = &*self.store;
        let n = geom.n();
        let w = geom.width();
        let map = self.passes.map;
        let chunk = self.passes.plan.chunk_rows;
        let mut measures: Vec<Vec<Option<Measure>>> = (0..geom.detail_levels())
            .map(|l| vec![None; geom.level(l).len()])
            .collect();
        let details = |l: usize, i: usize, h: &mut [i32]| -> Result<bool, EncodeError> {
            let any = spill.get(store, l, i, h)?;
            if any {
                for x in h.iter_mut() {
                    *x = dequantize(*x, steps[l]);
                }
            }
            Ok(any)
        };
        // Source rows `src_first ..` in `src`, read a chunk at a time as rows arrive.
        let source = &mut *self.passes.source;
        let height = geom.height();
        let mut src = vec![0.0; chunk * w];
        let (mut src_first, mut src_rows) = (0usize, 0usize);
        let mut row = 0usize;
        let mut pieces: Vec<(f64, f64)> = Vec::new();
        let (mut acc, mut in_piece) = ((0.0, 0.0f64), 0usize);
        self.passes
            .meter
            .note(src.capacity() * 8 + store.held() + self.kept.held() + self.last.held());
        synth::synthesize_rows(
            geom,
            &self.root,
            &details,
            &mut |(l, i, coarse, fine, cells)| {
                measures[l][i] = Some(measure(
                    n,
                    geom.level(l)[i].mask.as_ref(),
                    coarse,
                    fine,
                    cells,
                ));
            },
            &mut |decoded: &[i32]| {
                if row >= src_first + src_rows {
                    src_first = row;
                    src_rows = chunk.min(height - row);
                    source
                        .read_rows(src_first, src_rows, &mut src[..src_rows * w])
                        .map_err(EncodeError::reading)?;
                }
                let vs = &src[(row - src_first) * w..(row - src_first + 1) * w];
                for (&d, &v) in decoded.iter().zip(vs) {
                    if v.is_finite() {
                        let e = (map.offset + d as f64 * map.scale - v).abs();
                        acc = (acc.0 + e * e, acc.1.max(e));
                    }
                    in_piece += 1;
                    if in_piece == PASS_CHUNK {
                        pieces.push(acc);
                        (acc, in_piece) = ((0.0, 0.0), 0);
                    }
                }
                row += 1;
                Ok(())
            },
        )?;
        if in_piece > 0 {
            pieces.push(acc);
        }
        let measures = measures
            .into_iter()
            .map(|l| l.into_iter().collect::<Option<Vec<Measure>>>())
            .collect::<Option<Vec<_>>>()
            .ok_or(EncodeError::Internal("a diamond was not synthesised"))?;
        Ok((measures, rms_of_pieces(&pieces, self.valid_count)))
    }
}

impl Verifier for StreamVerifier<'_> {
    fn train_cost(&mut self, q: &Quantise, steps: &[u32]) -> Result<CodecModel, EncodeError> {
        let mut counts = RoundCounts {
            quantise: q,
            steps,
            counts: ContextCounts::default(),
        };
        self.passes.analyse(&mut counts)?;
        Ok(CodecModel::from_counts(&counts.counts))
    }

    fn attempt(
        &mut self,
        q: &Quantise,
        cost_model: Option<&CodecModel>,
        steps: &[u32],
    ) -> Result<Attempt, EncodeError> {
        let mut last = std::mem::take(&mut self.last);
        last.clear(self.store)?;
        let mut into = QuantiseInto {
            quantise: q,
            cost_model,
            steps,
            spill: &mut last,
            store: &mut *self.store,
            coded: false,
        };
        self.passes.analyse(&mut into)?;
        let coded = into.coded;
        let verified = self.verify(steps, &last);
        self.last = last;
        let (measures, errors) = verified?;
        Ok((measures, coded, errors))
    }

    fn keep_last(&mut self) {
        std::mem::swap(&mut self.last, &mut self.kept);
    }
}

/// Encodes a planar raster at an RMS target out of core (see the module docs).
pub(crate) fn encode_rms<'a>(
    mut passes: Passes<'a>,
    target: f64,
    rdo: RdoMode,
    valid_count: usize,
    (sink, store): (&mut dyn BlobSink, &'a mut dyn IndexSpill),
) -> Result<StreamEncoded, EncodeError> {
    let geom = passes.geom;
    let (n, levels) = (geom.n(), geom.detail_levels());
    let map = *passes.map;
    let unit = passes.source.quantum_m().unwrap_or(map.scale);
    let mut hist = Histograms::new(levels);
    let root = passes.analyse(&mut hist)?;
    let hist = hist.finish();
    let mut verifier = StreamVerifier {
        valid_count,
        store,
        root,
        last: Spill::new(geom, 0),
        kept: Spill::new(geom, 1),
        passes,
    };
    let out = search_scale(
        n,
        &hist,
        (target, unit, map.scale),
        valid_count,
        rdo,
        &mut verifier,
    )?;
    let StreamVerifier {
        root,
        kept,
        passes,
        store,
        ..
    } = verifier;
    let store: &dyn IndexSpill = store;
    let side = side_information(geom, |l, i| kept.has(l, i), &out.measures);
    // Training cannot stop half-way: a spill read that fails trains on zeros and is
    // reported once the model is done.
    let failed = std::sync::Mutex::new(None);
    let matrix = |l: usize, i: usize| {
        Cow::Owned(kept.matrix(store, l, i).unwrap_or_else(|e| {
            if let Ok(mut f) = failed.lock() {
                f.get_or_insert(e);
            }
            vec![0; n * n]
        }))
    };
    let model = blob_model(geom, &out.steps, &matrix, &side);
    if let Some(e) = failed.into_inner().ok().flatten() {
        return Err(e);
    }
    // Coded and handed to the sink a piece of a level at a time.
    let (mut blob_count, mut blob_bytes) = (0, 0);
    for l in 0..levels {
        let len = geom.level(l).len();
        for start in (0..len).step_by(CODE_PIECE) {
            let blobs: Vec<Option<Vec<u8>>> = (start..(start + CODE_PIECE).min(len))
                .into_par_iter()
                .map(|i| {
                    let q = kept.matrix(store, l, i)?;
                    Ok(code_blob(geom, &out.steps, &model, &q, &side, l, i))
                })
                .collect::<Result<_, EncodeError>>()?;
            for (k, blob) in blobs.iter().enumerate() {
                if let Some(b) = blob {
                    let i = start + k;
                    sink.put(l, i, &geom.level(l)[i].key, b)
                        .map_err(EncodeError::writing)?;
                    blob_count += 1;
                    blob_bytes += b.len();
                }
            }
        }
    }
    let report = EncodeReport::tally(Tally {
        samples: geom.width() * geom.height(),
        valid_samples: valid_count,
        blobs: (blob_count, blob_bytes),
        roots: std::slice::from_ref(&root),
        model: &model,
        steps: out.steps.len(),
        errors: out.errors,
        rdo: out.rdo_used,
        decodes: out.decodes,
    });
    Ok(StreamEncoded {
        width: geom.width(),
        height: geom.height(),
        n,
        value_scale_m: map.scale,
        value_offset_m: map.offset,
        steps: out.steps,
        root,
        model,
        report,
        peak_buffer_bytes: passes.meter.peak,
        coverage: None,
    })
}
