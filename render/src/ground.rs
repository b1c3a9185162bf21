//! The streamed surface under a point: what "metres above the terrain" means for a
//! camera (`quincunx render --height-m`, the viewer's fly mode), and [`SurfaceIndex`], a
//! copy of a cut's triangles as drawn with a bucket index, for many queries (the image
//! error measures of [`crate::error`]).

use std::collections::HashMap;
use std::sync::{Arc, OnceLock};

use glam::DVec3;
use quincunx_client::dag::{Dag, Half};
use quincunx_client::session::Session;

use crate::RenderError;
use crate::domain::{AffinePatch, Geometry, RenderDomain, WorldFrame};

/// Height (metres) of the current cut's surface below `eye` (along the up direction:
/// `+z` on the plane, the radius on a planet), where that line meets the patches' grid
/// triangles as they are drawn (on a planet: flat chords between the vertices, not an
/// interpolation in face coordinates). `None` outside the data (past the planar raster).
/// Costs a pass over the cut; [`SurfaceIndex`] answers many queries.
pub fn surface_height_m<R: RenderDomain>(session: &Session<R>, eye: DVec3) -> Option<f64> {
    let dag = session.dag();
    let world = dag.refiner().world_frame(&session.world(), 0);
    if !eye.is_finite() {
        return None;
    }
    let up = up_at(&world, eye);
    let footprints = footprints(&world, eye);
    let n = f64::from(world.n);
    let mut near = Vec::new();
    for (id, half) in dag.cut() {
        let Some(node) = dag.node(id) else { continue };
        let Some(a) = dag.refiner().affine(id, &node.corners, half) else {
            continue;
        };
        let Some(p) = index_patch(&world, a, half, Arc::clone(&node.grid)) else {
            continue;
        };
        let Some(c) = footprints.on(p.face) else {
            continue;
        };
        let g = p.grid_of(c);
        if p.contains(n, g, INSIDE_EPS)
            && let Some((_, r)) = hit_cells(&world, &p, g, 0, eye, up)
        {
            return Some(height_m(&world, r));
        }
        if p.contains(n, g, 1.0) {
            near.push((p, g));
        }
    }
    near.iter()
        .filter_map(|(p, g)| hit_cells(&world, p, *g, 1, eye, up))
        .min_by(|a, b| a.0.total_cmp(&b.0))
        .map(|(_, r)| height_m(&world, r))
}

/// Height above the datum (metres) of a surface point.
fn height_m(world: &WorldFrame, r: DVec3) -> f64 {
    match world.geometry {
        Geometry::Planar { .. } => r.z,
        Geometry::Planet { radius_m, .. } => r.length() - radius_m,
    }
}

fn up_at(world: &WorldFrame, x: DVec3) -> DVec3 {
    match world.geometry {
        Geometry::Planar { .. } => DVec3::Z,
        Geometry::Planet { .. } => x.normalize_or(DVec3::Z),
    }
}

/// A cut's surface exactly as the renderer draws it, in f64: every patch's `N^2`
/// triangles (the grid cells split along `i = j` as [`crate::renderer::grid_indices`]
/// does), vertices at [`WorldFrame::point`] of their fine points and grid values, the
/// planar raster clip included. It owns copies of what it needs (affine maps, halves,
/// shared grids, the world frame), so the session can go on refining.
///
/// Queries find the patch under a point through buckets over the patches' footprints in
/// fine units (the plane's `x, y`; a planet's cube face coordinates, one family of
/// buckets per face), one bucket size per power of two of patch size, so a query looks at
/// a handful of candidates whatever the spread of levels in the cut.
#[derive(Clone, Debug)]
pub struct SurfaceIndex {
    world: WorldFrame,
    patches: Vec<IndexedPatch>,
    /// `(face, log2 bucket side, bucket x, bucket y)` -> patches whose footprint, grown by
    /// one cell, meets the bucket.
    buckets: HashMap<(u8, u8, i64, i64), Vec<u32>>,
    /// Per face (planar: face 0), the bucket sizes in use.
    sizes: [Vec<u8>; 6],
    skipped: usize,
    /// Each patch's bounding box (min, max corners), made by the first ray query.
    boxes: OnceLock<Vec<[DVec3; 2]>>,
}

