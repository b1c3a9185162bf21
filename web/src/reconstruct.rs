//! A whole repository at full resolution: what `web-demo/tools/decode-repo.mjs` hashes,
//! to check the module against `quincunx verify` (the reconstruction hash of
//! `docs/blob-format.md`), by either of two decoders:
//!
//! - [`Decoder::Whole`]: the whole-raster decoder `quincunx verify` runs
//!   ([`quincunx_decoder::layout::decode_levels`]): each level synthesised in place in the
//!   domain's sample layout. Memory: the layout per channel and the output.
//! - [`Decoder::Refiners`]: every diamond of every detail level refined coarse to fine as
//!   a client does (each child's grid cut from its refined parents' lattices), each
//!   refined lattice written into the layout. Memory: also the lattices of one level.
//!
//! Points outside a sparse repository's coverage end as 0 in both.

use std::collections::{HashMap, HashSet};
use std::time::Duration;

use quincunx_client_core::domain::Domain;
use quincunx_client_core::fetch::Key;
use quincunx_client_core::open::SessionError;
use quincunx_client_core::refine::Clock;
use quincunx_decoder::coverage::Coverage;
use quincunx_decoder::diamond::{PlanarDomain, PlanarId, SphereId};
use quincunx_decoder::incremental::{PlanarRefiner, RefineError, Refined, Refiner, SphereRefiner};
use quincunx_decoder::lattice::write_lattice;
use quincunx_decoder::layout::{ChannelCoding, Layout, decode_levels};
use quincunx_decoder::raster::{self, DiamondSlot, RasterGeometry};
use quincunx_decoder::sphere_raster::{SphereFrame, SphereGeometry, SphereSlot};
use quincunx_meta::channels::split_channels;
use quincunx_meta::{Domain as MetaDomain, Metadata};

use crate::wire::{Reader, WireError};

/// Bytes of the output's header (`u32 channels, u32 samples, f64 seconds`): the values
/// after it are 4-byte aligned.
pub const HEADER: usize = 16;

/// Most values (samples times channels) a reconstruction holds: with the output, 8 bytes
/// each, half of a 32-bit module's 4 GiB memory.
pub const MAX_VALUES: usize = 1 << 28;

/// Most bytes a reconstruction holds at once: three quarters of a 32-bit module's 4 GiB.
pub const MAX_BYTES: u64 = 3 << 30;

/// Refuses, before taking any memory, a reconstruction of `count` channels of `len`
/// samples in `N x N` diamonds that would hold more than [`MAX_VALUES`] values or about
/// [`MAX_BYTES`]: the sample arrays and the output (8 bytes a value), and the decoder's
/// tables: every diamond's slot (`slot_bytes` each) for the whole-raster decoder, the
/// refined lattices of two levels per channel for the refiners (a level has at most about
/// `len / N^2` diamonds, all levels together twice that).
fn check_memory(
    count: usize,
    len: usize,
    n: usize,
    decoder: Decoder,
    slot_bytes: usize,
) -> Result<(), String> {
    if len.saturating_mul(count) > MAX_VALUES {
        return Err(format!(
            "{count} x {len} values are too many to reconstruct in memory (at most {MAX_VALUES})"
        ));
    }
    let (len, count, n) = (len as u64, count as u64, (n as u64).max(1));
    let finest = len / (n * n) + 1;
    let tables = match decoder {
        Decoder::Whole => 2 * finest * slot_bytes as u64,
        Decoder::Refiners => 2 * count * finest * ((n + 1) * (n + 1) + n * n) * 4,
    };
    let need = 8 * len * count + tables;
    if need > MAX_BYTES {
        return Err(format!(
            "reconstructing {count} x {len} values in diamonds of {n} x {n} needs about {} MiB \
             of memory, more than the {} MiB allowed",
            need >> 20,
            MAX_BYTES >> 20
        ));
    }
    Ok(())
}

/// Which decoder reconstructs (both give the same values, bit for bit).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Decoder {
    /// The whole-raster decoder `quincunx verify` runs, level by level in place.
    Whole,
    /// The refiners a viewer runs, one diamond at a time.
    Refiners,
}

impl Decoder {
    /// The decoder of an ABI code: 0 whole-raster, 1 refiners.
    pub fn from_code(code: u32) -> Option<Decoder> {
        match code {
            0 => Some(Decoder::Whole),
            1 => Some(Decoder::Refiners),
            _ => None,
        }
    }
}

