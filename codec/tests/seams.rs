//! Any mixed-level cut is seamless without stitching: per-diamond synthesis, the way a
//! client does it, on a real DEM.
//!
//! The bundled Korea crop (1025 x 1025) is analysed into a hierarchy of N = 32 diamonds.
//! Starting from the root grid, diamonds are synthesised one at a time: a diamond's vertex
//! grid is assembled from its parents' refined lattices ([`child_half`] +
//! [`scatter_to_child`]) and refined with [`lifting::synthesize`]. A random cut (fixed
//! seed) refines a diamond only when all its in-domain parents are refined. Then every
//! pair of diamonds that meet is checked: vertices at identical positions must hold
//! bit-identical values, where both are valid samples.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use std::collections::{BTreeMap, HashMap};

use quincunx_codec::diamond::{PlanarDomain, PlanarId};
use quincunx_codec::lifting::{self, DiamondMask, child_half, scatter_to_child};
use quincunx_codec::raster::{RasterGeometry, Transform};

const N: usize = 32;
const W: usize = N + 1;

/// A diamond whose vertex grid is known (all its in-domain parents are refined).
struct Node {
    level: usize,
    slot: usize,
    /// The vertex grid as assembled from the parents (before its own synthesis).
    coarse: Vec<i32>,
    /// After synthesis: refined vertices and cell centres.
    refined: Option<(Vec<i32>, Vec<i32>)>,
}

/// SplitMix64: a fixed-seed generator, no dependency.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    fn chance(&mut self, p: f64) -> bool {
        (self.next() >> 11) as f64 / (1u64 << 53) as f64 <= p
    }
}

/// Comparison counters of one kind of pair.
#[derive(Default, Debug)]
struct Tally {
    pairs: usize,
    compared: usize,
    mismatches: usize,
    examples: Vec<String>,
}

impl Tally {
    fn check(&mut self, a: i32, b: i32, what: impl FnOnce() -> String) {
        self.compared += 1;
        if a != b {
            self.mismatches += 1;
            if self.examples.len() < 8 {
                self.examples.push(format!("{} ({a} != {b})", what()));
            }
        }
    }
}

fn vertex_valid(mask: Option<&DiamondMask>, i: usize, j: usize) -> bool {
    mask.is_none_or(|m| m.vertex(i, j))
}

fn cell_valid(mask: Option<&DiamondMask>, i: usize, j: usize) -> bool {
    mask.is_none_or(|m| m.cell(i, j))
}