#[derive(Clone, Debug)]
struct IndexedPatch {
    affine: AffinePatch,
    half: Half,
    grid: Arc<Vec<i32>>,
    face: u8,
    /// The fine-point coordinates spanning the patch's plane.
    axes: [usize; 2],
    /// Grid `(i, j)` from those coordinates relative to the base (row-major 2x2).
    grid_from_fine: [f64; 4],
}

/// Grid units a point may lie outside a patch and still count as inside it.
const INSIDE_EPS: f64 = 1e-7;
/// Barycentric slack of the line-triangle test (shared edges are hit from both sides).
const EDGE_EPS: f64 = 1e-12;

impl IndexedPatch {
    /// Grid coordinates of the footprint point `c` (fine units in `axes`).
    fn grid_of(&self, c: [f64; 2]) -> (f64, f64) {
        let b = [
            c[0] - self.affine.base[self.axes[0]] as f64,
            c[1] - self.affine.base[self.axes[1]] as f64,
        ];
        let m = self.grid_from_fine;
        (m[0] * b[0] + m[1] * b[1], m[2] * b[0] + m[3] * b[1])
    }

    /// Whether grid point `(fi, fj)` lies in the half grown by `margin` grid units.
    fn contains(&self, n: f64, (fi, fj): (f64, f64), margin: f64) -> bool {
        fi >= -margin
            && fj >= -margin
            && fi <= n + margin
            && fj <= n + margin
            && match self.half {
                Half::Lower => fi >= fj - margin,
                Half::Upper => fi <= fj + margin,
            }
    }
}

impl SurfaceIndex {
    /// The index of `session`'s current cut ([`Dag::cut`]: what a renderer synced to the
    /// session draws).
    pub fn new<R: RenderDomain>(session: &Session<R>) -> SurfaceIndex {
        SurfaceIndex::from_dag(session.dag(), &session.world())
    }

    /// The index of a DAG's current cut, for a repository mapped by `world`.
    pub fn from_dag<R: RenderDomain>(dag: &Dag<R>, world: &R::World) -> SurfaceIndex {
        let frame = dag.refiner().world_frame(world, 0);
        let cut = dag.cut();
        let total = cut.len();
        let patches: Vec<_> = cut
            .into_iter()
            .filter_map(|(id, half)| {
                let node = dag.node(id)?;
                let affine = dag.refiner().affine(id, &node.corners, half)?;
                Some((affine, half, Arc::clone(&node.grid)))
            })
            .collect();
        let missing = total - patches.len();
        let mut index = SurfaceIndex::from_patches(frame, patches);
        index.skipped += missing;
        index
    }

    /// The index of explicit patches: each one's affine map, half and `(N+1)^2` grid
    /// (row `i`, column `j`). Patches the index cannot use (a grid of the wrong size, a
    /// singular map, a planet patch off the cube's faces) are skipped and counted
    /// ([`SurfaceIndex::skipped`]).
    pub fn from_patches(
        world: WorldFrame,
        patches: impl IntoIterator<Item = (AffinePatch, Half, Arc<Vec<i32>>)>,
    ) -> SurfaceIndex {
        let mut index = SurfaceIndex {
            world,
            patches: Vec::new(),
            buckets: HashMap::new(),
            sizes: Default::default(),
            skipped: 0,
            boxes: OnceLock::new(),
        };
        for (affine, half, grid) in patches {
            match index_patch(&world, affine, half, grid) {
                Some(p) => {
                    index.insert(p);
                }
                None => index.skipped += 1,
            }
        }
        for sizes in &mut index.sizes {
            sizes.sort_unstable();
            sizes.dedup();
        }
        index
    }

