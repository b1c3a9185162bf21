//! Every diamond's error bound, measured: the build's last pass.
//!
//! A diamond's blob carries, for each child it owns, a side-information class whose
//! [`class_bound`] (value quanta) bounds how far the finest decoded surface beneath that
//! child departs from the surface the child draws, and the client's geometric metric
//! refines by it. The encoder's classes bound the departure by a sum over levels of each
//! level's largest step, 4x the true departure at the median on korea. This pass
//! replaces them, in every build path (it runs on the published repository, and the
//! in-memory, out-of-core and sharded builds publish the same bytes, so they get the
//! same bounds), by what the decode measures:
//!
//! 1. A tile at a time ([`TILE_SAMPLES`] a side, overlapping by one sample), the
//!    diamonds over the tile and their ancestors are decoded top-down as a client decodes
//!    them (the client's refiners: decode, synthesise, cut each child's grid from its
//!    parents' lattices); the finest level's lattices fill the tile with the
//!    full-resolution decode, and a second walk measures each diamond there.
//! 2. A diamond's **departure** is the largest `|surface - decoded|` over its two halves
//!    on the continuum ([`half_departure`]: every sample, and every centre of four
//!    samples, where the two triangulations can cross), exact in integers and rounded up
//!    to whole quanta: the largest over the tiles it meets.
//! 3. Bottom-up, its **bound** is the largest of its departure and its coded children's
//!    bounds (monotone up the DAG). A diamond with no valid sample of its own (sparse)
//!    takes its subtree's whole range. The client's box, its grid's range widened by the
//!    bound, holds the full-resolution surface beneath it.
//! 4. Each blob is coded again (blob version 6) with its owned children's classes of
//!    those bounds ([`gamma_class`]: rounded up, at most sqrt 2 too large) and the same
//!    details. A child with nothing below it that has a blob (flagged no-data: no client
//!    ever asks for its subtree) also gets a **profile**: per level below it, the class
//!    of its descendants' largest bound, so that they are not bounded by its own class
//!    all the way down. A diamond without a blob but with data below it, which clients
//!    ask for anyway, gets a blob of zero details to carry its children's classes.
//!
//! Colour repositories keep the encoder's classes: their layer refines by its texel rule.
//! The pass holds one tile's decode and the lattices over it, the DAG and a few figures
//! per diamond, and up to 1,024 blobs coded again (more wait in a file once the
//! repository's blobs pass 8 MB): not the whole decode, so it keeps out-of-core builds'
//! memory budgets. The bounds do not depend on the tiles' size.

use std::collections::{HashMap, HashSet};
use std::path::Path;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use quincunx_client::open::{planar_channel_refiner, sphere_channel_refiner};
use quincunx_codec::diamond::sphere::{axes, chart_of};
use quincunx_codec::entropy::{NO_DATA, class_bound, gamma_class, split_side};
use quincunx_codec::incremental::{PlanarRefiner, Refined, Refiner, SphereRefiner};
use quincunx_codec::lifting::DiamondMask;
use quincunx_store::{AttributeKind, Domain, Metadata, Repository, RepositoryBuilder};
use rayon::prelude::*;

/// Side of the pass's tiles in samples, by default: it holds one tile's decode (4 MB) and
/// the lattices of the diamonds over it.
pub const TILE_SAMPLES: i64 = 1024;

/// The tile side for a build's memory budget (MB; `None`: [`TILE_SAMPLES`]): the largest
/// power of two up to [`TILE_SAMPLES`] with 128 bytes of budget a sample of the tile
/// (256 at 16 MB: the pass's peak on the bundled korea crop is 12 MB; 512 at 32 MB: 25 MB
/// on the 16.8 M samples of korea at RMS 9 m).
pub fn tile_for_budget(budget_mb: Option<u64>) -> i64 {
    let Some(mb) = budget_mb else {
        return TILE_SAMPLES;
    };
    let bytes = i64::try_from(mb)
        .unwrap_or(i64::MAX)
        .saturating_mul(1 << 20);
    let mut tile = 64;
    while tile < TILE_SAMPLES && (2 * tile) * (2 * tile) * 128 <= bytes {
        tile *= 2;
    }
    tile
}

/// Repositories with more bytes of blobs than this have them coded again into a file,
/// not memory.
const SPILL_BYTES: u64 = 8 << 20;

/// What the bound pass needs of a domain besides its refiner: the chart each half of a
/// diamond lies in, and the decoded value of a chart point.
pub trait Charted: Refiner {
    /// The chart of a half (`lower`: vertices `i >= j`, the triangle `E1 P1 E2`; else
    /// `i <= j`, `E1 P2 E2`) and its corners `[E1, P, E2]` there (id units = samples).
    fn half_chart(&self, id: Self::Id, lower: bool) -> (u8, [[i64; 2]; 3]);
    /// The chart's sample box `[x0, x1, y0, y1]` (inclusive).
    fn chart_box(&self) -> [i64; 4];
    /// The charts (planar: one; planets: the six faces).
    fn charts(&self) -> Vec<u8>;
    /// Index in the full-resolution decode of sample `(x, y)` of `chart` (inside its box).
    fn sample_index(&self, chart: u8, x: i64, y: i64) -> usize;
    /// A child's vertex grid from its refined parents (the refiner's `child_grid`).
    fn grid_of(&self, child: Self::Id, parents: &[&Refined<Self::Id>]) -> Result<Vec<i32>>;
    /// Length of the full-resolution decode (planets: every copy of a cube-edge point).
    fn sample_len(&self) -> usize;
}

impl Charted for PlanarRefiner {
    fn half_chart(&self, id: Self::Id, lower: bool) -> (u8, [[i64; 2]; 3]) {
        let c = Refiner::corners(self, id).map(|p| [p[0], p[1]]);
        (0, [c[0], if lower { c[1] } else { c[3] }, c[2]])
    }

    fn chart_box(&self) -> [i64; 4] {
        let (w, h) = self.raster_size();
        [0, w as i64 - 1, 0, h as i64 - 1]
    }

    fn charts(&self) -> Vec<u8> {
        vec![0]
    }

    fn sample_index(&self, _chart: u8, x: i64, y: i64) -> usize {
        y as usize * self.raster_size().0 + x as usize
    }

    fn grid_of(&self, child: Self::Id, parents: &[&Refined<Self::Id>]) -> Result<Vec<i32>> {
        Ok(self.child_grid(child, parents)?)
    }

