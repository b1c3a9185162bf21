//! The side-information bounds of the bundled repositories (`quincunx demo --build-only`)
//! against their decoded surfaces, for every diamond.
//!
//! Every diamond's blob carries, per owned child (a child whose first parent it is), a
//! class whose [`class_bound`] (value quanta) is meant to bound how far the finest decoded
//! surface beneath the child departs from the piecewise-linear surface the child draws from
//! its `(N+1)^2` vertex grid, and to be monotone up the DAG. The test decodes every diamond
//! top-down as a client does (`quincunx_client::open`'s refiners: decode, synthesise,
//! assemble children's grids from both parents' lattices), and checks:
//!
//! 1. **Upper bound.** Each diamond's surface, its grid cells split along the diagonal
//!    from vertex `(i, j)` to `(i+1, j+1)` (as `quincunx_render::grid_indices` draws them
//!    and `codec/src/encode.rs` fn `measure` measures them) and interpolated linearly on
//!    each triangle, is evaluated at every full-resolution sample inside each of its
//!    triangles whose three vertices are valid samples (planets: each half of a diamond
//!    lies on one cube face, evaluated in that face's chart), and compared with the
//!    full-resolution decode (`quincunx_repo_tools::verify::decode_repository`). The
//!    comparison is exact: a point's grid coordinates are rationals `I / D` with integer
//!    `I` and `D`, so `D` times the surface and `D` times the bound are compared as
//!    integers (no epsilon). Roots carry no class (no owner) and are only reported.
//! 2. **Monotone.** A diamond's class is at least each of its children's, where both are
//!    known.
//!
//! Sanity checks keep the mapping honest: the finest level's refined lattices equal the
//! full-resolution decode at their sample positions, and on elevation the points compared
//! with a bound number at least 90% of `(detail levels - 1) x samples` (every sample lies
//! in a diamond of each level). `earth_colour` has no elevation channel: its Y, Co and Cg
//! channels are checked where their classes are known (Cg's roots have no blob, so none).
//!
//! Diagnostics (printed, not asserted): the same deviations with the cells split
//! 4-8-mesh fashion (the diagonal through `(i, j)` where `i + j` is even, through
//! `(i+1, j)` where it is odd), the triangulation that nests from level to level.
//!
//! The cells of a child with odd `i + j` have their diagonal across a parent grid edge
//! (it joins two parent cell centres), so the encoder's measure also visits the parent's
//! interior edge midpoints (`codec/src/encode.rs`, `edge_departures`). Without them, korea
//! built with `--diamond-size 9 --rms-m 2` had diamond (328, 552) of level 12 depart by 191
//! quanta from a class-16 bound of 182; `small_diamonds_cross_their_parents_edges_within_
//! the_bound` keeps that build checked. `QUINCUNX_BOUND_REPOS` checks any other builds.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use std::collections::{HashMap, HashSet};
use std::path::{Path, PathBuf};
use std::sync::OnceLock;
use std::time::Instant;

use common::bin;
use quincunx_client::open::{planar_channel_refiner, sphere_channel_refiner};
use quincunx_codec::diamond::sphere::{axes, chart_of};
use quincunx_codec::entropy::class_bound;
use quincunx_codec::incremental::{PlanarRefiner, Refined, Refiner, SphereRefiner};
use quincunx_codec::lifting::DiamondMask;
use quincunx_store::{AttributeKind, Domain, Repository};
use rayon::prelude::*;

/// The bundled repositories, built once per run.
fn demo_dir() -> &'static Path {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join("error-bound");
        let _ = std::fs::remove_dir_all(&dir);
        let o = bin()
            .args(["demo", "--build-only", "--dir"])
            .arg(&dir)
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        dir
    })
}