    fn insert(&mut self, p: IndexedPatch) {
        let n = self.world.n as usize;
        let corners = match p.half {
            Half::Lower => [(0, 0), (n, 0), (n, n)],
            Half::Upper => [(0, 0), (0, n), (n, n)],
        };
        let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
        for (i, j) in corners {
            let f = p.affine.at(i, j);
            for k in 0..2 {
                let c = f[p.axes[k]] as f64;
                lo[k] = lo[k].min(c);
                hi[k] = hi[k].max(c);
            }
        }
        // One cell of margin: queries near a border also try the cells across it.
        let cell = p
            .axes
            .iter()
            .flat_map(|&k| [p.affine.e1[k].abs(), p.affine.e2[k].abs()])
            .max()
            .unwrap_or(1) as f64;
        let extent = (hi[0] - lo[0]).max(hi[1] - lo[1]) + 2.0 * cell;
        let log2 = (extent.max(1.0).log2().ceil() as u8).min(62);
        let side = (1u64 << log2) as f64;
        let at = self.patches.len() as u32;
        let b0 = [0, 1].map(|k| ((lo[k] - cell) / side).floor() as i64);
        let b1 = [0, 1].map(|k| ((hi[k] + cell) / side).floor() as i64);
        for bx in b0[0]..=b1[0] {
            for by in b0[1]..=b1[1] {
                self.buckets
                    .entry((p.face, log2, bx, by))
                    .or_default()
                    .push(at);
            }
        }
        self.sizes[usize::from(p.face)].push(log2);
        self.patches.push(p);
    }

    /// The world frame of the surface (with any [`SurfaceIndex::with_offset_m`] applied).
    pub fn world(&self) -> &WorldFrame {
        &self.world
    }

    /// Patches indexed.
    pub fn patches(&self) -> usize {
        self.patches.len()
    }

    /// Cut patches left out (no node, not affine, or unusable: a bug upstream if not 0).
    pub fn skipped(&self) -> usize {
        self.skipped
    }

    /// The same surface with every vertex `offset_m` metres further along the local up
    /// (a known displacement, for tests of the error measures). Errors when the offset is
    /// not finite.
    pub fn with_offset_m(mut self, offset_m: f64) -> Result<SurfaceIndex, RenderError> {
        if !offset_m.is_finite() {
            return Err(RenderError::Config(format!(
                "surface offset {offset_m} m is not finite"
            )));
        }
        self.world.value_offset_m += offset_m;
        self.boxes = OnceLock::new();
        Ok(self)
    }

    /// The first point where the ray from `origin` along `dir` meets the surface's
    /// triangles as drawn (the smallest positive parameter; exact in f64), `None` where
    /// it meets none. What a pixel whose centre's ray this is shows, with no rasteriser
    /// in between. Tests the triangles of every patch whose bounding box the ray meets
    /// (the boxes are made by the first query): a pass over the patches per query, for
    /// checking a few pixels ([`crate::error::recheck`]), not whole images.
    pub fn first_hit(&self, origin: DVec3, dir: DVec3) -> Option<DVec3> {
        if !(origin.is_finite() && dir.is_finite()) || dir == DVec3::ZERO {
            return None;
        }
        let boxes = self.boxes.get_or_init(|| {
            self.patches
                .iter()
                .map(|p| patch_box(&self.world, p))
                .collect()
        });
        let n = self.world.n as usize;
        let mut best: Option<(f64, DVec3)> = None;
        for (p, b) in self.patches.iter().zip(boxes) {
            let Some(enter) = ray_box(origin, dir, b) else {
                continue;
            };
            if best.is_some_and(|(s, _)| enter > s) {
                continue;
            }
            for i in 0..n {
                for j in 0..n {
                    for tri in cell_triangles(p.half, i, j).into_iter().flatten() {
                        let v = tri.map(|(i, j)| vertex(&self.world, p, i, j));
                        if let Some((s, r)) = line_triangle(origin, dir, v)
                            && s > 0.0
                            && drawn(&self.world, r)
                            && best.is_none_or(|(b, _)| s < b)
                        {
                            best = Some((s, r));
                        }
                    }
                }
            }
        }
        best.map(|(_, r)| r)
    }

    /// The local up direction at `x` (unit): `+z` on the plane, radial from the planet's
    /// centre on a planet (`+z` at the centre itself).
    pub fn up(&self, x: DVec3) -> DVec3 {
        up_at(&self.world, x)
    }

    /// The point where the line `x + s up` (`s` of either sign) meets the surface's
    /// triangles, the nearest to `x` if several; `None` where it meets none (outside the
    /// data, past the planar raster). The candidates are the cells around the footprint
    /// of `x` (its `x, y` on the plane, its direction from a planet's centre), so `up`
    /// should be the local up ([`SurfaceIndex::up`]) or close to it; the intersection
    /// itself is exact for the line given (f64).
    pub fn along(&self, x: DVec3, up: DVec3) -> Option<DVec3> {
        self.along_hinted(x, up, &mut None)
    }