    fn sample_len(&self) -> usize {
        let (w, h) = self.raster_size();
        w * h
    }
}

impl Charted for SphereRefiner {
    fn half_chart(&self, id: Self::Id, lower: bool) -> (u8, [[i64; 2]; 3]) {
        let c = Refiner::corners(self, id);
        let tri = [c[0], if lower { c[1] } else { c[3] }, c[2]];
        let s = self.domain().size();
        // The face the whole triangle lies on (an edge diamond's halves are on two faces;
        // the domain puts each half on one).
        let face = (0..6u8)
            .find(|&f| {
                let ax = axes(f);
                tri.iter().all(|p| p[ax.a] == ax.s * s)
            })
            .unwrap_or(0);
        (face, tri.map(|p| chart_of(face, p, s)))
    }

    fn chart_box(&self) -> [i64; 4] {
        let side = self.frame().face_side() as i64;
        [0, side, 0, side]
    }

    fn charts(&self) -> Vec<u8> {
        (0..6).collect()
    }

    fn sample_index(&self, chart: u8, x: i64, y: i64) -> usize {
        self.frame().cube_index(chart, x as usize, y as usize)
    }

    fn grid_of(&self, child: Self::Id, parents: &[&Refined<Self::Id>]) -> Result<Vec<i32>> {
        Ok(self.child_grid(child, parents)?)
    }

    fn sample_len(&self) -> usize {
        self.frame().cube_len()
    }
}

/// A half's grid frame in its chart: vertex `(i, j)` at `e1 + (i a + j b) / N`.
#[derive(Clone, Copy, Debug)]
pub struct HalfFrame {
    /// The chart (planet face; 0 on a plane).
    pub chart: u8,
    /// Corner `E1`, where vertex `(0, 0)` lies.
    pub e1: [i64; 2],
    /// `N` times the step of `i`.
    pub a: [i64; 2],
    /// `N` times the step of `j`.
    pub b: [i64; 2],
    /// `|a|^2 = |b|^2`: a sample's grid coordinates are `I / d` with integer `I`.
    pub d: i64,
    /// The half with `i >= j`.
    pub lower: bool,
    /// The triangle's sample box `[x0, x1, y0, y1]`, clipped to the chart's.
    pub bbox: [i64; 4],
}

/// The frame of one half of `id`, or why it has none (corners that make no square).
pub fn half_frame<R: Charted>(r: &R, id: R::Id, lower: bool) -> Result<HalfFrame> {
    let (chart, [e1, p, e2]) = r.half_chart(id, lower);
    // The square's fourth corner: P1 + P2 = E1 + E2.
    let q = [e1[0] + e2[0] - p[0], e1[1] + e2[1] - p[1]];
    let (p1, p2) = if lower { (p, q) } else { (q, p) };
    let a = [p1[0] - e1[0], p1[1] - e1[1]];
    let b = [p2[0] - e1[0], p2[1] - e1[1]];
    let d = a[0] * a[0] + a[1] * a[1];
    if !(d > 0 && d == b[0] * b[0] + b[1] * b[1] && a[0] * b[0] + a[1] * b[1] == 0) {
        bail!("diamond {id:?}: its half's frame is not a square");
    }
    let [x0, x1, y0, y1] = r.chart_box();
    let (xs, ys) = ([e1[0], p[0], e2[0]], [e1[1], p[1], e2[1]]);
    let lo = |v: [i64; 3]| v.into_iter().min().unwrap_or(0);
    let hi = |v: [i64; 3]| v.into_iter().max().unwrap_or(0);
    Ok(HalfFrame {
        chart,
        e1,
        a,
        b,
        d,
        lower,
        bbox: [
            lo(xs).max(x0),
            hi(xs).min(x1),
            lo(ys).max(y0),
            hi(ys).min(y1),
        ],
    })
}

/// How far a diamond's surface departs from the full-resolution decode, and the range of
/// the decoded samples it covers.
#[derive(Clone, Copy, Debug, Default)]
pub struct Departure {
    /// Largest `|surface - decoded|`, times `d` (exact).
    pub worst: i128,
    /// The common denominator of the diamond's grid coordinates.
    pub d: i64,
    /// Sample points compared (per half: points on the hypotenuse count twice).
    pub points: u64,
    /// Lowest and highest decoded sample compared (`(i32::MAX, i32::MIN)` for none).
    pub fine: (i32, i32),
}

impl Departure {
    fn none(d: i64) -> Self {
        Departure {
            d,
            fine: (i32::MAX, i32::MIN),
            ..Departure::default()
        }
    }

    /// The departure rounded up to whole quanta.
    pub fn ceil_quanta(&self) -> u64 {
        if self.d <= 0 {
            return 0;
        }
        let d = i128::from(self.d);
        u64::try_from((self.worst + d - 1) / d).unwrap_or(u64::MAX)
    }

    /// Both halves' figures together.
    pub fn merge(&mut self, o: Departure) {
        self.d = o.d;
        self.worst = self.worst.max(o.worst);
        self.points += o.points;
        self.fine = (self.fine.0.min(o.fine.0), self.fine.1.max(o.fine.1));
    }
}

/// The departure of one half of a diamond whose vertex grid is `grid`, from the decode
/// in `window`, on the continuum: at every sample of the half, and at every centre of a
/// square of four samples (`(x + 1/2, y + 1/2)`) in it.
///
/// Both surfaces are linear on the two triangles of one diagonal of each such square:
/// the decode's (the finest diamonds' grids are the samples) and this diamond's (its
/// grid lines and cell diagonals run along sample rows, columns and 45-degree lines
/// through samples). Where they take the same diagonal, their difference is linear on
/// each triangle and largest at a sample; where not, at the centre, where each is the
/// mean of one diagonal's two samples. The centre is compared with both of the decode's
/// candidates (which diagonal the decode takes is not assumed), this diamond's value
/// there exactly. Points are compared where the cell triangle that holds them has three
/// valid vertices (ties on the cell diagonal go to this half's side).
///
/// Only the half's points in `window` are compared (none when it is another chart's): a
/// pass over tiles that overlap by one sample compares every point once or more.
pub fn half_departure<R: Charted>(
    r: &R,
    f: &HalfFrame,
    grid: &[i32],
    mask: Option<&DiamondMask>,
    window: &Window,
) -> Departure {
    let [x0, x1, y0, y1] = f.bbox;
    let [wx0, wx1, wy0, wy1] = window.bbox;
    let bbox = [x0.max(wx0), x1.min(wx1), y0.max(wy0), y1.min(wy1)];
    if f.chart != window.chart || bbox[0] > bbox[1] || bbox[2] > bbox[3] {
        return Departure::none(2 * f.d);
    }
    // Times `2d`, a surface value is at most `2d 2^31` and each product of the
    // interpolation `2d 2^32`: within `i64` while `2d < 2^28`.
    if 2 * f.d < 1 << 28 {
        departure_in::<R, i64>(r, f, grid, mask, window, bbox)
    } else {
        departure_in::<R, i128>(r, f, grid, mask, window, bbox)
    }
}