/// Input `u32 meta_len, metadata JSON, u32 count, (key, u32 len, bytes)*` (each diamond's
/// stored blob by its fetch key); output `u32 channels, u32 samples, f64 decode_seconds,
/// i32 values` (channel after channel, canonical order), all little-endian.
///
/// `decode_seconds`, read from `clock`, is the decode and synthesis alone, as
/// `quincunx verify` times its decode: from the blobs and the parsed coding (metadata,
/// geometry tables) to the full-resolution values; not parsing the input or writing the
/// output.
pub fn reconstruct_call(
    input: &[u8],
    decoder: Decoder,
    clock: &dyn Clock,
) -> Result<Vec<u8>, String> {
    let (meta, blobs) = parse(input)?;
    let (channels, seconds) = match (meta.domain, decoder) {
        (MetaDomain::Planar, Decoder::Whole) => whole::<PlanarRefiner>(&meta, blobs, clock)?,
        (MetaDomain::Sphere, Decoder::Whole) => whole::<SphereRefiner>(&meta, blobs, clock)?,
        (MetaDomain::Planar, Decoder::Refiners) => reconstruct::<Plane>(&meta, blobs, clock)?,
        (MetaDomain::Sphere, Decoder::Refiners) => reconstruct::<Cube>(&meta, blobs, clock)?,
    };
    output(channels, seconds)
}

/// Seconds of `clock` since `start`.
fn since(clock: &dyn Clock, start: Duration) -> f64 {
    clock.now().saturating_sub(start).as_secs_f64()
}

/// A domain's whole-raster geometry, as its refiner's parameters give it.
trait WholeRaster: Domain {
    type Geometry: Layout;
    /// Samples of the domain's layout (cheap: checked before the geometry is built).
    fn sample_len(&self) -> usize;
    /// Diamond size `N`.
    fn diamond_size(&self) -> usize;
    /// The geometry (with the repository's coverage, if any).
    fn geometry(&self) -> Result<Self::Geometry, String>;
    /// The diamond at `index` of detail level `level`.
    fn id_at(g: &Self::Geometry, level: usize, index: usize) -> Self::Id;
    /// The channel's coding (roots, steps, model).
    fn channel_coding(&self) -> ChannelCoding<'_>;
}

impl WholeRaster for PlanarRefiner {
    type Geometry = RasterGeometry;

    fn sample_len(&self) -> usize {
        let (w, h) = self.raster_size();
        w.saturating_mul(h)
    }

    fn diamond_size(&self) -> usize {
        self.n()
    }

    fn geometry(&self) -> Result<RasterGeometry, String> {
        let (w, h) = self.raster_size();
        match self.frame().coverage() {
            None => RasterGeometry::new(w, h, self.n()),
            Some(c) => RasterGeometry::with_coverage(w, h, self.n(), c),
        }
        .map_err(|e| format!("metadata: {e}"))
    }

    fn id_at(g: &RasterGeometry, level: usize, index: usize) -> PlanarId {
        g.level(level)[index].id
    }

    fn channel_coding(&self) -> ChannelCoding<'_> {
        self.coding()
    }
}

impl WholeRaster for SphereRefiner {
    type Geometry = SphereGeometry;

    fn sample_len(&self) -> usize {
        self.frame().cube_len()
    }

    fn diamond_size(&self) -> usize {
        self.frame().n()
    }

    fn geometry(&self) -> Result<SphereGeometry, String> {
        let f = self.frame();
        match f.coverage() {
            None => SphereGeometry::new(f.face_side(), f.n()),
            Some(c) => SphereGeometry::with_coverage(f.face_side(), f.n(), c),
        }
        .map_err(|e| format!("metadata: {e}"))
    }

    fn id_at(g: &SphereGeometry, level: usize, index: usize) -> SphereId {
        g.level(level)[index].id
    }

    fn channel_coding(&self) -> ChannelCoding<'_> {
        self.coding()
    }
}