    /// [`SurfaceIndex::along`], trying the patch of the previous query first (queries of
    /// neighbouring pixels mostly land in the same patch).
    pub(crate) fn along_hinted(
        &self,
        x: DVec3,
        up: DVec3,
        hint: &mut Option<u32>,
    ) -> Option<DVec3> {
        if !(x.is_finite() && up.is_finite()) || up == DVec3::ZERO {
            return None;
        }
        let n = self.world.n as f64;
        let footprints = footprints(&self.world, x);
        // The patch containing the footprint: its central cell.
        if let Some(h) = *hint
            && let Some(p) = self.patches.get(h as usize)
            && let Some(c) = footprints.on(p.face)
        {
            let g = p.grid_of(c);
            if p.contains(n, g, INSIDE_EPS)
                && let Some((_, r)) = hit_cells(&self.world, p, g, 0, x, up)
            {
                return Some(r);
            }
        }
        let mut candidates = Vec::new();
        let mut best: Option<(f64, DVec3)> = None;
        for &(face, c) in footprints.all() {
            candidates.clear();
            self.candidates(face, c, &mut candidates);
            for &k in &candidates {
                let p = &self.patches[k as usize];
                let g = p.grid_of(c);
                if p.contains(n, g, INSIDE_EPS)
                    && let Some((_, r)) = hit_cells(&self.world, p, g, 0, x, up)
                {
                    *hint = Some(k);
                    return Some(r);
                }
            }
            // Near a cell or patch border (or where the planet's cells bend away from
            // the flat triangles): the cells around, in every patch nearby.
            for &k in &candidates {
                let p = &self.patches[k as usize];
                let g = p.grid_of(c);
                if p.contains(n, g, 1.0)
                    && let Some((s, r)) = hit_cells(&self.world, p, g, 1, x, up)
                    && best.is_none_or(|(b, _)| s.abs() < b)
                {
                    best = Some((s.abs(), r));
                    *hint = Some(k);
                }
            }
            if best.is_some() {
                break;
            }
        }
        best.map(|(_, r)| r)
    }

    fn candidates(&self, face: u8, c: [f64; 2], out: &mut Vec<u32>) {
        for &log2 in &self.sizes[usize::from(face)] {
            let side = (1u64 << log2) as f64;
            let key = (
                face,
                log2,
                (c[0] / side).floor() as i64,
                (c[1] / side).floor() as i64,
            );
            if let Some(list) = self.buckets.get(&key) {
                out.extend_from_slice(list);
            }
        }
    }
}

/// Up to three faces with the footprint of a point on each.
struct Footprints {
    items: [(u8, [f64; 2]); 3],
    len: usize,
}

impl Footprints {
    fn all(&self) -> &[(u8, [f64; 2])] {
        &self.items[..self.len]
    }

    fn on(&self, face: u8) -> Option<[f64; 2]> {
        self.all().iter().find(|(f, _)| *f == face).map(|fc| fc.1)
    }
}

/// The faces to look on and the footprint of `x` on each: the plane's `x, y` in fine
/// units; on a planet the face `x` points at first (then, at a cube edge or corner, the
/// faces it ties with), in that face's fine coordinates (the inverse equal-angle map).
fn footprints(world: &WorldFrame, x: DVec3) -> Footprints {
    let mut out = Footprints {
        items: [(0, [0.0; 2]); 3],
        len: 0,
    };
    match world.geometry {
        Geometry::Planar {
            metres_per_fine, ..
        } => {
            out.items[0] = (0, [x.x / metres_per_fine, x.y / metres_per_fine]);
            out.len = 1;
        }
        Geometry::Planet { half_side_fine, .. } => {
            let d = x.to_array();
            let big = d.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            if big == 0.0 || !big.is_finite() {
                return out;
            }
            let s = half_side_fine as f64;
            let mut axes = [0usize, 1, 2];
            axes.sort_by(|&a, &b| d[b].abs().total_cmp(&d[a].abs()));
            for k in axes {
                if d[k].abs() < big * (1.0 - 1e-9) {
                    break;
                }
                let c = other_axes(k)
                    .map(|a| (d[a] / d[k].abs()).atan() / std::f64::consts::FRAC_PI_4 * s);
                out.items[out.len] = (face_of(k, d[k] > 0.0), c);
                out.len += 1;
            }
        }
    }
    out
}