/// What the check needs of a domain besides its refiner: the chart each half of a
/// diamond lies in, and the decoded value of a chart point.
trait Charted: Refiner {
    /// The chart of a half (`lower`: vertices `i >= j`, the triangle `E1 P1 E2`; else
    /// `i <= j`, `E1 P2 E2`) and its corners `[E1, P, E2]` there (id units = samples).
    fn half_chart(&self, id: Self::Id, lower: bool) -> (u8, [[i64; 2]; 3]);
    /// The chart's sample box `[x0, x1, y0, y1]` (inclusive).
    fn chart_box(&self) -> [i64; 4];
    /// Index in the full-resolution decode of sample `(x, y)` of `chart` (inside its box).
    fn sample_index(&self, chart: u8, x: i64, y: i64) -> usize;
    /// A child's vertex grid from its refined parents (the refiner's `child_grid`).
    fn grid_of(&self, child: Self::Id, parents: &[&Refined<Self::Id>]) -> Vec<i32>;
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

    fn grid_of(&self, child: Self::Id, parents: &[&Refined<Self::Id>]) -> Vec<i32> {
        self.child_grid(child, parents).unwrap()
    }
}

impl Charted for SphereRefiner {
    fn half_chart(&self, id: Self::Id, lower: bool) -> (u8, [[i64; 2]; 3]) {
        let c = Refiner::corners(self, id);
        let tri = [c[0], if lower { c[1] } else { c[3] }, c[2]];
        let s = self.domain().size();
        // The face the whole triangle lies on (an edge diamond's halves are on two faces).
        let face = (0..6u8)
            .find(|&f| {
                let ax = axes(f);
                tri.iter().all(|p| p[ax.a] == ax.s * s)
            })
            .unwrap_or_else(|| panic!("half of {id:?} ({tri:?}) on no single face"));
        (face, tri.map(|p| chart_of(face, p, s)))
    }

    fn chart_box(&self) -> [i64; 4] {
        let side = self.frame().face_side() as i64;
        [0, side, 0, side]
    }

    fn sample_index(&self, chart: u8, x: i64, y: i64) -> usize {
        self.frame().cube_index(chart, x as usize, y as usize)
    }

    fn grid_of(&self, child: Self::Id, parents: &[&Refined<Self::Id>]) -> Vec<i32> {
        self.child_grid(child, parents).unwrap()
    }
}

/// A half's grid frame in its chart: vertex `(i, j)` at `e1 + (i a + j b) / N`.
struct HalfFrame {
    chart: u8,
    e1: [i64; 2],
    a: [i64; 2],
    b: [i64; 2],
    /// `|a|^2 = |b|^2`: grid coordinates are `I / d` with integer `I`.
    d: i64,
    lower: bool,
    /// The triangle's sample box, clipped to the chart's.
    bbox: [i64; 4],
}

fn half_frame<R: Charted>(r: &R, id: R::Id, lower: bool) -> HalfFrame {
    let (chart, [e1, p, e2]) = r.half_chart(id, lower);
    // The square's fourth corner: P1 + P2 = E1 + E2.
    let q = [e1[0] + e2[0] - p[0], e1[1] + e2[1] - p[1]];
    let (p1, p2) = if lower { (p, q) } else { (q, p) };
    let a = [p1[0] - e1[0], p1[1] - e1[1]];
    let b = [p2[0] - e1[0], p2[1] - e1[1]];
    let d = a[0] * a[0] + a[1] * a[1];
    assert!(
        d > 0 && d == b[0] * b[0] + b[1] * b[1] && a[0] * b[0] + a[1] * b[1] == 0,
        "{id:?}: frame is not a square"
    );
    let [x0, x1, y0, y1] = r.chart_box();
    let xs = [e1[0], p[0], e2[0]];
    let ys = [e1[1], p[1], e2[1]];
    let bbox = [
        xs.iter().copied().min().unwrap().max(x0),
        xs.iter().copied().max().unwrap().min(x1),
        ys.iter().copied().min().unwrap().max(y0),
        ys.iter().copied().max().unwrap().min(y1),
    ];
    HalfFrame {
        chart,
        e1,
        a,
        b,
        d,
        lower,
        bbox,
    }
}