/// Decodes every channel of the repository `meta` describes with the whole-raster
/// decoder; `blobs` by fetch key. One sample array per channel, and the seconds of the
/// decode (see [`reconstruct_call`]).
fn whole<R: WholeRaster>(
    meta: &Metadata,
    mut blobs: HashMap<Key, &[u8]>,
    clock: &dyn Clock,
) -> Result<(Vec<Vec<i32>>, f64), String> {
    let count = meta.channels.len();
    let refiners = (0..count)
        .map(|c| R::channel_from_metadata("", meta, c).map_err(metadata_error))
        .collect::<Result<Vec<_>, _>>()?;
    let r0 = refiners.first().ok_or("metadata: no channels")?;
    let len = r0.sample_len();
    // A slot, and its children's indices and mask on the heap.
    let slot_bytes = std::mem::size_of::<<R::Geometry as Layout>::Slot>() + 128;
    check_memory(count, len, r0.diamond_size(), Decoder::Whole, slot_bytes)?;
    let geom = r0.geometry()?;
    // Each diamond's blob, split into its channels' parts, by level and index.
    let mut parts: Vec<Vec<Vec<Option<&[u8]>>>> = Vec::with_capacity(geom.slot_levels().len());
    for (level, slots) in geom.slot_levels().iter().enumerate() {
        let mut row = Vec::with_capacity(slots.len());
        for index in 0..slots.len() {
            let key = R::key_of(R::id_at(&geom, level, index));
            row.push(match blobs.remove(&key).filter(|b| !b.is_empty()) {
                None => Vec::new(),
                Some(b) => {
                    split_channels(b, count).map_err(|e| format!("blob {}: {e}", key_text(key)))?
                }
            });
        }
        parts.push(row);
    }
    if let Some(&k) = blobs.keys().min() {
        return Err(format!(
            "blob {} belongs to no diamond of the repository",
            key_text(k)
        ));
    }
    let start = clock.now();
    let mut out = Vec::with_capacity(count);
    for (c, r) in refiners.iter().enumerate() {
        let mut values = Vec::new();
        values
            .try_reserve_exact(len)
            .map_err(|_| format!("{len} values do not fit in memory"))?;
        // The diamond whose blob was asked for last is the one an error is about.
        let last = std::cell::Cell::new((0, 0));
        decode_levels(
            &geom,
            r.channel_coding(),
            |l, i| {
                last.set((l, i));
                parts[l][i].get(c).copied().flatten()
            },
            &mut values,
        )
        .map_err(|e| {
            let (l, i) = last.get();
            format!(
                "diamond {}, channel {c}: {e}",
                key_text(R::key_of(R::id_at(&geom, l, i)))
            )
        })?;
        out.push(values);
    }
    Ok((out, since(clock, start)))
}

/// The metadata and the blobs by fetch key.
fn parse(input: &[u8]) -> Result<(Metadata, HashMap<Key, &[u8]>), String> {
    let wire = |e: WireError| format!("input: {e}");
    let mut r = Reader::new(input);
    let json = r.bytes().map_err(wire)?;
    let meta: Metadata = serde_json::from_slice(json).map_err(|e| format!("metadata: {e}"))?;
    // A key and a length at least.
    let count = r.count(28).map_err(wire)?;
    let mut blobs = HashMap::with_capacity(count);
    for _ in 0..count {
        let key = r.key().map_err(wire)?;
        let bytes = r.bytes().map_err(wire)?;
        if blobs.insert(key, bytes).is_some() {
            return Err(format!("blob {} given twice", key_text(key)));
        }
    }
    r.finish().map_err(wire)?;
    Ok((meta, blobs))
}

/// `u32 channels, u32 samples, f64 seconds`, then each channel's values.
fn output(channels: Vec<Vec<i32>>, seconds: f64) -> Result<Vec<u8>, String> {
    let samples = channels.first().map_or(0, Vec::len);
    let header = |v: usize| u32::try_from(v).map_err(|_| format!("{v} does not fit a u32"));
    let len = channels
        .len()
        .checked_mul(samples)
        .and_then(|v| v.checked_mul(4))
        .and_then(|v| v.checked_add(HEADER))
        .ok_or("the output does not fit in memory")?;
    let mut out = Vec::new();
    out.try_reserve_exact(len)
        .map_err(|_| format!("the output ({len} bytes) does not fit in memory"))?;
    out.extend_from_slice(&header(channels.len())?.to_le_bytes());
    out.extend_from_slice(&header(samples)?.to_le_bytes());
    out.extend_from_slice(&seconds.to_le_bytes());
    out.resize(len, 0);
    // Each channel is freed once copied.
    for (values, dst) in channels
        .into_iter()
        .zip(out[HEADER..].chunks_exact_mut(4 * samples.max(1)))
    {
        for (d, v) in dst.chunks_exact_mut(4).zip(values) {
            d.copy_from_slice(&v.to_le_bytes());
        }
    }
    Ok(out)
}