/// The nearest intersection of the line `x + s up` with the half's triangles in the
/// cells within `reach` of the cell of grid point `g`: `(|s|, point)`.
fn hit_cells(
    world: &WorldFrame,
    p: &IndexedPatch,
    g: (f64, f64),
    reach: i64,
    x: DVec3,
    up: DVec3,
) -> Option<(f64, DVec3)> {
    let n = i64::from(world.n);
    let ci = (g.0.floor() as i64).clamp(0, n - 1);
    let cj = (g.1.floor() as i64).clamp(0, n - 1);
    let mut best: Option<(f64, DVec3)> = None;
    for i in (ci - reach).max(0)..=(ci + reach).min(n - 1) {
        for j in (cj - reach).max(0)..=(cj + reach).min(n - 1) {
            for tri in cell_triangles(p.half, i as usize, j as usize)
                .into_iter()
                .flatten()
            {
                let v = tri.map(|(i, j)| vertex(world, p, i, j));
                if let Some((s, r)) = line_triangle(x, up, v)
                    && drawn(world, r)
                    && best.is_none_or(|(b, _)| s.abs() < b)
                {
                    best = Some((s.abs(), r));
                }
            }
        }
    }
    best
}

fn vertex(world: &WorldFrame, p: &IndexedPatch, i: usize, j: usize) -> DVec3 {
    let n = world.n as usize;
    let v = p.grid.get(i * (n + 1) + j).copied().unwrap_or(0);
    world.point(p.affine.at(i, j), v)
}

/// Whether a surface point is drawn: inside the planar raster (the shader discards
/// fragments outside it, in f32: a relative slack of 1e-5 of its size); everywhere on a
/// planet.
fn drawn(world: &WorldFrame, r: DVec3) -> bool {
    match world.geometry {
        Geometry::Planar {
            metres_per_fine,
            extent_fine,
        } => {
            let e = extent_fine.map(|v| v as f64 * metres_per_fine);
            let slack = 1e-5 * e[0].max(e[1]).max(1.0);
            r.x >= -slack && r.y >= -slack && r.x <= e[0] + slack && r.y <= e[1] + slack
        }
        Geometry::Planet { .. } => true,
    }
}

/// The bounding box of a patch's vertices (its triangles are flat between them), grown
/// by a relative 1e-9 for rounding.
fn patch_box(world: &WorldFrame, p: &IndexedPatch) -> [DVec3; 2] {
    let n = world.n as usize;
    let (mut lo, mut hi) = (DVec3::INFINITY, DVec3::NEG_INFINITY);
    for i in 0..=n {
        for j in 0..=n {
            let inside = match p.half {
                Half::Lower => i >= j,
                Half::Upper => i <= j,
            };
            if inside {
                let v = vertex(world, p, i, j);
                lo = lo.min(v);
                hi = hi.max(v);
            }
        }
    }
    let grow = DVec3::splat(1e-9 * lo.abs().max(hi.abs()).max_element().max(1.0));
    [lo - grow, hi + grow]
}

/// Where the ray `origin + s dir` (`s >= 0`) enters the box, `None` if it misses it.
fn ray_box(origin: DVec3, dir: DVec3, b: &[DVec3; 2]) -> Option<f64> {
    let (mut enter, mut leave) = (0.0f64, f64::INFINITY);
    for k in 0..3 {
        let (o, d, lo, hi) = (origin[k], dir[k], b[0][k], b[1][k]);
        if d == 0.0 {
            if o < lo || o > hi {
                return None;
            }
            continue;
        }
        let (a, c) = ((lo - o) / d, (hi - o) / d);
        enter = enter.max(a.min(c));
        leave = leave.min(a.max(c));
    }
    (enter <= leave).then_some(enter)
}

/// The planet face of axis `k` and sign (`2 k + positive`).
fn face_of(k: usize, positive: bool) -> u8 {
    (2 * k + usize::from(positive)) as u8
}

fn other_axes(k: usize) -> [usize; 2] {
    match k {
        0 => [1, 2],
        1 => [0, 2],
        _ => [0, 1],
    }
}