/// How far a diamond's surface departs from the full-resolution decode.
#[derive(Clone, Copy, Debug, Default)]
struct Deviation {
    /// Largest `|surface - decoded|`, times `d` (exact).
    worst: i128,
    /// The same with 4-8 (alternating) diagonals: diagnostics only.
    worst_48: i128,
    /// The common denominator of the diamond's grid coordinates.
    d: i64,
    /// Sample points compared (per half: points on the hypotenuse count twice).
    points: u64,
}

impl Deviation {
    fn quanta(&self) -> f64 {
        self.worst as f64 / self.d as f64
    }

    fn quanta_48(&self) -> f64 {
        self.worst_48 as f64 / self.d as f64
    }

    fn merge(&mut self, o: Deviation) {
        debug_assert!(self.d == 0 || self.d == o.d);
        self.d = o.d;
        self.worst = self.worst.max(o.worst);
        self.worst_48 = self.worst_48.max(o.worst_48);
        self.points += o.points;
    }
}

/// The deviation of one half of a diamond whose vertex grid is `grid`.
fn half_deviation<R: Charted>(
    r: &R,
    f: &HalfFrame,
    grid: &[i32],
    mask: Option<&DiamondMask>,
    values: &[i32],
) -> Deviation {
    let n = r.n() as i64;
    let w = r.n() + 1;
    let d = f.d;
    let nd = n * d;
    let valid = |i: i64, j: i64| mask.is_none_or(|m| m.vertex(i as usize, j as usize));
    let v = |i: i64, j: i64| i128::from(grid[i as usize * w + j as usize]);
    let (d128, mut out) = (
        i128::from(d),
        Deviation {
            d,
            ..Deviation::default()
        },
    );
    let [x0, x1, y0, y1] = f.bbox;
    for y in y0..=y1 {
        for x in x0..=x1 {
            let (dx, dy) = (x - f.e1[0], y - f.e1[1]);
            // Grid coordinates (i, j) = (gi, gj) / d.
            let gi = n * (dx * f.a[0] + dy * f.a[1]);
            let gj = n * (dx * f.b[0] + dy * f.b[1]);
            let inside = if f.lower {
                0 <= gj && gj <= gi && gi <= nd
            } else {
                0 <= gi && gi <= gj && gj <= nd
            };
            if !inside {
                continue;
            }
            let (ci, cj) = ((gi / d).min(n - 1), (gj / d).min(n - 1));
            let (fi, fj) = (i128::from(gi - ci * d), i128::from(gj - cj * d));
            // The cell's triangle holding the point; ties go to this half's side.
            let lower_tri = fi > fj || (fi == fj && f.lower);
            let tri_ok = if lower_tri {
                valid(ci, cj) && valid(ci + 1, cj) && valid(ci + 1, cj + 1)
            } else {
                valid(ci, cj) && valid(ci, cj + 1) && valid(ci + 1, cj + 1)
            };
            if !tri_ok {
                continue;
            }
            let (v00, v10, v01, v11) = (v(ci, cj), v(ci + 1, cj), v(ci, cj + 1), v(ci + 1, cj + 1));
            let surface = if lower_tri {
                d128 * v00 + fi * (v10 - v00) + fj * (v11 - v10)
            } else {
                d128 * v00 + fj * (v01 - v00) + fi * (v11 - v01)
            };
            let fine = d128 * i128::from(values[r.sample_index(f.chart, x, y)]);
            out.worst = out.worst.max((surface - fine).abs());
            out.points += 1;
            // Diagnostics: 4-8 diagonals (the other one where ci + cj is odd), when the
            // four corners are valid.
            let all_valid = valid(ci, cj) && valid(ci + 1, cj) && valid(ci, cj + 1);
            let surface_48 = if (ci + cj) % 2 == 0 || !(all_valid && valid(ci + 1, cj + 1)) {
                surface
            } else if fi + fj <= d128 {
                d128 * v00 + fi * (v10 - v00) + fj * (v01 - v00)
            } else {
                d128 * v11 + (d128 - fi) * (v01 - v11) + (d128 - fj) * (v10 - v11)
            };
            out.worst_48 = out.worst_48.max((surface_48 - fine).abs());
        }
    }
    out
}