/// A tile of one chart and its part of the full-resolution decode.
pub struct Window {
    /// The chart (planet face; 0 on a plane).
    pub chart: u8,
    /// Its samples `[x0, x1, y0, y1]` (inclusive).
    pub bbox: [i64; 4],
    /// Their decoded values, row by row.
    pub values: Vec<i32>,
}

impl Window {
    /// The tile `bbox` of `chart`, every value 0.
    pub fn new(chart: u8, bbox: [i64; 4]) -> Window {
        let [x0, x1, y0, y1] = bbox;
        let len = usize::try_from((x1 - x0 + 1).max(0) * (y1 - y0 + 1).max(0)).unwrap_or(0);
        Window {
            chart,
            bbox,
            values: vec![0; len],
        }
    }

    /// Index of sample `(x, y)` in [`Window::values`], if it is in the tile.
    pub fn index(&self, chart: u8, x: i64, y: i64) -> Option<usize> {
        let [x0, x1, y0, y1] = self.bbox;
        let inside = chart == self.chart && (x0..=x1).contains(&x) && (y0..=y1).contains(&y);
        inside.then(|| self.offset(x, y))
    }

    /// The decoded value of sample `(x, y)` of the tile.
    fn at(&self, x: i64, y: i64) -> i32 {
        self.values[self.offset(x, y)]
    }

    /// Where sample `(x, y)` of the tile is in [`Window::values`].
    fn offset(&self, x: i64, y: i64) -> usize {
        let [x0, x1, y0, _] = self.bbox;
        ((y - y0) * (x1 - x0 + 1) + (x - x0)) as usize
    }
}

/// Integers wide enough for [`half_departure`]'s exact arithmetic.
trait Wide:
    Copy
    + Ord
    + From<i64>
    + Into<i128>
    + std::ops::Add<Output = Self>
    + std::ops::Sub<Output = Self>
    + std::ops::Mul<Output = Self>
{
}

impl Wide for i64 {}
impl Wide for i128 {}

fn abs<T: Wide>(x: T) -> T {
    let zero = T::from(0);
    if x < zero { zero - x } else { x }
}

fn departure_in<R: Charted, T: Wide>(
    r: &R,
    f: &HalfFrame,
    grid: &[i32],
    mask: Option<&DiamondMask>,
    window: &Window,
    bbox: [i64; 4],
) -> Departure {
    let n = r.n() as i64;
    let w = r.n() + 1;
    let valid = |i: i64, j: i64| mask.is_none_or(|m| m.vertex(i as usize, j as usize));
    let v = |i: i64, j: i64| T::from(i64::from(grid[i as usize * w + j as usize]));
    // This half's surface at the point `(x2, y2) / 2` (doubled sample coordinates), times
    // `2 d`; `None` outside the half or over an invalid triangle.
    let surface = |x2: i64, y2: i64| -> Option<T> {
        let d = 2 * f.d;
        let nd = n * d;
        let (dx, dy) = (x2 - 2 * f.e1[0], y2 - 2 * f.e1[1]);
        let gi = n * (dx * f.a[0] + dy * f.a[1]);
        let gj = n * (dx * f.b[0] + dy * f.b[1]);
        let inside = if f.lower {
            0 <= gj && gj <= gi && gi <= nd
        } else {
            0 <= gi && gi <= gj && gj <= nd
        };
        if !inside {
            return None;
        }
        let (ci, cj) = ((gi / d).min(n - 1), (gj / d).min(n - 1));
        let (fi, fj) = (T::from(gi - ci * d), T::from(gj - cj * d));
        let lower_tri = fi > fj || (fi == fj && f.lower);
        let third = if lower_tri {
            (ci + 1, cj)
        } else {
            (ci, cj + 1)
        };
        if !(valid(ci, cj) && valid(third.0, third.1) && valid(ci + 1, cj + 1)) {
            return None;
        }
        let (v00, v11) = (v(ci, cj), v(ci + 1, cj + 1));
        Some(if lower_tri {
            let v10 = v(ci + 1, cj);
            T::from(d) * v00 + fi * (v10 - v00) + fj * (v11 - v10)
        } else {
            let v01 = v(ci, cj + 1);
            T::from(d) * v00 + fj * (v01 - v00) + fi * (v11 - v01)
        })
    };
    let d2 = T::from(2 * f.d);
    let sample = |x: i64, y: i64| T::from(i64::from(window.at(x, y)));
    let mut out = Departure::none(2 * f.d);
    let [x0, x1, y0, y1] = bbox;
    for y in y0..=y1 {
        // Only the row's span inside the triangle (one more each side: `surface` decides).
        let (lo, hi) = row_span(f, n, 0, 2 * y);
        for x in (lo - 1).max(x0)..=(hi + 1).min(x1) {
            if let Some(s) = surface(2 * x, 2 * y) {
                let value = window.at(x, y);
                out.worst = out
                    .worst
                    .max(abs(s - d2 * T::from(i64::from(value))).into());
                out.points += 1;
                out.fine = (out.fine.0.min(value), out.fine.1.max(value));
            }
        }
        if y == y1 {
            continue;
        }
        let (lo, hi) = row_span(f, n, 1, 2 * y + 1);
        for x in (lo - 1).max(x0)..=(hi + 1).min(x1 - 1) {
            if let Some(s) = surface(2 * x + 1, 2 * y + 1) {
                // Times 2d, each candidate is d times the sum of its diagonal's samples.
                let h = T::from(f.d);
                for fine in [
                    h * (sample(x, y) + sample(x + 1, y + 1)),
                    h * (sample(x + 1, y) + sample(x, y + 1)),
                ] {
                    out.worst = out.worst.max(abs(s - fine).into());
                }
            }
        }
    }
    out
}

