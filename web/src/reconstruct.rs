//! A whole repository at full resolution through the refiners: what
//! `web-demo/tools/decode-repo.mjs` hashes, to check the module against `quincunx verify`
//! (the reconstruction hash of `docs/blob-format.md`).
//!
//! Every diamond of every detail level is refined coarse to fine as a client would (each
//! child's grid cut from its refined parents' lattices), and each refined lattice is
//! written into the domain's canonical sample layout; points outside a sparse
//! repository's coverage end as 0, as the whole-raster decoder leaves them. Memory: the
//! layout per channel, the output, and the lattices of one level.

use std::collections::{HashMap, HashSet};

use quincunx_client_core::domain::Domain;
use quincunx_client_core::fetch::Key;
use quincunx_client_core::open::SessionError;
use quincunx_decoder::coverage::Coverage;
use quincunx_decoder::diamond::{PlanarDomain, PlanarId, SphereId};
use quincunx_decoder::incremental::{PlanarRefiner, RefineError, Refined, Refiner, SphereRefiner};
use quincunx_decoder::lattice::write_lattice;
use quincunx_decoder::raster::{self, DiamondSlot};
use quincunx_decoder::sphere_raster::{SphereFrame, SphereSlot};
use quincunx_meta::channels::split_channels;
use quincunx_meta::{Domain as MetaDomain, Metadata};

use crate::wire::{Reader, WireError};

/// Most values (samples times channels) a reconstruction holds: with the output, 8 bytes
/// each, half of a 32-bit module's 4 GiB memory.
pub const MAX_VALUES: usize = 1 << 28;

/// Input `u32 meta_len, metadata JSON, u32 count, (key, u32 len, bytes)*` (each diamond's
/// stored blob by its fetch key); output `u32 channels, u32 samples, i32 values` (channel
/// after channel, canonical order), all little-endian.
pub fn reconstruct_call(input: &[u8]) -> Result<Vec<u8>, String> {
    let (meta, blobs) = parse(input)?;
    let channels = match meta.domain {
        MetaDomain::Planar => reconstruct::<Plane>(&meta, blobs)?,
        MetaDomain::Sphere => reconstruct::<Cube>(&meta, blobs)?,
    };
    output(channels)
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

/// `u32 channels, u32 samples`, then each channel's values.
fn output(channels: Vec<Vec<i32>>) -> Result<Vec<u8>, String> {
    let samples = channels.first().map_or(0, Vec::len);
    let header = |v: usize| u32::try_from(v).map_err(|_| format!("{v} does not fit a u32"));
    let len = channels
        .len()
        .checked_mul(samples)
        .and_then(|v| v.checked_mul(4))
        .and_then(|v| v.checked_add(8))
        .ok_or("the output does not fit in memory")?;
    let mut out = Vec::new();
    out.try_reserve_exact(len)
        .map_err(|_| format!("the output ({len} bytes) does not fit in memory"))?;
    out.extend_from_slice(&header(channels.len())?.to_le_bytes());
    out.extend_from_slice(&header(samples)?.to_le_bytes());
    out.resize(len, 0);
    // Each channel is freed once copied.
    for (values, dst) in channels
        .into_iter()
        .zip(out[8..].chunks_exact_mut(4 * samples.max(1)))
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
/// channel with its own refiner; `blobs` by fetch key. One raster per channel.
fn reconstruct<C: Canvas>(
    meta: &Metadata,
    mut blobs: HashMap<Key, &[u8]>,
) -> Result<Vec<Vec<i32>>, String> {
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
    if len.saturating_mul(count) > MAX_VALUES {
        return Err(format!(
            "{count} x {len} values are too many to reconstruct in memory (at most {MAX_VALUES})"
        ));
    }
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
    Ok(rasters)
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