/// Checks a refined diamond of the finest level against the full-resolution decode at
/// its lattice points: `(points checked, mismatches)`.
fn finest_lattice<R: Charted>(
    r: &R,
    id: R::Id,
    refined: &Refined<R::Id>,
    mask: Option<&DiamondMask>,
    values: &[i32],
) -> (u64, u64) {
    let n = r.n();
    let n64 = n as i64;
    let (mut checked, mut bad) = (0, 0);
    for lower in [true, false] {
        let f = half_frame(r, id, lower);
        let [x0, x1, y0, y1] = r.chart_box();
        let mut at = |p2: i64, q2: i64, value: i32| {
            // Doubled grid coordinates (p2, q2): position 2N e1 + p2 a + q2 b.
            let x = 2 * n64 * f.e1[0] + p2 * f.a[0] + q2 * f.b[0];
            let y = 2 * n64 * f.e1[1] + p2 * f.a[1] + q2 * f.b[1];
            assert!(
                x % (2 * n64) == 0 && y % (2 * n64) == 0,
                "{id:?}: a finest lattice point is not a sample"
            );
            let (x, y) = (x / (2 * n64), y / (2 * n64));
            assert!((x0..=x1).contains(&x) && (y0..=y1).contains(&y));
            checked += 1;
            if values[r.sample_index(f.chart, x, y)] != value {
                bad += 1;
            }
        };
        let mine = |i: usize, j: usize| if lower { i >= j } else { i <= j };
        for i in 0..=n {
            for j in 0..=n {
                if mine(i, j) && mask.is_none_or(|m| m.vertex(i, j)) {
                    at(
                        2 * i as i64,
                        2 * j as i64,
                        refined.vertices[i * (n + 1) + j],
                    );
                }
                if i < n && j < n && mine(i, j) && mask.is_none_or(|m| m.cell(i, j)) {
                    at(2 * i as i64 + 1, 2 * j as i64 + 1, refined.cells[i * n + j]);
                }
            }
        }
    }
    (checked, bad)
}

/// One diamond's figures.
struct Row<I> {
    id: I,
    level: usize,
    dev: Deviation,
    /// Classes the diamond's blob carries for its owned children.
    child_classes: Vec<(I, u8)>,
    /// Coded children.
    children: Vec<I>,
    refined: Refined<I>,
    /// Finest level: lattice points checked against the decode, and mismatches.
    lattice: (u64, u64),
}

/// What a channel's check found.
#[derive(Default)]
struct Report {
    diamonds: u64,
    roots: u64,
    /// Non-root diamonds whose owner has no blob (so no class is known).
    unknown: u64,
    /// The largest departure (quanta) of those: a client takes their bound as 0.
    unknown_worst_quanta: f64,
    checked: u64,
    /// Points compared against a known bound.
    points: u64,
    /// Points evaluated in every non-root diamond (known class or not).
    points_all: u64,
    /// measured / bound of each checked diamond with a nonzero bound.
    ratios: Vec<f64>,
    /// The largest ratio and where: (ratio, text).
    worst: Option<(f64, String)>,
    /// Largest 4-8 ratio (diagnostics).
    worst_48: f64,
    violations: Vec<String>,
    violations_48: u64,
    monotone_pairs: u64,
    monotone_violations: Vec<String>,
    lattice_points: u64,
    lattice_mismatches: u64,
    root_worst_quanta: f64,
    /// Per level: diamonds checked, largest ratio, violations.
    levels: Vec<(u64, f64, u64)>,
    samples: u64,
    detail_levels: usize,
}

/// A diamond's blob (this channel's part) by storage key.
type BlobOf<'a> = dyn Fn(&[u8]) -> Option<Vec<u8>> + Sync + 'a;