/// The sample columns `x` whose points `(2x + o, y2) / 2` lie in the half `f` (`lo > hi`
/// for none): each of the triangle's three sides is a linear condition on `x`.
fn row_span(f: &HalfFrame, n: i64, o: i64, y2: i64) -> (i64, i64) {
    let dy = y2 - 2 * f.e1[1];
    let (ai, bi) = (
        2 * n * f.a[0],
        n * (f.a[0] * (o - 2 * f.e1[0]) + f.a[1] * dy),
    );
    let (aj, bj) = (
        2 * n * f.b[0],
        n * (f.b[0] * (o - 2 * f.e1[0]) + f.b[1] * dy),
    );
    let nd = n * 2 * f.d;
    // `alpha x + beta >= 0` for each side.
    let sides = if f.lower {
        [(aj, bj), (ai - aj, bi - bj), (-ai, nd - bi)]
    } else {
        [(ai, bi), (aj - ai, bj - bi), (-aj, nd - bj)]
    };
    let (mut lo, mut hi) = (i64::MIN / 4, i64::MAX / 4);
    for (alpha, beta) in sides {
        match alpha.signum() {
            1 => lo = lo.max(-(beta.div_euclid(alpha))),
            -1 => hi = hi.min(beta.div_euclid(-alpha)),
            _ if beta < 0 => return (1, 0),
            _ => {}
        }
    }
    (lo, hi)
}

/// One decoded diamond, as [`walk`] hands it over.
pub struct Decoded<I> {
    /// The diamond.
    pub id: I,
    /// Its detail level.
    pub level: usize,
    /// Its storage key (its blob's, when it has one).
    pub key: Vec<u8>,
    /// Its surface's departure from the decode.
    pub departure: Departure,
    /// Lowest and highest valid vertex of its grid (`None`: no valid vertex).
    pub grid_range: Option<(i32, i32)>,
    /// The side information its blob carries (empty without a blob).
    pub child_classes: Vec<(I, u8)>,
    /// Whether it has a blob.
    pub has_blob: bool,
    /// Its coded children.
    pub children: Vec<I>,
    /// Its refined lattices (the finest level's hold the decode at its samples; empty
    /// there when the walk measures).
    pub refined: Refined<I>,
    /// Its valid points.
    pub mask: Option<DiamondMask>,
}

/// A diamond's blob (one channel's part) by storage key.
pub type BlobOf<'a> = dyn Fn(&[u8]) -> Result<Option<Vec<u8>>> + Sync + 'a;

/// Decodes the coded diamonds of one channel top-down, a level at a time (those in `keep`,
/// which must hold the parents of each, or all), measuring each against the decode in
/// `window` (`None`: no measure), and hands each level to `visit` (in the level's order
/// of ids).
pub fn walk<R: Charted>(
    r: &R,
    blob_of: &BlobOf<'_>,
    keep: Option<&HashSet<R::Id>>,
    window: Option<&Window>,
    mut visit: impl FnMut(usize, &[Decoded<R::Id>]) -> Result<()>,
) -> Result<()> {
    let kept = |id: &R::Id| keep.is_none_or(|k| k.contains(id));
    let mut current: Vec<(R::Id, Vec<i32>)> = r
        .roots()
        .into_iter()
        .filter(|(id, _)| kept(id))
        .map(|(id, g)| (id, g.to_vec()))
        .collect();
    for level in 0..r.detail_levels() {
        // The finest level's lattices are only wanted without a measure (they are the
        // decode).
        let lattices = level + 1 < r.detail_levels() || window.is_none();
        let rows: Vec<Decoded<R::Id>> = current
            .into_par_iter()
            .map(|(id, grid)| decode_one(r, blob_of, window, level, id, &grid, lattices))
            .collect::<Result<_>>()?;
        visit(level, &rows)?;
        if level + 1 == r.detail_levels() {
            break;
        }
        // The next level's grids, each from its parents' lattices.
        let refined: HashMap<R::Id, &Refined<R::Id>> =
            rows.iter().map(|row| (row.id, &row.refined)).collect();
        let mut seen = HashSet::new();
        let kids: Vec<R::Id> = rows
            .iter()
            .flat_map(|row| row.children.iter().copied())
            .filter(|&c| kept(&c) && seen.insert(c))
            .collect();
        current =
            kids.into_par_iter()
                .map(|c| {
                    // Parents outside the data (the raster's border when it is not
                    // 2^k + 1 on a side) hold no part of the child.
                    let parents =
                        r.parents(c)
                            .iter()
                            .filter(|&&p| r.is_refinable(p))
                            .map(|p| {
                                refined.get(p).copied().with_context(|| {
                                    format!("parent {p:?} of {c:?} was not decoded")
                                })
                            })
                            .collect::<Result<Vec<_>>>()?;
                    Ok((c, r.grid_of(c, &parents)?))
                })
                .collect::<Result<_>>()?;
    }
    Ok(())
}

fn decode_one<R: Charted>(
    r: &R,
    blob_of: &BlobOf<'_>,
    window: Option<&Window>,
    level: usize,
    id: R::Id,
    grid: &[i32],
    lattices: bool,
) -> Result<Decoded<R::Id>> {
    let info = r
        .info(id)
        .with_context(|| format!("diamond {id:?} is not refinable"))?;
    if info.level != level {
        bail!(
            "diamond {id:?} is of level {}, reached at {level}",
            info.level
        );
    }
    let blob = blob_of(&info.key)?;
    let details = blob
        .as_deref()
        .map(|b| r.decode(id, b))
        .transpose()
        .with_context(|| format!("decoding diamond {id:?}"))?;
    let refined = if lattices {
        r.synthesize(id, grid, details.as_ref())?
    } else {
        Refined {
            id,
            vertices: Vec::new(),
            cells: Vec::new(),
            child_classes: Vec::new(),
            child_profiles: Vec::new(),
        }
    };
    let mask = info.mask;
    let mut departure = Departure::none(0);
    if let Some(window) = window {
        for lower in [true, false] {
            let f = half_frame(r, id, lower)?;
            departure.merge(half_departure(r, &f, grid, mask.as_ref(), window));
        }
    }
    let w = r.n() + 1;
    let grid_range = grid
        .iter()
        .enumerate()
        .filter(|&(k, _)| mask.as_ref().is_none_or(|m| m.vertex(k / w, k % w)))
        .fold(None, |acc: Option<(i32, i32)>, (_, &v)| {
            Some(acc.map_or((v, v), |(lo, hi)| (lo.min(v), hi.max(v))))
        });
    Ok(Decoded {
        id,
        level,
        key: info.key,
        departure,
        grid_range,
        child_classes: details.map(|d| d.child_classes).unwrap_or_default(),
        has_blob: blob.is_some(),
        children: info
            .children
            .into_iter()
            .filter(|&c| r.is_coded(c))
            .collect(),
        refined,
        mask,
    })
}