/// A fetch key as the export names its file: `x/y` on the plane, `x/y/z` on a planet.
fn key_text(k: Key) -> String {
    match k {
        [x, y, 0] => format!("{x}/{y}"),
        [x, y, z] => format!("{x}/{y}/{z}"),
    }
}

/// A zeroed raster of `len` values, or an error when memory is short.
fn zeros(len: usize) -> Result<Vec<i32>, String> {
    let mut v = Vec::new();
    v.try_reserve_exact(len)
        .map_err(|_| format!("a raster of {len} values does not fit in memory"))?;
    v.resize(len, 0);
    Ok(v)
}

/// Metadata a refiner refused, without the repository name (there is none here).
fn metadata_error(e: SessionError) -> String {
    match e {
        SessionError::Metadata { reason, .. } | SessionError::Unsupported { reason, .. } => {
            format!("metadata: {reason}")
        }
        e => e.to_string(),
    }
}

/// A domain's canonical sample layout and how refined diamonds land in it.
trait Canvas: Sized {
    /// The domain's refiner.
    type Refiner: Domain;
    /// Where one diamond's points are.
    type Slot;

    /// The layout of the repository of `meta`, whose first channel `r` refines.
    fn new(meta: &Metadata, r: &Self::Refiner) -> Result<Self, String>;
    /// Points in the layout.
    fn len(&self) -> usize;
    /// Diamond size `N`.
    fn n(&self) -> usize;
    /// Writes the root grids of one channel.
    fn scatter_roots(&self, r: &Self::Refiner, raster: &mut [i32]) -> Result<(), String>;
    /// The placement of a coded diamond.
    fn slot(&self, id: <Self::Refiner as Refiner>::Id) -> Result<Self::Slot, String>;
    /// Writes a refined diamond: its cells, and its interior vertices when `vertices`
    /// (with zero details they are its grid's, already written).
    fn write(
        &self,
        slot: &Self::Slot,
        refined: &Refined<<Self::Refiner as Refiner>::Id>,
        vertices: bool,
        raster: &mut [i32],
    );
    /// Sets the points outside the coverage to 0.
    fn clear_invalid(&self, raster: &mut [i32]);
    /// The grid of `child` from its parents' lattices.
    fn child_grid(
        r: &Self::Refiner,
        child: <Self::Refiner as Refiner>::Id,
        parents: &[&Refined<<Self::Refiner as Refiner>::Id>],
    ) -> Result<Vec<i32>, RefineError>;
}