#[test]
fn any_mixed_level_cut_is_seamless_on_a_real_dem() {
    let grid = common::grid(&common::bundled_korea());
    let (width, height) = (grid.width, grid.height);
    // Integer metres; nodata as 0 (the values only need to be real terrain, not exact).
    let original: Vec<i32> = grid
        .values_m
        .iter()
        .map(|v| if v.is_finite() { v.round() as i32 } else { 0 })
        .collect();

    let geom = RasterGeometry::new(width, height, N).unwrap();
    let domain: PlanarDomain = geom.domain();
    let levels = geom.detail_levels();
    let mut raster = original.clone();
    let details = geom.analyze(&mut raster).unwrap();
    let root_grid = geom.gather_root(&raster);

    // Which slot holds an id.
    let slot_of: HashMap<PlanarId, (usize, usize)> = (0..levels)
        .flat_map(|l| {
            geom.level(l)
                .iter()
                .enumerate()
                .map(move |(i, s)| (s.id, (l, i)))
        })
        .collect();
    let mask_of = |id: PlanarId| -> Option<&DiamondMask> {
        let (l, i) = slot_of[&id];
        geom.level(l)[i].mask.as_ref()
    };

    // Synthesis over a random cut, level by level. Refinement is likelier near a focus
    // point, so the cut reaches the finest level there and stays coarse elsewhere.
    let mut rng = Rng(0x5EA_15EA_u64);
    let size = domain.size();
    let focus = [size as f64 * 0.55, size as f64 * 0.4];
    let root = domain.root();
    let (root_level, root_slot) = slot_of[&root];
    assert_eq!(root_level, 0);
    let mut nodes: BTreeMap<PlanarId, Node> = BTreeMap::new();
    nodes.insert(
        root,
        Node {
            level: 0,
            slot: root_slot,
            coarse: root_grid,
            refined: None,
        },
    );
    let mut parents_agree = Tally::default();
    let mut unwritten = 0usize;
    for (level, level_details) in details.iter().enumerate() {
        let ids: Vec<PlanarId> = nodes
            .iter()
            .filter(|(_, n)| n.level == level)
            .map(|(&id, _)| id)
            .collect();
        for id in ids {
            let dist = ((id.x as f64 - focus[0]).powi(2) + (id.y as f64 - focus[1]).powi(2)).sqrt()
                / size as f64;
            // The always-refined radius shrinks slower than parents spread apart, so the
            // focus keeps complete parents all the way down.
            let p = if dist < 0.1 + 2.5 * 0.5f64.powf(level as f64 / 2.0) {
                1.0
            } else {
                0.35
            };
            if !rng.chance(p) {
                continue;
            }
            let node = nodes.get_mut(&id).unwrap();
            let mut v = node.coarse.clone();
            let mut c = vec![0; N * N];
            lifting::synthesize(N, &mut v, &level_details[node.slot], &mut c, mask_of(id));
            node.refined = Some((v, c));
        }
        if level + 1 == levels {
            break;
        }
        // Children whose in-domain parents are all refined get a vertex grid.
        for (slot, s) in geom.level(level + 1).iter().enumerate() {
            let parents = domain.parents(s.id).unwrap();
            let all_refined = !parents.is_empty()
                && parents
                    .iter()
                    .all(|p| nodes.get(p).is_some_and(|n| n.refined.is_some()));
            if !all_refined {
                continue;
            }
            let child_corners = domain.corners(s.id).unwrap();
            let mut grid = vec![0; W * W];
            let mut written = vec![false; W * W];
            parents_agree.pairs += usize::from(parents.len() == 2);
            for p in &parents {
                let (v, c) = nodes[p].refined.as_ref().unwrap();
                let map = child_half(&domain.corners(*p).unwrap(), &child_corners, N)
                    .unwrap_or_else(|| panic!("{p:?} and its child {:?} do not line up", s.id));
                let mut half = vec![0; W * W];
                let mut half_written = vec![false; W * W];
                let count = scatter_to_child(&map, N, v, c, &mut half, Some(&mut half_written));
                assert!(count > 0, "parent {p:?} wrote nothing into {:?}", s.id);
                for k in 0..W * W {
                    if !half_written[k] {
                        continue;
                    }
                    let (i, j) = (k / W, k % W);
                    // Both parents write the child's hypotenuse: they must agree there.
                    if written[k] && vertex_valid(s.mask.as_ref(), i, j) {
                        parents_agree.check(grid[k], half[k], || {
                            format!("child {:?} vertex ({i},{j}) from two parents", s.id)
                        });
                    }
                    grid[k] = half[k];
                    written[k] = true;
                }
            }
            unwritten += (0..W * W)
                .filter(|&k| !written[k] && vertex_valid(s.mask.as_ref(), k / W, k % W))
                .count();
            nodes.insert(
                s.id,
                Node {
                    level: level + 1,
                    slot,
                    coarse: grid,
                    refined: None,
                },
            );
        }
    }
    let mut per_level: BTreeMap<usize, (usize, usize)> = BTreeMap::new();
    for node in nodes.values() {
        let e = per_level.entry(node.level).or_default();
        e.0 += 1;
        e.1 += usize::from(node.refined.is_some());
    }
    println!("(diamonds with a grid, refined) per level: {per_level:?}");
    assert_eq!(unwritten, 0, "valid child vertices that no parent wrote");

    // Sanity: the per-diamond path reproduces the data. Refined diamonds of the finest
    // detail level hold original samples (lossless, no quantisation here).
    let mut finest_checked = 0usize;
    let mut finest_wrong = 0usize;
    for (&id, node) in nodes.iter().filter(|(_, n)| n.level + 1 == levels) {
        let Some((v, c)) = &node.refined else {
            continue;
        };
        let mask = mask_of(id);
        let at = |p: [i64; 2]| -> Option<i32> {
            let s = 2 * N as i64;
            assert!(
                p[0] % s == 0 && p[1] % s == 0,
                "finest lattice off the samples"
            );
            let (x, y) = (p[0] / s, p[1] / s);
            (x >= 0 && y >= 0 && (x as usize) < width && (y as usize) < height)
                .then(|| original[y as usize * width + x as usize])
        };
        for i in 0..=N {
            for j in 0..=N {
                if vertex_valid(mask, i, j) {
                    let want = at(domain.vertex_position(id, N, i, j).unwrap()).unwrap();
                    finest_checked += 1;
                    finest_wrong += usize::from(v[i * W + j] != want);
                }
                if i < N && j < N && cell_valid(mask, i, j) {
                    let want = at(domain.cell_position(id, N, i, j).unwrap()).unwrap();
                    finest_checked += 1;
                    finest_wrong += usize::from(c[i * N + j] != want);
                }
            }
        }
    }
    assert!(finest_checked > 0, "the cut never reached the finest level");
    assert_eq!(
        finest_wrong, 0,
        "finest-level samples differ from the data ({finest_checked} checked)"
    );

    // Positions of every known diamond's valid vertices.
    let positions: HashMap<PlanarId, HashMap<[i64; 2], usize>> = nodes
        .keys()
        .map(|&id| {
            let mask = mask_of(id);
            let map = (0..W * W)
                .filter(|&k| vertex_valid(mask, k / W, k % W))
                .map(|k| (domain.vertex_position(id, N, k / W, k % W).unwrap(), k))
                .collect();
            (id, map)
        })
        .collect();

    // 1. Same-level neighbours: their shared side, before and after either is refined
    //    (the update is zero on boundary vertices).
    let mut same_level = Tally::default();
    for (&a, na) in &nodes {
        for b in domain.neighbours(a).unwrap().into_iter().flatten() {
            let Some(nb) = nodes.get(&b) else { continue };
            if b <= a {
                continue;
            }
            same_level.pairs += 1;
            for (pos, &ka) in &positions[&a] {
                let Some(&kb) = positions[&b].get(pos) else {
                    continue;
                };
                let mut values_a = vec![("coarse", na.coarse[ka])];
                values_a.extend(na.refined.as_ref().map(|(v, _)| ("refined", v[ka])));
                let mut values_b = vec![("coarse", nb.coarse[kb])];
                values_b.extend(nb.refined.as_ref().map(|(v, _)| ("refined", v[kb])));
                for &(wa, va) in &values_a {
                    for &(wb, vb) in &values_b {
                        same_level.check(va, vb, || {
                            format!("{a:?} {wa} vs neighbour {b:?} {wb} at {pos:?}")
                        });
                    }
                }
            }
        }
    }

    // 2. Parent and child: the child's grid is the parent's refined lattice, and where it
    //    meets the parent's border it also equals the parent's unrefined grid, which is
    //    what the parent's unrefined neighbours see.
    let mut parent_child = Tally::default();
    let mut parent_border = Tally::default();
    for (&child, nc) in nodes.iter().filter(|(_, n)| n.level > 0) {
        for parent in domain.parents(child).unwrap() {
            let np = &nodes[&parent];
            let (pv, pc) = np.refined.as_ref().unwrap();
            let pmask = mask_of(parent);
            let mut lattice: HashMap<[i64; 2], (i32, Option<i32>)> = HashMap::new();
            for i in 0..=N {
                for j in 0..=N {
                    if vertex_valid(pmask, i, j) {
                        let border = i == 0 || j == 0 || i == N || j == N;
                        lattice.insert(
                            domain.vertex_position(parent, N, i, j).unwrap(),
                            (pv[i * W + j], border.then_some(np.coarse[i * W + j])),
                        );
                    }
                    if i < N && j < N && cell_valid(pmask, i, j) {
                        lattice.insert(
                            domain.cell_position(parent, N, i, j).unwrap(),
                            (pc[i * N + j], None),
                        );
                    }
                }
            }
            parent_child.pairs += 1;
            parent_border.pairs += 1;
            for (pos, &k) in &positions[&child] {
                let Some(&(fine, coarse_border)) = lattice.get(pos) else {
                    continue;
                };
                parent_child.check(nc.coarse[k], fine, || {
                    format!("child {child:?} vs refined parent {parent:?} at {pos:?}")
                });
                if let Some(coarse) = coarse_border {
                    parent_border.check(nc.coarse[k], coarse, || {
                        format!("child {child:?} vs unrefined parent border {parent:?} at {pos:?}")
                    });
                }
            }
        }
    }

    // 3. The cut itself: every unrefined diamond with a grid is drawn; wherever two of
    //    them share a position (sides of same-level neighbours, corners across levels)
    //    the values agree.
    let mut cut_levels: BTreeMap<usize, usize> = BTreeMap::new();
    let mut drawn: HashMap<[i64; 2], (PlanarId, usize, i32)> = HashMap::new();
    let mut cut = Tally::default();
    let mut across_levels = 0usize;
    for (&id, node) in nodes.iter().filter(|(_, n)| n.refined.is_none()) {
        *cut_levels.entry(node.level).or_default() += 1;
        for (pos, &k) in &positions[&id] {
            let value = node.coarse[k];
            match drawn.get(pos) {
                Some(&(other, other_level, other_value)) => {
                    across_levels += usize::from(other_level != node.level);
                    cut.check(value, other_value, || {
                        format!("cut diamonds {id:?} and {other:?} at {pos:?}")
                    });
                }
                None => {
                    drawn.insert(*pos, (id, node.level, value));
                }
            }
        }
    }
    cut.pairs = cut_levels.values().sum();

    println!("diamonds with a grid: {}", nodes.len());
    println!("cut (unrefined) diamonds per level: {cut_levels:?}");
    let tallies = [
        ("two parents of one child", &parents_agree),
        ("same-level neighbours", &same_level),
        ("child vs refined parent", &parent_child),
        ("child vs parent border", &parent_border),
        ("cut diamonds", &cut),
    ];
    for (name, t) in tallies {
        println!(
            "{name:>26}: {} pairs/diamonds, {} shared vertices compared, {} mismatches",
            t.pairs, t.compared, t.mismatches
        );
        for e in &t.examples {
            println!("    {e}");
        }
    }
    println!("cut positions shared across levels: {across_levels}");

    assert!(
        cut_levels.len() >= 3,
        "the cut is not mixed-level enough: {cut_levels:?}"
    );
    for (name, t) in tallies {
        assert!(t.compared > 0, "{name}: no shared vertices were compared");
        assert_eq!(
            t.mismatches,
            0,
            "{name}: {} of {} shared vertices differ, e.g.\n  {}",
            t.mismatches,
            t.compared,
            t.examples.join("\n  ")
        );
    }
    assert!(across_levels > 0, "no cut positions shared across levels");
}
