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
use quincunx_codec::entropy::class_bound;
use quincunx_codec::incremental::Refined;
use quincunx_codec::lifting::DiamondMask;
use quincunx_repo_tools::bounds::{self, Charted, HalfFrame};
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

/// The half frames and charts are the bound pass's ([`quincunx_repo_tools::bounds`]); the
/// departure below is measured here, independently of its arithmetic.
fn half_frame<R: Charted>(r: &R, id: R::Id, lower: bool) -> HalfFrame {
    bounds::half_frame(r, id, lower).unwrap()
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
    /// Bound profiles its blob carries for owned children with nothing below them.
    child_profiles: Vec<(I, Vec<u8>)>,
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
    /// Diamonds bounded by a parent's profile (nothing below their owner has a blob).
    profiled: u64,
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
    // Bound profiles of the current level's diamonds (their owners' blobs', or the rest of
    // a parent's), and the classes their parents' profiles give them: a client's bound is
    // the smaller of that and the owner's class.
    let mut profiles: HashMap<R::Id, Vec<u8>> = HashMap::new();
    let mut handed: HashMap<R::Id, u8> = HashMap::new();
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
                    child_classes: details
                        .as_ref()
                        .map(|d| d.child_classes.clone())
                        .unwrap_or_default(),
                    child_profiles: details.map(|d| d.child_profiles).unwrap_or_default(),
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
            let class = [classes.get(&row.id), handed.get(&row.id)]
                .into_iter()
                .flatten()
                .copied()
                .min();
            rep.profiled += u64::from(handed.contains_key(&row.id));
            let Some(class) = class else {
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
                    .filter(|&&p| r.is_refinable(p))
                    .map(|p| {
                        *refined
                            .get(p)
                            .unwrap_or_else(|| panic!("parent {p:?} of {c:?} not refined"))
                    })
                    .collect();
                (c, r.grid_of(c, &parents).unwrap())
            })
            .collect();
        classes = next_classes;
        let (mut next_profiles, mut next_handed) = (HashMap::new(), HashMap::new());
        let mut tighter = |c: R::Id, p: &[u8]| {
            let q: &mut Vec<u8> = next_profiles.entry(c).or_insert_with(|| p.to_vec());
            for (k, &v) in p.iter().enumerate() {
                match q.get_mut(k) {
                    Some(x) => *x = (*x).min(v),
                    None => q.push(v),
                }
            }
        };
        for row in &rows {
            for (c, p) in &row.child_profiles {
                tighter(*c, p);
            }
            if let Some(p) = profiles.get(&row.id).filter(|p| !p.is_empty()) {
                for &c in &row.children {
                    tighter(c, &p[1..]);
                    let k: &mut u8 = next_handed.entry(c).or_insert(p[0]);
                    *k = (*k).min(p[0]);
                }
            }
        }
        profiles = next_profiles;
        handed = next_handed;
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
        // Built with `--bounds measured` (or `quincunx bounds`): then they are tight.
        let measured = meta.build["bounds"] == "measured";
        report(name, &coding.name, rep, (elevation, measured), started);
    }
    assert!(compared > 0, "{name}: no point compared with a bound");
}