fn index_patch(
    world: &WorldFrame,
    affine: AffinePatch,
    half: Half,
    grid: Arc<Vec<i32>>,
) -> Option<IndexedPatch> {
    let n = world.n as usize;
    if n == 0 || grid.len() != (n + 1) * (n + 1) {
        return None;
    }
    let (face, axes) = match world.geometry {
        Geometry::Planar { .. } => (0, [0, 1]),
        Geometry::Planet { half_side_fine, .. } => {
            let k = (0..3).find(|&k| affine.e1[k] == 0 && affine.e2[k] == 0)?;
            if affine.base[k].abs() != half_side_fine {
                return None;
            }
            (face_of(k, affine.base[k] > 0), other_axes(k))
        }
    };
    let (a11, a12) = (affine.e1[axes[0]] as f64, affine.e2[axes[0]] as f64);
    let (a21, a22) = (affine.e1[axes[1]] as f64, affine.e2[axes[1]] as f64);
    let det = a11 * a22 - a12 * a21;
    if det == 0.0 {
        return None;
    }
    Some(IndexedPatch {
        affine,
        half,
        grid,
        face,
        axes,
        grid_from_fine: [a22 / det, -a12 / det, -a21 / det, a11 / det],
    })
}

/// The triangles of grid cell `(i, j)` (corners `(i, j)`, `(i+1, j+1)`) that belong to
/// `half`, as [`crate::renderer::grid_indices`] lists them.
fn cell_triangles(half: Half, i: usize, j: usize) -> [Option<[(usize, usize); 3]>; 2] {
    let (a, b, c, d) = ((i, j), (i + 1, j), (i + 1, j + 1), (i, j + 1));
    match half {
        Half::Lower => [(i >= j).then_some([a, b, c]), (i > j).then_some([a, c, d])],
        Half::Upper => [(i <= j).then_some([a, c, d]), (i < j).then_some([a, b, c])],
    }
}

/// Where the line `x + s d` meets triangle `v` (its closed inside, with a slack of
/// [`EDGE_EPS`] in barycentric terms): `(s, point)`. Möller-Trumbore, both signs of `s`.
fn line_triangle(x: DVec3, d: DVec3, v: [DVec3; 3]) -> Option<(f64, DVec3)> {
    let e1 = v[1] - v[0];
    let e2 = v[2] - v[0];
    let pv = d.cross(e2);
    let det = e1.dot(pv);
    if det == 0.0 || !det.is_finite() {
        return None;
    }
    let inv = 1.0 / det;
    let t = x - v[0];
    let a = t.dot(pv) * inv;
    if !(-EDGE_EPS..=1.0 + EDGE_EPS).contains(&a) {
        return None;
    }
    let q = t.cross(e1);
    let b = d.dot(q) * inv;
    if b < -EDGE_EPS || a + b > 1.0 + EDGE_EPS {
        return None;
    }
    let s = e2.dot(q) * inv;
    Some((s, x + d * s))
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use super::*;
    use crate::renderer::grid_indices;

    #[test]
    fn cell_triangles_are_the_drawn_triangles() {
        let n = 6usize;
        let (idx, half_len) = grid_indices(n as u32);
        let nv = n + 1;
        for (h, half) in Half::BOTH.into_iter().enumerate() {
            let drawn = &idx[h * half_len as usize..(h + 1) * half_len as usize];
            let mut ours = Vec::new();
            for i in 0..n {
                for j in 0..n {
                    for tri in cell_triangles(half, i, j).into_iter().flatten() {
                        ours.extend(tri.map(|(i, j)| (i * nv + j) as u32));
                    }
                }
            }
            assert_eq!(ours, drawn, "{half:?}");
        }
    }

    #[test]
    fn line_meets_a_triangle_inside_and_misses_outside() {
        let v = [
            DVec3::ZERO,
            DVec3::new(2.0, 0.0, 1.0),
            DVec3::new(2.0, 2.0, 2.0),
        ];
        let (s, r) = line_triangle(DVec3::new(1.5, 0.5, 10.0), DVec3::Z, v).unwrap();
        assert!((r - DVec3::new(1.5, 0.5, 1.0)).length() < 1e-12 && (s + 9.0).abs() < 1e-12);
        let (s, _) = line_triangle(DVec3::new(1.5, 0.5, -3.0), DVec3::Z, v).unwrap();
        assert!((s - 4.0).abs() < 1e-12);
        assert!(line_triangle(DVec3::new(0.5, 1.5, 0.0), DVec3::Z, v).is_none());
        assert!(line_triangle(DVec3::new(0.5, 0.5, 0.0), DVec3::X, v).is_none());
    }
}