/// Refines every diamond of the repository `meta` describes, level by level, each
/// channel with its own refiner; `blobs` by fetch key. One raster per channel, and the
/// seconds of the decode (see [`reconstruct_call`]).
fn reconstruct<C: Canvas>(
    meta: &Metadata,
    mut blobs: HashMap<Key, &[u8]>,
    clock: &dyn Clock,
) -> Result<(Vec<Vec<i32>>, f64), String> {
    type Id<C> = <<C as Canvas>::Refiner as Refiner>::Id;
    let key_of = <C::Refiner as Refiner>::key_of;
    let count = meta.channels.len();
    let refiners = (0..count)
        .map(|c| C::Refiner::channel_from_metadata("", meta, c).map_err(metadata_error))
        .collect::<Result<Vec<_>, _>>()?;
    let r0 = refiners.first().ok_or("metadata: no channels")?;
    let stray = blobs
        .keys()
        .filter(|&&k| {
            let id = <C::Refiner as Refiner>::id_of(k);
            key_of(id) != k || !r0.is_coded(id)
        })
        .min();
    if let Some(&k) = stray {
        return Err(format!(
            "blob {} belongs to no diamond of the repository",
            key_text(k)
        ));
    }

    let canvas = C::new(meta, r0)?;
    let len = canvas.len();
    check_memory(count, len, canvas.n(), Decoder::Refiners, 0)?;
    let start = clock.now();
    let mut rasters = (0..count)
        .map(|_| zeros(len))
        .collect::<Result<Vec<_>, _>>()?;
    for (r, raster) in refiners.iter().zip(&mut rasters) {
        canvas.scatter_roots(r, raster)?;
    }

    let levels = r0.detail_levels();
    let mut ids: Vec<Id<C>> = r0.roots().iter().map(|&(id, _)| id).collect();
    // Per channel, the lattices of the previous level by id.
    let mut previous: Vec<HashMap<Id<C>, Refined<Id<C>>>> = vec![HashMap::new(); count];
    for level in 0..levels {
        let last = level + 1 == levels;
        let mut current: Vec<HashMap<Id<C>, Refined<Id<C>>>> = vec![HashMap::new(); count];
        let mut next = Vec::new();
        let mut seen = HashSet::new();
        for &id in &ids {
            let key = key_of(id);
            let info = r0.info(id).filter(|i| i.level == level).ok_or_else(|| {
                format!(
                    "diamond {} is not refinable at level {level}",
                    key_text(key)
                )
            })?;
            let slot = canvas.slot(id)?;
            let parts = match blobs.remove(&key).filter(|b| !b.is_empty()) {
                None => vec![None; count],
                Some(b) => {
                    split_channels(b, count).map_err(|e| format!("blob {}: {e}", key_text(key)))?
                }
            };
            let parents = if level == 0 {
                Vec::new()
            } else {
                r0.parents(id)
            };
            for (c, r) in refiners.iter().enumerate() {
                let refine_error = |e: RefineError| format!("diamond {}: {e}", key_text(key));
                let grid = if level == 0 {
                    r.roots()
                        .into_iter()
                        .find(|&(root, _)| root == id)
                        .map(|(_, g)| g.to_vec())
                        .ok_or_else(|| format!("diamond {} is not a root", key_text(key)))?
                } else {
                    let lattices: Vec<&Refined<Id<C>>> =
                        parents.iter().filter_map(|p| previous[c].get(p)).collect();
                    C::child_grid(r, id, &lattices).map_err(refine_error)?
                };
                let details = parts[c]
                    .map(|p| r.decode(id, p))
                    .transpose()
                    .map_err(refine_error)?;
                let refined = r
                    .synthesize(id, &grid, details.as_ref())
                    .map_err(refine_error)?;
                canvas.write(&slot, &refined, details.is_some(), &mut rasters[c]);
                if !last {
                    current[c].insert(id, refined);
                }
            }
            if !last {
                next.extend(info.children.into_iter().filter(|&c| seen.insert(c)));
            }
        }
        previous = current;
        ids = next;
    }
    // Every blob key is a coded diamond's, and the levels visit every coded diamond.
    if let Some(&k) = blobs.keys().min() {
        return Err(format!(
            "blob {} belongs to no diamond the refiners reached",
            key_text(k)
        ));
    }
    for raster in &mut rasters {
        canvas.clear_invalid(raster);
    }
    Ok((rasters, since(clock, start)))
}

/// The planar layout: the raster, `width x height`, row-major.
struct Plane {
    width: usize,
    height: usize,
    n: usize,
    domain: PlanarDomain,
    coverage: Option<Coverage>,
}

impl Plane {
    /// Raster index of point `(x, y)`, `None` outside the raster.
    fn index(&self, (x, y): (i64, i64)) -> Option<usize> {
        let (x, y) = (usize::try_from(x).ok()?, usize::try_from(y).ok()?);
        (x < self.width && y < self.height).then(|| y * self.width + x)
    }
}

impl Canvas for Plane {
    type Refiner = PlanarRefiner;
    type Slot = DiamondSlot;

    fn new(meta: &Metadata, r: &PlanarRefiner) -> Result<Self, String> {
        let (width, height) = r.raster_size();
        let coverage = meta
            .coverage
            .as_deref()
            .map(Coverage::from_bytes)
            .transpose()
            .map_err(|e| format!("metadata: coverage: {e}"))?;
        Ok(Plane {
            width,
            height,
            n: r.n(),
            domain: r.domain(),
            coverage,
        })
    }

    fn len(&self) -> usize {
        self.width.saturating_mul(self.height)
    }

    fn n(&self) -> usize {
        self.n
    }

    fn scatter_roots(&self, r: &PlanarRefiner, raster: &mut [i32]) -> Result<(), String> {
        let (root, grid) = r.root();
        let s = self.slot(root)?;
        let n = self.n;
        for i in 0..=n {
            for j in 0..=n {
                if let Some(k) = self.index(s.vertex_xy(i, j)) {
                    raster[k] = grid[i * (n + 1) + j];
                }
            }
        }
        Ok(())
    }

    fn slot(&self, id: PlanarId) -> Result<DiamondSlot, String> {
        raster::slot(&self.domain, id, self.n, self.width, self.height)
            .ok_or_else(|| format!("diamond {}/{} lies outside the raster", id.x, id.y))
    }