/// Prints a channel's figures and asserts its checks (`elevation`: every level below the
/// roots must be compared nearly everywhere; `measured`: the bounds must be tight).
fn report(
    name: &str,
    channel: &str,
    mut rep: Report,
    (elevation, measured): (bool, bool),
    started: Instant,
) {
    let label = format!("{name}/{channel}");
    let med = median(&mut rep.ratios);
    eprintln!(
        "{label}: {} diamonds ({} roots without a class, not checked; {} bounded by a \
         parent's profile; {} without a known \
         class: owner has no blob, departing by up to {:.2} quanta), {} checked over {} \
         points ({} in all non-root diamonds; {} samples, {} detail levels)",
        rep.diamonds,
        rep.roots,
        rep.profiled,
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
    // The build measures the bounds (`quincunx_repo_tools::bounds`): a class rounds the
    // monotone measure up by at most sqrt 2, so half of the diamonds sit well within 2x
    // of theirs (the encoder's sum over levels was 4x at the median).
    assert!(
        !(elevation && measured) || med >= 0.5,
        "{label}: loose bounds: measured / bound is {med:.3} at the median"
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
        .args([
            "--diamond-size",
            "9",
            "--rms-m",
            "2",
            "--bounds",
            "measured",
        ])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    check_repository_at("korea N=8 RMS 2 m", &dir);
}

/// A raster that is not `2^k + 1` on a side (a 700 x 450 crop of the bundled korea):
/// diamonds on its border have a parent outside the data, which holds no part of them;
/// the pass, like a client, cuts their grids from the parents inside alone.
#[test]
fn a_raster_of_any_size_gets_measured_bounds() {
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join("error-bound-crop");
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let raw =
        std::fs::read(Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/korea_srtm3_1025.i16"))
            .unwrap();
    let values: Vec<f64> = raw
        .chunks_exact(2)
        .map(|b| f64::from(i16::from_le_bytes([b[0], b[1]])))
        .collect();
    let tile = common::crop(&values, 1025, 300..=749, 200..=899, 1);
    assert_eq!((tile.0, tile.1), (700, 450));
    common::write_raw(&dir, "crop", &tile, 126.0, 38.0, 1.0 / 1200.0);
    let out = dir.join("repo");
    common::build(
        &["--rms-m", "4", "--bounds", "measured"],
        &dir.join("crop.json"),
        &out,
    );
    let repo = Repository::open(&out).unwrap();
    assert_eq!(repo.metadata().build["bounds"], "measured");
    assert!(repo.metadata().coverage.is_none(), "the crop is dense");
    check_repository_at("korea crop 700 x 450", &out);
}

/// The bound pass's full-resolution decode (the finest level's lattices, written point by
/// point) is the whole-raster decoder's, every copy of every planet point included.
#[test]
fn the_bound_pass_decodes_what_verify_decodes() {
    use quincunx_repo_tools::bounds::finest_values;
    for name in ["korea", "earth"] {
        let repo = Repository::open(demo_dir().join(name)).unwrap();
        let meta = repo.metadata().clone();
        let blob_of = |key: &[u8]| -> anyhow::Result<Option<Vec<u8>>> {
            Ok(repo.get(key)?.map(|b| b.to_vec()))
        };
        let got = match meta.domain {
            Domain::Planar => {
                let r = planar_channel_refiner(name, &meta, 0).unwrap();
                finest_values(&r, &blob_of, true).unwrap()
            }
            Domain::Sphere => {
                let r = sphere_channel_refiner(name, &meta, 0).unwrap();
                finest_values(&r, &blob_of, true).unwrap()
            }
        };
        let want = quincunx_repo_tools::verify::decode_repository(&repo).unwrap();
        let got = got.unwrap_or_else(|| panic!("{name}: points left unwritten"));
        assert_eq!(got.len(), want.values[0].len(), "{name}");
        let differ = got
            .iter()
            .zip(&want.values[0])
            .filter(|(a, b)| a != b)
            .count();
        assert_eq!(differ, 0, "{name}: {differ} points differ");
    }
}

/// The bounds a build measured are what `quincunx bounds` measures again: the pass is a
/// fixed point (the same bytes), and it says why a colour repository is left alone.
#[test]
fn measuring_the_bounds_again_changes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    for name in ["korea", "earth", "earth_colour"] {
        let v = measure_a_copy(dir.path(), name, &[]);
        let b = &v["bounds"];
        if name == "earth_colour" {
            assert!(b.is_null(), "{v}");
        } else {
            assert!(b["diamonds"].as_u64().unwrap() > 100, "{v}");
            assert_eq!(
                (b["lowered"].as_u64(), b["raised"].as_u64()),
                (Some(0), Some(0)),
                "{v}"
            );
        }
    }
}

/// The pass measures a tile at a time; the bounds do not depend on the tiles: with tiles
/// of 64 samples (256 on korea; on the planet 16 a face, with diamonds across tiles and
/// cube faces) it writes the same bytes as with one tile.
#[test]
fn the_bounds_do_not_depend_on_the_tiles() {
    let dir = tempfile::tempdir().unwrap();
    for name in ["korea", "earth"] {
        let v = measure_a_copy(dir.path(), name, &["--tile-samples", "64"]);
        assert_eq!(v["bounds"]["tile_samples"], 64, "{v}");
    }
    // Too small a tile is a clear error.
    let o = bin()
        .arg("bounds")
        .arg(dir.path().join("korea"))
        .args(["--tile-samples", "1"])
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(1));
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(stderr.contains("at least 2 samples"), "{stderr}");
}

/// `quincunx bounds <copy> --json <extra>` on a copy (in `dir`) of the bundled `name`,
/// which must leave its content hash as it was; what it printed.
fn measure_a_copy(dir: &Path, name: &str, extra: &[&str]) -> serde_json::Value {
    let copy = dir.join(name);
    std::fs::create_dir_all(&copy).unwrap();
    let pack = "repository.pack";
    std::fs::copy(demo_dir().join(name).join(pack), copy.join(pack)).unwrap();
    let o = bin()
        .arg("bounds")
        .arg(&copy)
        .arg("--json")
        .args(extra)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let before = Repository::open(demo_dir().join(name)).unwrap();
    let after = Repository::open(&copy).unwrap();
    assert_eq!(
        before.metadata().content_hash,
        after.metadata().content_hash,
        "{name} {extra:?}: {v}"
    );
    v
}

/// Golden repositories: the bundled builds, bounds included (blob version 6), are these
/// bytes. A change to what a build writes (the format, the encoder or the bound pass)
/// shows here; if it is meant, bump `blob::VERSION` where the format changed, say why in
/// `docs/blob-format.md`, and put the new hashes here.
#[test]
fn the_bundled_builds_are_the_golden_bytes() {
    for (name, hash) in [
        (
            "korea",
            "6507523f2d4d0b6aa1c8f47f945b2fe5435d46c611c74a3bcba4ef07c059ab5d",
        ),
        (
            "earth",
            "e2632d97da5aaeeefd8e62a1f04a958daa5741c40300b4c883bc8db8888bab1e",
        ),
        (
            "earth_colour",
            "5744725bcd64378bd506cd4cce3a57ea5f281ca0fa2fa0e1e0d41de50b1677d7",
        ),
    ] {
        let repo = Repository::open(demo_dir().join(name)).unwrap();
        assert_eq!(repo.metadata().content_hash, hash, "{name}");
        assert_eq!(repo.compute_content_hash().unwrap(), hash, "{name}");
    }
}