/// The full-resolution decode from the finest level's refined lattices (vertices and
/// cell centres, which are the samples), by one [`walk`] without measuring: what
/// [`crate::verify::decode_repository`] gives, holding only the result and one level's
/// lattices. `None` when a point of a dense repository is left unwritten.
pub fn finest_values<R: Charted>(
    r: &R,
    blob_of: &BlobOf<'_>,
    dense: bool,
) -> Result<Option<Vec<i32>>> {
    let len = r.sample_len();
    let mut values = vec![0i32; len];
    let mut written = vec![0u64; len.div_ceil(64)];
    let [x0, x1, y0, y1] = r.chart_box();
    walk_finest(r, blob_of, None, |chart, x, y, value| {
        if (x0..=x1).contains(&x) && (y0..=y1).contains(&y) {
            let k = r.sample_index(chart, x, y);
            values[k] = value;
            written[k / 64] |= 1 << (k % 64);
        }
    })?;
    let all = (0..len).all(|k| written[k / 64] & (1 << (k % 64)) != 0);
    Ok((!dense || all).then_some(values))
}

/// Fills `window` with the decode, from the finest level of a [`walk`] over `keep` (which
/// must hold every finest diamond over the tile); whether every sample was written.
fn fill_window<R: Charted>(
    r: &R,
    blob_of: &BlobOf<'_>,
    keep: &HashSet<R::Id>,
    window: &mut Window,
) -> Result<bool> {
    let mut written = vec![false; window.values.len()];
    walk_finest(r, blob_of, Some(keep), |chart, x, y, value| {
        if let Some(k) = window.index(chart, x, y) {
            window.values[k] = value;
            written[k] = true;
        }
    })?;
    Ok(written.into_iter().all(|w| w))
}

/// A [`walk`] over `keep` (or all) without measuring that hands every sample of the
/// finest level to `put(chart, x, y, value)`.
fn walk_finest<R: Charted>(
    r: &R,
    blob_of: &BlobOf<'_>,
    keep: Option<&HashSet<R::Id>>,
    mut put: impl FnMut(u8, i64, i64, i32),
) -> Result<()> {
    walk(r, blob_of, keep, None, |level, rows| {
        if level + 1 == r.detail_levels() {
            for row in rows {
                finest_points(r, row, &mut put)?;
            }
        }
        Ok(())
    })
}

/// Hands every sample of a finest-level diamond (the points of its refined lattices:
/// vertices and cell centres, each half's own) to `put(chart, x, y, value)`.
fn finest_points<R: Charted>(
    r: &R,
    row: &Decoded<R::Id>,
    mut put: impl FnMut(u8, i64, i64, i32),
) -> Result<()> {
    let n = r.n();
    let n64 = n as i64;
    for lower in [true, false] {
        let f = half_frame(r, row.id, lower)?;
        let mine = |i: usize, j: usize| if lower { i >= j } else { i <= j };
        // Doubled grid coordinates `(p2, q2)`: position `2N e1 + p2 a + q2 b`.
        let mut at = |p2: i64, q2: i64, value: i32| {
            let x = 2 * n64 * f.e1[0] + p2 * f.a[0] + q2 * f.b[0];
            let y = 2 * n64 * f.e1[1] + p2 * f.a[1] + q2 * f.b[1];
            if x % (2 * n64) == 0 && y % (2 * n64) == 0 {
                put(f.chart, x / (2 * n64), y / (2 * n64), value);
            }
        };
        let mask = row.mask.as_ref();
        for i in 0..=n {
            for j in 0..=n {
                if mine(i, j) && mask.is_none_or(|m| m.vertex(i, j)) {
                    at(
                        2 * i as i64,
                        2 * j as i64,
                        row.refined.vertices[i * (n + 1) + j],
                    );
                }
                if i < n && j < n && mine(i, j) && mask.is_none_or(|m| m.cell(i, j)) {
                    at(
                        2 * i as i64 + 1,
                        2 * j as i64 + 1,
                        row.refined.cells[i * n + j],
                    );
                }
            }
        }
    }
    Ok(())
}

/// Every coded diamond of one channel by level, in the order [`walk`] reaches them.
type Topology<I> = Vec<Vec<I>>;

/// A blob coded again, into the new repository: `(level, key, blob)`.
type Put<'a> = dyn FnMut(u32, &[u8], &[u8]) -> Result<()> + 'a;

/// The [`Topology`]: the DAG without decoding anything.
fn topology<R: Charted>(r: &R) -> Topology<R::Id> {
    let mut levels = Vec::new();
    let mut current: Vec<R::Id> = r.roots().into_iter().map(|(id, _)| id).collect();
    for level in 0..r.detail_levels() {
        let mut seen = HashSet::new();
        let next = current
            .iter()
            .flat_map(|&id| r.children(id).unwrap_or_default())
            .filter(|&c| r.is_coded(c) && seen.insert(c))
            .collect();
        levels.push(std::mem::replace(&mut current, next));
        if level + 1 == r.detail_levels() {
            break;
        }
    }
    levels
}

/// The diamonds a tile's pass decodes: those with a half over the tile `bbox` of `chart`
/// (their halves tile it at every level), and their ancestors.
fn over_tile<R: Charted>(
    r: &R,
    topology: &Topology<R::Id>,
    chart: u8,
    bbox: [i64; 4],
) -> HashSet<R::Id> {
    let [x0, x1, y0, y1] = bbox;
    let over = |id: R::Id| {
        [true, false].into_iter().any(|lower| {
            let (c, tri) = r.half_chart(id, lower);
            let lo = |k: usize| tri.iter().map(|p| p[k]).min().unwrap_or(i64::MAX);
            let hi = |k: usize| tri.iter().map(|p| p[k]).max().unwrap_or(i64::MIN);
            c == chart && lo(0) <= x1 && hi(0) >= x0 && lo(1) <= y1 && hi(1) >= y0
        })
    };
    let mut keep = HashSet::new();
    for rows in topology.iter().rev() {
        for &id in rows {
            if !keep.contains(&id) && over(id) {
                keep.insert(id);
            }
        }
        let parents: Vec<R::Id> = rows
            .iter()
            .filter(|id| keep.contains(id))
            .flat_map(|&id| r.parents(id))
            .filter(|&p| r.is_refinable(p))
            .collect();
        keep.extend(parents);
    }
    keep
}