/// Decodes every diamond of one channel top-down and checks its bound.
fn check_channel<R: Charted>(r: &R, blob_of: &BlobOf<'_>, values: &[i32], samples: u64) -> Report {
    let mut rep = Report {
        samples,
        detail_levels: r.detail_levels(),
        levels: vec![(0, 0.0, 0); r.detail_levels()],
        ..Report::default()
    };
    let mut current: Vec<(R::Id, Vec<i32>)> = r
        .roots()
        .into_iter()
        .map(|(id, g)| (id, g.to_vec()))
        .collect();
    rep.roots = current.len() as u64;
    // Classes of the current level's diamonds, from their owners' blobs.
    let mut classes: HashMap<R::Id, u8> = HashMap::new();
    for level in 0..r.detail_levels() {
        let finest = level + 1 == r.detail_levels();
        let rows: Vec<Row<R::Id>> = current
            .par_iter()
            .map(|(id, grid)| {
                let id = *id;
                let info = r.info(id).unwrap();
                assert_eq!(info.level, level, "{id:?}");
                let details = blob_of(&info.key).map(|b| r.decode(id, &b).unwrap());
                let refined = r.synthesize(id, grid, details.as_ref()).unwrap();
                let mask = info.mask.as_ref();
                let mut dev = Deviation::default();
                for lower in [true, false] {
                    let f = half_frame(r, id, lower);
                    dev.merge(half_deviation(r, &f, grid, mask, values));
                }
                let lattice = if finest {
                    finest_lattice(r, id, &refined, mask, values)
                } else {
                    (0, 0)
                };
                Row {
                    id,
                    level,
                    dev,
                    child_classes: details.map(|d| d.child_classes).unwrap_or_default(),
                    children: info
                        .children
                        .into_iter()
                        .filter(|&c| r.is_coded(c))
                        .collect(),
                    refined,
                    lattice,
                }
            })
            .collect();
        let mut next_classes = HashMap::new();
        for row in &rows {
            rep.diamonds += 1;
            rep.lattice_points += row.lattice.0;
            rep.lattice_mismatches += row.lattice.1;
            for &(c, k) in &row.child_classes {
                assert!(next_classes.insert(c, k).is_none(), "{c:?} has two owners");
            }
            if level == 0 {
                rep.root_worst_quanta = rep.root_worst_quanta.max(row.dev.quanta());
                continue;
            }
            rep.points_all += row.dev.points;
            let Some(&class) = classes.get(&row.id) else {
                rep.unknown += 1;
                rep.unknown_worst_quanta = rep.unknown_worst_quanta.max(row.dev.quanta());
                continue;
            };
            let bound = class_bound(class);
            rep.checked += 1;
            rep.points += row.dev.points;
            let lv = &mut rep.levels[row.level];
            lv.0 += 1;
            let text = || {
                format!(
                    "{:?} level {}: measured {:.4} quanta, class {class} bound {bound} \
                     (4-8 diagonals: {:.4})",
                    row.id,
                    row.level,
                    row.dev.quanta(),
                    row.dev.quanta_48()
                )
            };
            // Exact: worst / d <= bound.
            if row.dev.worst > i128::from(bound as i64) * i128::from(row.dev.d) {
                rep.violations.push(text());
                lv.2 += 1;
            }
            if row.dev.worst_48 > i128::from(bound as i64) * i128::from(row.dev.d) {
                rep.violations_48 += 1;
            }
            if bound > 0 {
                let ratio = row.dev.quanta() / bound as f64;
                rep.ratios.push(ratio);
                lv.1 = lv.1.max(ratio);
                rep.worst_48 = rep.worst_48.max(row.dev.quanta_48() / bound as f64);
                if rep.worst.as_ref().is_none_or(|w| ratio > w.0) {
                    rep.worst = Some((ratio, text()));
                }
            }
        }
        // Monotone: a diamond's class >= each child's (both known).
        for row in &rows {
            let Some(&mine) = classes.get(&row.id) else {
                continue;
            };
            for c in &row.children {
                if let Some(&k) = next_classes.get(c) {
                    rep.monotone_pairs += 1;
                    if class_bound(mine) < class_bound(k) {
                        rep.monotone_violations.push(format!(
                            "{:?} level {level} class {mine} (bound {}) < child {c:?} class \
                             {k} (bound {})",
                            row.id,
                            class_bound(mine),
                            class_bound(k)
                        ));
                    }
                }
            }
        }
        if finest {
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
        current = kids
            .into_par_iter()
            .map(|c| {
                let parents: Vec<&Refined<R::Id>> = r
                    .parents(c)
                    .iter()
                    .map(|p| {
                        *refined
                            .get(p)
                            .unwrap_or_else(|| panic!("parent {p:?} of {c:?} not refined"))
                    })
                    .collect();
                (c, r.grid_of(c, &parents))
            })
            .collect();
        classes = next_classes;
    }
    rep
}

fn median(v: &mut [f64]) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    let k = v.len() / 2;
    if v.len() % 2 == 1 {
        v[k]
    } else {
        (v[k - 1] + v[k]) / 2.0
    }
}