    fn write(
        &self,
        s: &DiamondSlot,
        refined: &Refined<PlanarId>,
        vertices: bool,
        raster: &mut [i32],
    ) {
        let n = self.n;
        if let Some([v0, c0, si, sj]) = s.lin {
            write_lattice(raster, 0, n, 0, c0, si, sj, &refined.cells);
            if vertices {
                write_lattice(raster, 0, n + 1, 1, v0, si, sj, &refined.vertices);
            }
            return;
        }
        // A diamond on the raster's edge: its points inside.
        for i in 0..n {
            for j in 0..n {
                if let Some(k) = self.index(s.cell_xy(i, j)) {
                    raster[k] = refined.cells[i * n + j];
                }
            }
        }
        if vertices {
            for i in 1..n {
                for j in 1..n {
                    if let Some(k) = self.index(s.vertex_xy(i, j)) {
                        raster[k] = refined.vertices[i * (n + 1) + j];
                    }
                }
            }
        }
    }

    fn clear_invalid(&self, raster: &mut [i32]) {
        let Some(c) = &self.coverage else { return };
        for (y, row) in raster.chunks_exact_mut(self.width).enumerate() {
            for (x, v) in row.iter_mut().enumerate() {
                if !c.covers_point(0, x, y) {
                    *v = 0;
                }
            }
        }
    }

    fn child_grid(
        r: &PlanarRefiner,
        child: PlanarId,
        parents: &[&Refined<PlanarId>],
    ) -> Result<Vec<i32>, RefineError> {
        r.child_grid(child, parents)
    }
}

/// The planet layout: the cube raster, `6 (2S+1)^2` points, every copy of cube-edge
/// points.
struct Cube {
    frame: SphereFrame,
}

impl Canvas for Cube {
    type Refiner = SphereRefiner;
    type Slot = SphereSlot;

    fn new(_meta: &Metadata, r: &SphereRefiner) -> Result<Self, String> {
        Ok(Cube {
            frame: r.frame().clone(),
        })
    }

    fn len(&self) -> usize {
        self.frame.cube_len()
    }

    fn n(&self) -> usize {
        self.frame.n()
    }

    /// As the whole-planet decoder: interior vertices of each face root, and each edge
    /// point from the root of its canonical (lowest) face, to every copy.
    fn scatter_roots(&self, r: &SphereRefiner, raster: &mut [i32]) -> Result<(), String> {
        let n = self.frame.n();
        let side = n + 1;
        let w = self.frame.width();
        for (root, grid) in r.roots() {
            let s = self.slot(root)?;
            for i in 0..side {
                for j in 0..side {
                    let x = grid[i * side + j];
                    if (1..n).contains(&i) && (1..n).contains(&j) {
                        let (k, other) = s.vertex_copies(i, j);
                        for k in std::iter::once(k).chain(other) {
                            raster[k] = x;
                        }
                        continue;
                    }
                    let here = s.vertex_index(i, j);
                    let (face, rest) = (here / (w * w), here % (w * w));
                    let p = self.frame.sample_position(face as u8, rest % w, rest / w);
                    let mut copies = self.frame.point_indices(p);
                    if copies.next() == Some(here) {
                        raster[here] = x;
                        for k in copies {
                            raster[k] = x;
                        }
                    }
                }
            }
        }
        Ok(())
    }

    fn slot(&self, id: SphereId) -> Result<SphereSlot, String> {
        self.frame
            .slot(id)
            .map_err(|e| format!("diamond {}: {e}", key_text(id.c)))
    }

    fn write(
        &self,
        s: &SphereSlot,
        refined: &Refined<SphereId>,
        vertices: bool,
        raster: &mut [i32],
    ) {
        let n = self.frame.n();
        if vertices {
            s.scatter(n + 1, 1, false, &refined.vertices, raster, 0);
        }
        s.scatter(n, 0, true, &refined.cells, raster, 0);
    }

    fn clear_invalid(&self, raster: &mut [i32]) {
        if self.frame.coverage().is_none() {
            return;
        }
        for (k, v) in raster.iter_mut().enumerate() {
            if !self.frame.is_valid(k) {
                *v = 0;
            }
        }
    }

    fn child_grid(
        r: &SphereRefiner,
        child: SphereId,
        parents: &[&Refined<SphereId>],
    ) -> Result<Vec<i32>, RefineError> {
        r.child_grid(child, parents)
    }
}