/// The tiles of side `side` (samples) that cover `[x0, x1] x [y0, y1]`, overlapping by
/// one sample so that every centre of four samples lies inside one.
fn tiles([x0, x1, y0, y1]: [i64; 4], side: i64) -> Vec<[i64; 4]> {
    let side = side.max(1);
    let starts = |lo: i64, hi: i64| {
        let mut out = vec![lo];
        while let Some(&last) = out.last() {
            if last + side >= hi {
                break;
            }
            out.push(last + side);
        }
        out.into_iter().map(move |a| (a, (a + side).min(hi)))
    };
    starts(y0, y1)
        .flat_map(|(ya, yb)| starts(x0, x1).map(move |(xa, xb)| [xa, xb, ya, yb]))
        .collect()
}

/// A diamond's bound from its own figures and its children's results: `(bound, (lo, hi))`,
/// the bound in quanta and the range of its subtree's values (empty: `lo > hi`).
pub fn subtree_bound(
    departure: &Departure,
    grid_range: Option<(i32, i32)>,
    children: impl Iterator<Item = (u64, (i64, i64))>,
) -> (u64, (i64, i64)) {
    let (glo, ghi) = grid_range.map_or((i64::MAX, i64::MIN), |(a, b)| (a.into(), b.into()));
    let (mut lo, mut hi) = (
        glo.min(departure.fine.0.into()),
        ghi.max(departure.fine.1.into()),
    );
    let mut bound = departure.ceil_quanta();
    for (b, (clo, chi)) in children {
        bound = bound.max(b);
        lo = lo.min(clo);
        hi = hi.max(chi);
    }
    // No valid point of its own (sparse): its grid bounds nothing, so its subtree's whole
    // range is the departure.
    if departure.points == 0 && lo <= hi {
        bound = bound.max(u64::try_from(hi - lo).unwrap_or(0));
    }
    (bound, (lo, hi))
}

/// What [`tighten`] did.
#[derive(Clone, Debug, Default, serde::Serialize, serde::Deserialize)]
pub struct Tightened {
    /// Diamonds decoded and measured.
    pub diamonds: u64,
    /// Blobs coded again.
    pub blobs: u64,
    /// Side-information entries written.
    pub classes: u64,
    /// Entries whose class fell.
    pub lowered: u64,
    /// Entries whose class rose (the encoder's bound was below the measured one).
    pub raised: u64,
    /// Entries the encoder wrote none for (children of diamonds without a blob).
    pub added: u64,
    /// Blobs of zero details written for diamonds without one but with data below.
    pub zero_detail_blobs: u64,
    /// Entries flagged no-data given a bound profile, and the classes of those profiles.
    pub profiled: u64,
    /// Classes in all profiles.
    pub profile_classes: u64,
    /// Median of new bound / old bound over entries with a nonzero old bound.
    pub median_ratio: f64,
    /// Bytes of blobs before and after.
    pub bytes: (u64, u64),
    /// Seconds for the whole pass.
    pub seconds: f64,
    /// Side of the tiles it measured, in samples.
    pub tile_samples: u64,
}

/// `quincunx bounds`: [`tighten`] the repository at `repo` and print what it did (with
/// this process's peak resident memory, `peak_rss_mb`).
pub fn run(repo: &Path, json: bool, tile: i64) -> Result<()> {
    let report = tighten(repo, tile)?.map(|(_, t)| t);
    let peak_rss_mb = crate::layout::peak_rss_mb();
    if json {
        let value = serde_json::json!({ "bounds": report, "peak_rss_mb": peak_rss_mb });
        println!("{value}");
        return Ok(());
    }
    match report {
        None => println!(
            "{}: a colour repository keeps its texel rule",
            repo.display()
        ),
        Some(t) => println!(
            "{}: {} diamonds measured in {:.2} s; {} classes written ({} lowered, {} raised, \
             {} new, median new/old bound {:.3}), {} profiles, {} blobs of zero details; \
             blobs {} -> {} bytes; peak {:.0} MB",
            repo.display(),
            t.diamonds,
            t.seconds,
            t.classes,
            t.lowered,
            t.raised,
            t.added,
            t.median_ratio,
            t.profiled,
            t.zero_detail_blobs,
            t.bytes.0,
            t.bytes.1,
            peak_rss_mb
        ),
    }
    Ok(())
}

/// [`tighten`] for a build: in a `quincunx bounds` child process when this process is
/// the `quincunx` tool (so the pass's memory is its own, not added to what the encoder
/// leaves behind in this one), else here. Returns the report and the child's peak
/// resident memory (MB; 0 when run here).
pub fn tighten_for_build(path: &Path, tile: i64) -> Result<Option<(Metadata, Tightened, f64)>> {
    let exe = std::env::current_exe().ok().filter(|e| {
        e.file_stem()
            .is_some_and(|s| s.to_string_lossy() == "quincunx")
    });
    let Some(exe) = exe else {
        return Ok(tighten(path, tile)?.map(|(m, t)| (m, t, 0.0)));
    };
    let out = std::process::Command::new(&exe)
        .arg("bounds")
        .arg(path)
        .arg("--json")
        .arg("--tile-samples")
        .arg(tile.to_string())
        .stderr(std::process::Stdio::inherit())
        .output()
        .with_context(|| format!("running {} bounds", exe.display()))?;
    if !out.status.success() {
        bail!(
            "{} bounds {} failed ({})",
            exe.display(),
            path.display(),
            out.status
        );
    }
    #[derive(serde::Deserialize)]
    struct Answer {
        bounds: Option<Tightened>,
        peak_rss_mb: f64,
    }
    let answer: Answer = serde_json::from_slice(&out.stdout)
        .with_context(|| format!("reading what {} bounds printed", exe.display()))?;
    let Some(t) = answer.bounds else {
        return Ok(None);
    };
    let repo = Repository::open(path).with_context(|| format!("opening {}", path.display()))?;
    Ok(Some((repo.metadata().clone(), t, answer.peak_rss_mb)))
}