/// Checks every channel of a bundled repository.
fn check_repository(name: &str) {
    check_repository_at(name, &demo_dir().join(name));
}

/// Checks every channel of the repository at `path` (dense ones; sparse ones are skipped).
fn check_repository_at(name: &str, path: &Path) {
    let started = Instant::now();
    let repo = Repository::open(path).unwrap();
    let meta = repo.metadata().clone();
    if meta.coverage.is_some() {
        eprintln!("{name}: sparse repository, skipped");
        return;
    }
    let elevation = meta.attribute.kind != AttributeKind::Colour;
    if !elevation {
        eprintln!(
            "{name}: a colour repository ({} channels), no elevation: its channels are \
             checked where their classes are known",
            meta.channels.len()
        );
    }
    let decoded = quincunx_repo_tools::verify::decode_repository(&repo).unwrap();
    let count = meta.channels.len();
    let mut compared = 0;
    for (c, coding) in meta.channels.iter().enumerate() {
        let values = &decoded.values[c];
        let blob_of = |key: &[u8]| {
            let blob = repo.get(key).unwrap()?;
            quincunx_store::channels::split_channels(&blob, count).unwrap()[c].map(<[u8]>::to_vec)
        };
        let rep = match meta.domain {
            Domain::Planar => {
                let r = planar_channel_refiner(name, &meta, c).unwrap();
                let (w, h) = r.raster_size();
                check_channel(&r, &blob_of, values, (w * h) as u64)
            }
            Domain::Sphere => {
                let r = sphere_channel_refiner(name, &meta, c).unwrap();
                let samples = r.frame().distinct_points() as u64;
                check_channel(&r, &blob_of, values, samples)
            }
        };
        compared += rep.points;
        report(name, &coding.name, rep, elevation, started);
    }
    assert!(compared > 0, "{name}: no point compared with a bound");
}

