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
//! 1. The repository is decoded at full resolution, then every diamond top-down as a
//!    client decodes it (the client's refiners: decode, synthesise, cut each child's grid
//!    from its parents' lattices).
//! 2. A diamond's **departure** is the largest `|surface - decoded|` over its two halves
//!    on the continuum ([`half_departure`]: every sample, and every centre of four
//!    samples, where the two triangulations can cross), exact in integers and rounded up
//!    to whole quanta.
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
//! The pass holds the full-resolution decode (4 bytes a sample), one level's lattices,
//! a few figures per diamond and the repository's blobs.

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

/// What the bound pass needs of a domain besides its refiner: the chart each half of a
/// diamond lies in, and the decoded value of a chart point.
pub trait Charted: Refiner {
    /// The chart of a half (`lower`: vertices `i >= j`, the triangle `E1 P1 E2`; else
    /// `i <= j`, `E1 P2 E2`) and its corners `[E1, P, E2]` there (id units = samples).
    fn half_chart(&self, id: Self::Id, lower: bool) -> (u8, [[i64; 2]; 3]);
    /// The chart's sample box `[x0, x1, y0, y1]` (inclusive).
    fn chart_box(&self) -> [i64; 4];
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

/// The departure of one half of a diamond whose vertex grid is `grid`, from the decoded
/// `values`, on the continuum: at every sample of the half, and at every centre of a
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
pub fn half_departure<R: Charted>(
    r: &R,
    f: &HalfFrame,
    grid: &[i32],
    mask: Option<&DiamondMask>,
    values: &[i32],
) -> Departure {
    // Times `2d`, a surface value is at most `2d 2^31` and each product of the
    // interpolation `2d 2^32`: within `i64` while `2d < 2^28`.
    if 2 * f.d < 1 << 28 {
        departure_in::<R, i64>(r, f, grid, mask, values)
    } else {
        departure_in::<R, i128>(r, f, grid, mask, values)
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
    values: &[i32],
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
    let sample = |x: i64, y: i64| T::from(i64::from(values[r.sample_index(f.chart, x, y)]));
    let mut out = Departure::none(2 * f.d);
    let [x0, x1, y0, y1] = f.bbox;
    for y in y0..=y1 {
        // Only the row's span inside the triangle (one more each side: `surface` decides).
        let (lo, hi) = row_span(f, n, 0, 2 * y);
        for x in (lo - 1).max(x0)..=(hi + 1).min(x1) {
            if let Some(s) = surface(2 * x, 2 * y) {
                let value = values[r.sample_index(f.chart, x, y)];
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

/// Decodes every coded diamond of one channel top-down, a level at a time, measuring
/// each against the full-resolution `values` (`None`: no measure), and hands each level
/// to `visit` (in the level's order of ids).
pub fn walk<R: Charted>(
    r: &R,
    blob_of: &BlobOf<'_>,
    values: Option<&[i32]>,
    mut visit: impl FnMut(usize, &[Decoded<R::Id>]) -> Result<()>,
) -> Result<()> {
    let mut current: Vec<(R::Id, Vec<i32>)> = r
        .roots()
        .into_iter()
        .map(|(id, g)| (id, g.to_vec()))
        .collect();
    for level in 0..r.detail_levels() {
        // The finest level's lattices are only wanted without a measure (they are the
        // decode).
        let lattices = level + 1 < r.detail_levels() || values.is_none();
        let rows: Vec<Decoded<R::Id>> = current
            .into_par_iter()
            .map(|(id, grid)| decode_one(r, blob_of, values, level, id, &grid, lattices))
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
            .filter(|&c| seen.insert(c))
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
    values: Option<&[i32]>,
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
    if let Some(values) = values {
        for lower in [true, false] {
            let f = half_frame(r, id, lower)?;
            departure.merge(half_departure(r, &f, grid, mask.as_ref(), values));
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
    let n = r.n();
    let n64 = n as i64;
    let [x0, x1, y0, y1] = r.chart_box();
    walk(r, blob_of, None, |level, rows| {
        if level + 1 != r.detail_levels() {
            return Ok(());
        }
        for row in rows {
            for lower in [true, false] {
                let f = half_frame(r, row.id, lower)?;
                let mine = |i: usize, j: usize| if lower { i >= j } else { i <= j };
                // Doubled grid coordinates `(p2, q2)`: position `2N e1 + p2 a + q2 b`.
                let mut put = |p2: i64, q2: i64, value: i32| {
                    let x = 2 * n64 * f.e1[0] + p2 * f.a[0] + q2 * f.b[0];
                    let y = 2 * n64 * f.e1[1] + p2 * f.a[1] + q2 * f.b[1];
                    if x % (2 * n64) != 0 || y % (2 * n64) != 0 {
                        return;
                    }
                    let (x, y) = (x / (2 * n64), y / (2 * n64));
                    if (x0..=x1).contains(&x) && (y0..=y1).contains(&y) {
                        let k = r.sample_index(f.chart, x, y);
                        values[k] = value;
                        written[k / 64] |= 1 << (k % 64);
                    }
                };
                let mask = row.mask.as_ref();
                for i in 0..=n {
                    for j in 0..=n {
                        if mine(i, j) && mask.is_none_or(|m| m.vertex(i, j)) {
                            let v = row.refined.vertices[i * (n + 1) + j];
                            put(2 * i as i64, 2 * j as i64, v);
                        }
                        if i < n && j < n && mine(i, j) && mask.is_none_or(|m| m.cell(i, j)) {
                            let v = row.refined.cells[i * n + j];
                            put(2 * i as i64 + 1, 2 * j as i64 + 1, v);
                        }
                    }
                }
            }
        }
        Ok(())
    })?;
    let all = (0..len).all(|k| written[k / 64] & (1 << (k % 64)) != 0);
    Ok((!dense || all).then_some(values))
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
}

/// `quincunx bounds`: [`tighten`] the repository at `repo` and print what it did (with
/// this process's peak resident memory, `peak_rss_mb`).
pub fn run(repo: &Path, json: bool) -> Result<()> {
    let report = tighten(repo)?.map(|(_, t)| t);
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
pub fn tighten_for_build(path: &Path) -> Result<Option<(Metadata, Tightened, f64)>> {
    let exe = std::env::current_exe().ok().filter(|e| {
        e.file_stem()
            .is_some_and(|s| s.to_string_lossy() == "quincunx")
    });
    let Some(exe) = exe else {
        return Ok(tighten(path)?.map(|(m, t)| (m, t, 0.0)));
    };
    let out = std::process::Command::new(&exe)
        .arg("bounds")
        .arg(path)
        .arg("--json")
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
/// published by a build) by measured bounds and publishes it again in place. `None` for
/// colour repositories, which keep theirs.
pub fn tighten(path: &Path) -> Result<Option<(Metadata, Tightened)>> {
    let started = Instant::now();
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
    let blobs = match meta.domain {
        Domain::Planar => {
            let r = planar_channel_refiner(&name, &meta, 0)?;
            recoded(&r, &repo, dense)?
        }
        Domain::Sphere => {
            let r = sphere_channel_refiner(&name, &meta, 0)?;
            recoded(&r, &repo, dense)?
        }
    };
    let (new_blobs, mut report) = blobs;
    let mut builder =
        RepositoryBuilder::create(path).with_context(|| format!("creating {}", path.display()))?;
    if meta.level_stats.iter().map(|s| s.bytes).sum::<u64>() > 1 << 30 {
        builder = builder.spill_to_disk()?;
    }
    for (level, key, blob) in &new_blobs {
        report.bytes.1 += blob.len() as u64;
        builder.put(*level, key, blob)?;
    }
    drop(new_blobs);
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

/// Every blob of the repository with its classes replaced by measured bounds, and a blob
/// of zero details for each diamond that has none but data below it (clients ask for it
/// anyway; now it tells them its children's bounds): `(level, key, blob)`, and the
/// figures.
type Recoded = (Vec<(u32, Vec<u8>, Vec<u8>)>, Tightened);

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

fn recoded<R: Charted>(r: &R, repo: &Repository, dense: bool) -> Result<Recoded> {
    let blob_of =
        |key: &[u8]| -> Result<Option<Vec<u8>>> { Ok(repo.get(key)?.map(|b| b.to_vec())) };
    let values = match finest_values(r, &blob_of, dense)? {
        Some(v) => v,
        None => crate::verify::decode_repository(repo)?
            .values
            .swap_remove(0),
    };
    let values = values.as_slice();
    let mut levels: Vec<Vec<Kept<R::Id>>> = Vec::new();
    walk(r, &blob_of, Some(values), |level, rows| {
        levels.push(
            rows.iter()
                .map(|d| Kept {
                    id: d.id,
                    level: level as u32,
                    key: d.key.clone(),
                    has_blob: d.has_blob,
                    departure: d.departure,
                    grid_range: d.grid_range,
                    children: d.children.clone(),
                })
                .collect(),
        );
        Ok(())
    })?;
    let mut report = Tightened {
        diamonds: levels.iter().map(|l| l.len() as u64).sum(),
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
    let out: Vec<Written> = writes
        .into_par_iter()
        .map(|k| {
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
                pairs.lock().unwrap_or_else(|e| e.into_inner()).push((
                    previous(c),
                    new,
                    profile.len(),
                ));
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
        })
        .collect::<Result<_>>()?;
    let mut ratios = Vec::new();
    let mut blobs = Vec::with_capacity(out.len());
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
        blobs.push((level, key, blob));
    }
    report.zero_detail_blobs = report.blobs - stored;
    ratios.sort_by(f64::total_cmp);
    report.median_ratio = ratios.get(ratios.len() / 2).copied().unwrap_or(f64::NAN);
    Ok((blobs, report))
}