/// Replaces the side-information classes of the elevation repository at `path` (just
/// published by a build) by measured bounds, tile by tile (`tile` samples a side), and
/// publishes it again in place. `None` for colour repositories, which keep theirs.
///
/// Every blob is coded again with its classes replaced by measured bounds, and a blob of
/// zero details is added for each diamond that has none but data below it (clients ask
/// for it anyway; now it tells them its children's bounds).
pub fn tighten(path: &Path, tile: i64) -> Result<Option<(Metadata, Tightened)>> {
    let started = Instant::now();
    if tile < 2 {
        bail!("--tile-samples {tile}: a tile is at least 2 samples a side");
    }
    let repo = Repository::open(path).with_context(|| format!("opening {}", path.display()))?;
    let meta = repo.metadata().clone();
    if meta.attribute.kind == AttributeKind::Colour || meta.channels.len() != 1 {
        return Ok(None);
    }
    let name = path
        .file_name()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    let dense = meta.coverage.is_none();
    let mut builder =
        RepositoryBuilder::create(path).with_context(|| format!("creating {}", path.display()))?;
    // Blobs beyond a few megabytes wait on disk, not in memory.
    if meta.level_stats.iter().map(|s| s.bytes).sum::<u64>() > SPILL_BYTES {
        builder = builder.spill_to_disk()?;
    }
    let mut put =
        |level: u32, key: &[u8], blob: &[u8]| -> Result<()> { Ok(builder.put(level, key, blob)?) };
    let mut report = match meta.domain {
        Domain::Planar => {
            let r = planar_channel_refiner(&name, &meta, 0)?;
            recoded(&r, &repo, dense, tile, &mut put)?
        }
        Domain::Sphere => {
            let r = sphere_channel_refiner(&name, &meta, 0)?;
            recoded(&r, &repo, dense, tile, &mut put)?
        }
    };
    drop(repo);
    let mut out = meta;
    if let Some(build) = out.build.as_object_mut() {
        build.insert("bounds".into(), serde_json::json!("measured"));
    }
    let published = builder
        .publish(out, true)
        .with_context(|| format!("publishing {}", path.display()))?;
    report.seconds = started.elapsed().as_secs_f64();
    Ok(Some((published, report)))
}

/// What the bound pass keeps of a decoded diamond.
struct Kept<I> {
    id: I,
    level: u32,
    key: Vec<u8>,
    has_blob: bool,
    departure: Departure,
    grid_range: Option<(i32, i32)>,
    children: Vec<I>,
}

/// A diamond's results bottom-up: its bound (quanta), its subtree's range, and whether it
/// or anything below it has a blob.
#[derive(Clone, Copy)]
struct Below {
    bound: u64,
    range: (i64, i64),
    data: bool,
}

/// Every coded diamond, a level at a time in [`walk`]'s order, with its departure from
/// the decode measured tile by tile (`tile` samples a side): each tile's pass decodes the
/// diamonds over it and their ancestors, fills the tile from the finest level and
/// measures them there; a diamond's departure is the largest over the tiles it meets.
fn measured<R: Charted>(
    r: &R,
    repo: &Repository,
    blob_of: &BlobOf<'_>,
    dense: bool,
    tile: i64,
) -> Result<Vec<Vec<Kept<R::Id>>>> {
    let topology = topology(r);
    let mut found: HashMap<R::Id, Kept<R::Id>> = HashMap::new();
    // The whole decode, only if a tile of a dense repository is left unwritten.
    let mut whole: Option<Vec<i32>> = None;
    for chart in r.charts() {
        for bbox in tiles(r.chart_box(), tile) {
            let keep = over_tile(r, &topology, chart, bbox);
            if keep.is_empty() {
                continue;
            }
            let mut window = Window::new(chart, bbox);
            if !fill_window(r, blob_of, &keep, &mut window)? && dense {
                if whole.is_none() {
                    whole = Some(
                        crate::verify::decode_repository(repo)?
                            .values
                            .swap_remove(0),
                    );
                }
                if let Some(all) = &whole {
                    let [x0, x1, y0, y1] = bbox;
                    for y in y0..=y1 {
                        for x in x0..=x1 {
                            if let Some(k) = window.index(chart, x, y) {
                                window.values[k] = all[r.sample_index(chart, x, y)];
                            }
                        }
                    }
                }
            }
            walk(r, blob_of, Some(&keep), Some(&window), |level, rows| {
                for d in rows {
                    match found.get_mut(&d.id) {
                        Some(k) => k.departure.merge(d.departure),
                        None => {
                            found.insert(
                                d.id,
                                Kept {
                                    id: d.id,
                                    level: level as u32,
                                    key: d.key.clone(),
                                    has_blob: d.has_blob,
                                    departure: d.departure,
                                    grid_range: d.grid_range,
                                    children: d.children.clone(),
                                },
                            );
                        }
                    }
                }
                Ok(())
            })?;
        }
    }
    let mut levels = Vec::with_capacity(topology.len());
    for rows in &topology {
        let mut level = Vec::with_capacity(rows.len());
        for id in rows {
            let k = found
                .remove(id)
                .with_context(|| format!("diamond {id:?} is over no tile"))?;
            level.push(k);
        }
        levels.push(level);
    }
    Ok(levels)
}