/// Prints a channel's figures and asserts its checks (`elevation`: every level below the
/// roots must be compared nearly everywhere).
fn report(name: &str, channel: &str, mut rep: Report, elevation: bool, started: Instant) {
    let label = format!("{name}/{channel}");
    let med = median(&mut rep.ratios);
    eprintln!(
        "{label}: {} diamonds ({} roots without a class, not checked; {} without a known \
         class: owner has no blob, departing by up to {:.2} quanta), {} checked over {} \
         points ({} in all non-root diamonds; {} samples, {} detail levels)",
        rep.diamonds,
        rep.roots,
        rep.unknown,
        rep.unknown_worst_quanta,
        rep.checked,
        rep.points,
        rep.points_all,
        rep.samples,
        rep.detail_levels
    );
    eprintln!(
        "{label}: measured/bound: largest {:.4}, median {:.4} (over {} nonzero bounds); \
         roots depart by up to {:.2} quanta",
        rep.worst.as_ref().map_or(f64::NAN, |w| w.0),
        med,
        rep.ratios.len(),
        rep.root_worst_quanta
    );
    if let Some((_, w)) = &rep.worst {
        eprintln!("{label}: largest ratio at {w}");
    }
    for (l, (k, worst, bad)) in rep.levels.iter().enumerate().skip(1) {
        eprintln!("{label}:   level {l}: {k} diamonds, largest ratio {worst:.4}, {bad} over");
    }
    eprintln!(
        "{label}: with 4-8 diagonals (diagnostics): largest ratio {:.4}, {} over",
        rep.worst_48, rep.violations_48
    );
    eprintln!(
        "{label}: {} parent-child class pairs, {} not monotone; finest lattice: {} points, \
         {} differ from the decode; {:.1} s",
        rep.monotone_pairs,
        rep.monotone_violations.len(),
        rep.lattice_points,
        rep.lattice_mismatches,
        started.elapsed().as_secs_f64()
    );
    for v in rep.violations.iter().take(20) {
        eprintln!("{label}: OVER BOUND {v}");
    }
    for v in rep.monotone_violations.iter().take(20) {
        eprintln!("{label}: NOT MONOTONE {v}");
    }
    assert!(
        rep.lattice_points > 0 && rep.lattice_mismatches == 0,
        "{label}: sample mapping"
    );
    let expected = (rep.detail_levels as u64).saturating_sub(1) * rep.samples;
    assert!(
        rep.points_all * 10 >= expected * 9,
        "{label}: only {} points evaluated (expected about {expected})",
        rep.points_all
    );
    assert!(
        !elevation || rep.points * 10 >= expected * 9,
        "{label}: only {} points compared with a bound (expected about {expected})",
        rep.points
    );
    assert!(
        !elevation || rep.monotone_pairs > 0,
        "{label}: no parent-child pair"
    );
    assert!(
        rep.violations.is_empty(),
        "{label}: {} diamonds depart from the decode by more than their class bound, e.g. {}",
        rep.violations.len(),
        rep.violations[0]
    );
    assert!(
        rep.monotone_violations.is_empty(),
        "{label}: {} classes not monotone, e.g. {}",
        rep.monotone_violations.len(),
        rep.monotone_violations[0]
    );
}

/// The planar SRTM crop.
#[test]
fn korea_bounds_hold_for_every_diamond() {
    check_repository("korea");
}

/// The ETOPO20 planet.
#[test]
fn earth_bounds_hold_for_every_diamond() {
    check_repository("earth");
}

/// The planet's colour (Blue Marble): no elevation channel; its Y, Co and Cg channels
/// carry the same side information, checked the same way.
#[test]
fn earth_colour_bounds_hold_for_every_diamond() {
    check_repository("earth_colour");
}

/// Further repositories, by path, in `QUINCUNX_BOUND_REPOS` (separated by commas), checked
/// the same way; nothing without it.
#[test]
fn repositories_named_in_the_environment() {
    let Ok(paths) = std::env::var("QUINCUNX_BOUND_REPOS") else {
        eprintln!("QUINCUNX_BOUND_REPOS unset: no further repository checked");
        return;
    };
    for path in paths.split(',').filter(|p| !p.is_empty()) {
        check_repository_at(path, Path::new(path));
    }
}

/// The build that found the parent-edge crossings (see the module docs): N = 8 over the
/// bundled korea crop at RMS 2 m, where a child's cells cross its parent's grid edges on
/// short diamonds.
#[test]
fn small_diamonds_cross_their_parents_edges_within_the_bound() {
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join("error-bound-n8");
    let _ = std::fs::remove_dir_all(&dir);
    let source = Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/korea_srtm3_1025.json");
    let o = bin()
        .arg("build")
        .arg(&source)
        .arg("--output")
        .arg(&dir)
        .args(["--diamond-size", "9", "--rms-m", "2"])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    check_repository_at("korea N=8 RMS 2 m", &dir);
}