fn recoded<R: Charted>(
    r: &R,
    repo: &Repository,
    dense: bool,
    tile: i64,
    put: &mut Put<'_>,
) -> Result<Tightened> {
    let blob_of =
        |key: &[u8]| -> Result<Option<Vec<u8>>> { Ok(repo.get(key)?.map(|b| b.to_vec())) };
    let levels = measured(r, repo, &blob_of, dense, tile)?;
    let mut report = Tightened {
        diamonds: levels.iter().map(|l| l.len() as u64).sum(),
        tile_samples: tile as u64,
        ..Tightened::default()
    };
    let mut below: HashMap<R::Id, Below> = HashMap::new();
    for rows in levels.iter().rev() {
        let here: Vec<(R::Id, Below)> = rows
            .par_iter()
            .map(|k| {
                let kids: Vec<Below> = k
                    .children
                    .iter()
                    .filter_map(|c| below.get(c).copied())
                    .collect();
                let (bound, range) = subtree_bound(
                    &k.departure,
                    k.grid_range,
                    kids.iter().map(|b| (b.bound, b.range)),
                );
                let data = k.has_blob || kids.iter().any(|b| b.data);
                (k.id, Below { bound, range, data })
            })
            .collect();
        below.extend(here);
    }
    let finest = levels.len().saturating_sub(1) as u32;
    let owners: HashSet<&[u8]> = levels
        .iter()
        .flatten()
        .filter(|k| k.has_blob)
        .map(|k| k.key.as_slice())
        .collect();
    let mut stored = 0u64;
    for kv in repo.blobs() {
        let (key, blob) = kv?;
        stored += 1;
        report.bytes.0 += blob.len() as u64;
        if !owners.contains(key.as_slice()) {
            bail!("a blob of key {key:?} belongs to no coded diamond");
        }
    }
    if stored != owners.len() as u64 {
        bail!(
            "{stored} blobs stored, {} diamonds decoded with one",
            owners.len()
        );
    }
    // Blobs to write: every stored one, and one for each diamond without a blob but with
    // data below (and children to tell about).
    let writes: Vec<&Kept<R::Id>> = levels
        .iter()
        .flatten()
        .filter(|k| k.has_blob || (k.level < finest && below.get(&k.id).is_some_and(|b| b.data)))
        .collect();
    // A no-data child's profile: per level below it, the class of its descendants'
    // largest bound (they have no blob to carry their own), down to a class 0 or the
    // finest level.
    let children_of: HashMap<R::Id, &[R::Id]> = levels
        .iter()
        .flatten()
        .map(|k| (k.id, k.children.as_slice()))
        .collect();
    let profile = |c: R::Id| -> Vec<u8> {
        let mut out = Vec::new();
        let mut layer = vec![c];
        loop {
            let mut seen = HashSet::new();
            layer = layer
                .iter()
                .flat_map(|p| children_of.get(p).copied().unwrap_or(&[]))
                .copied()
                .filter(|k| seen.insert(*k))
                .collect();
            let Some(worst) = layer
                .iter()
                .filter_map(|k| below.get(k))
                .map(|b| b.bound)
                .max()
            else {
                return out;
            };
            let class = gamma_class(worst);
            out.push(class);
            if class == 0 {
                return out;
            }
        }
    };
    type Written = (u32, Vec<u8>, Vec<u8>, Vec<(Option<u8>, u8, usize)>);
    let code = |k: &Kept<R::Id>| -> Result<Written> {
        let old = match k.has_blob {
            true => blob_of(&k.key)?,
            false => None,
        };
        // The encoder's entries, for children the walk did not reach.
        let details = old
            .as_deref()
            .map(|b| r.decode(k.id, b))
            .transpose()
            .with_context(|| format!("decoding diamond {:?}", k.id))?;
        let previous = |c: R::Id| {
            details.as_ref().and_then(|d| {
                let class = d.child_classes.iter().find(|p| p.0 == c)?.1;
                let empty = d.empty_children.contains(&c);
                Some(if empty && class > 0 {
                    class | NO_DATA
                } else {
                    class
                })
            })
        };
        let pairs = std::sync::Mutex::new(Vec::new());
        let missing = std::sync::Mutex::new(None);
        let entry = |c: R::Id| -> (u8, Vec<u8>) {
            let (new, profile) = match below.get(&c) {
                Some(b) => {
                    let class = gamma_class(b.bound);
                    if !b.data && class > 0 {
                        (class | NO_DATA, profile(c))
                    } else {
                        (class, Vec::new())
                    }
                }
                None => (
                    previous(c).unwrap_or_else(|| {
                        *missing.lock().unwrap_or_else(|e| e.into_inner()) = Some(c);
                        0
                    }),
                    Vec::new(),
                ),
            };
            pairs
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .push((previous(c), new, profile.len()));
            (new, profile)
        };
        let blob = r
            .recode(k.id, old.as_deref(), &entry)
            .with_context(|| format!("coding diamond {:?} again", k.id))?;
        if let Some(c) = missing.into_inner().unwrap_or_else(|e| e.into_inner()) {
            bail!(
                "child {c:?} of {:?} has no measured bound and no class",
                k.id
            );
        }
        let pairs = pairs.into_inner().unwrap_or_else(|e| e.into_inner());
        Ok((k.level, k.key.clone(), blob, pairs))
    };
    let mut ratios = Vec::new();
    // A chunk at a time, into the builder: the pass holds no more than a chunk of blobs.
    for chunk in writes.chunks(1024) {
        let out: Vec<Written> = chunk.par_iter().map(|&k| code(k)).collect::<Result<_>>()?;
        for (level, key, blob, pairs) in out {
            report.blobs += 1;
            for (old, new, profile) in pairs {
                report.classes += 1;
                report.profiled += u64::from(profile > 0);
                report.profile_classes += profile as u64;
                let new = split_side(new).0;
                match old.map(|o| split_side(o).0) {
                    Some(old) => {
                        report.lowered += u64::from(new < old);
                        report.raised += u64::from(new > old);
                        if class_bound(old) > 0 {
                            ratios.push(class_bound(new) as f64 / class_bound(old) as f64);
                        }
                    }
                    None => report.added += 1,
                }
            }
            report.bytes.1 += blob.len() as u64;
            put(level, &key, &blob)?;
        }
    }
    report.zero_detail_blobs = report.blobs - stored;
    ratios.sort_by(f64::total_cmp);
    report.median_ratio = ratios.get(ratios.len() / 2).copied().unwrap_or(f64::NAN);
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_tile_follows_the_budget() {
        assert_eq!(tile_for_budget(None), TILE_SAMPLES);
        assert_eq!(tile_for_budget(Some(1)), 64);
        assert_eq!(tile_for_budget(Some(16)), 256);
        assert_eq!(tile_for_budget(Some(20)), 256);
        assert_eq!(tile_for_budget(Some(32)), 512);
        assert_eq!(tile_for_budget(Some(128)), 1024);
        assert_eq!(tile_for_budget(Some(u64::MAX)), 1024);
    }

    #[test]
    fn tiles_overlap_by_one_sample_and_cover_the_box() {
        assert_eq!(tiles([0, 1024, 0, 1024], 1024), vec![[0, 1024, 0, 1024]]);
        assert_eq!(
            tiles([0, 100, 5, 5], 64),
            vec![[0, 64, 5, 5], [64, 100, 5, 5]]
        );
        let t = tiles([0, 699, 0, 449], 256);
        assert_eq!(t.len(), 3 * 2);
        assert_eq!(t[2], [512, 699, 0, 256]);
        assert_eq!(t[5], [512, 699, 256, 449]);
    }
}
