//! Planets one diamond at a time, as a streaming client refines: grids assembled from
//! refined parents (across cube edges and at cube corners) equal the whole-planet
//! decoder's state, and the finished refinement equals it exactly.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use std::collections::HashMap;

use quincunx_codec::diamond::SphereId;
use quincunx_codec::encode::{
    self, EncodeOptions, Encoded, FromEncoded, RateMode, decode_sphere_integers,
};
use quincunx_codec::incremental::{RefineError, Refined, Refiner, SphereRefiner};

fn planet(face_side: usize, n: usize, mode: RateMode) -> Encoded {
    let g = common::synthetic_planet(face_side, n).unwrap();
    encode::encode_sphere(
        &g,
        EncodeOptions {
            n,
            mode,
            sparse: false,
            rdo: Default::default(),
        },
    )
    .unwrap()
}

/// Refines every diamond coarse to fine from grids assembled by `child_grid`, checking
/// each grid against the raster state and the end against `decode_sphere_integers`.
fn refine_everything(enc: &Encoded) {
    let r = SphereRefiner::from_encoded(enc).unwrap();
    let n = r.n();
    let domain = r.domain();
    let geom = r.frame().clone();
    let blobs = enc.blobs_by_key().unwrap();
    let two_n = 2 * n as i64;
    let decoded = decode_sphere_integers(enc).unwrap();
    let mut raster = vec![0i32; decoded.len()];
    let mut refined: HashMap<SphereId, Refined<SphereId>> = HashMap::new();
    let write = |raster: &mut Vec<i32>, p: [i64; 3], x: i32| {
        let p = p.map(|c| c / two_n);
        let mut copies = 0;
        for k in geom.point_indices(p) {
            raster[k] = x;
            copies += 1;
        }
        assert!(copies >= 1, "{p:?} has no sample");
    };
    let read = |raster: &[i32], p: [i64; 3]| {
        let k = geom.point_indices(p.map(|c| c / two_n)).next().unwrap();
        raster[k]
    };
    let mut level_ids: Vec<SphereId> = r.roots().iter().map(|(id, _)| *id).collect();
    let (mut edge_children, mut checked) = (0, 0usize);
    for level in 0..r.detail_levels() {
        let mut next = Vec::new();
        for &id in &level_ids {
            let info = r.info(id).unwrap();
            assert_eq!(info.level, level);
            let grid = if level == 0 {
                let roots = r.roots();
                roots.iter().find(|(rid, _)| *rid == id).unwrap().1.to_vec()
            } else {
                let parents: Vec<&Refined<SphereId>> = r
                    .parents(id)
                    .iter()
                    .filter_map(|p| refined.get(p))
                    .collect();
                assert_eq!(parents.len(), 2, "{id:?}");
                if domain.faces(id).unwrap().1.is_some() {
                    edge_children += 1;
                }
                r.child_grid(id, &parents).unwrap()
            };
            for i in 0..=n {
                for j in 0..=n {
                    let p = domain.vertex_position(id, n, i, j).unwrap();
                    if level == 0 {
                        write(&mut raster, p, grid[i * (n + 1) + j]);
                    } else {
                        assert_eq!(grid[i * (n + 1) + j], read(&raster, p), "{id:?} ({i},{j})");
                        checked += 1;
                    }
                }
            }
            let blob = blobs.get(&info.key).map(Vec::as_slice);
            let details = blob.map(|b| r.decode(id, b).unwrap());
            let out = r.synthesize(id, &grid, details.as_ref()).unwrap();
            for i in 0..=n {
                for j in 0..=n {
                    let p = domain.vertex_position(id, n, i, j).unwrap();
                    write(&mut raster, p, out.vertices[i * (n + 1) + j]);
                }
            }
            for i in 0..n {
                for j in 0..n {
                    let p = domain.cell_position(id, n, i, j).unwrap();
                    write(&mut raster, p, out.cells[i * n + j]);
                }
            }
            for c in &info.children {
                if !next.contains(c) {
                    next.push(*c);
                }
            }
            refined.insert(id, out);
        }
        level_ids = next;
    }
    // The leaves (children of the finest level) assemble from the final lattices.
    for &leaf in &level_ids {
        let parents: Vec<&Refined<SphereId>> = r
            .parents(leaf)
            .iter()
            .filter_map(|p| refined.get(p))
            .collect();
        let grid = r.child_grid(leaf, &parents).unwrap();
        for i in 0..=n {
            for j in 0..=n {
                let p = domain.vertex_position(leaf, n, i, j).unwrap();
                assert_eq!(grid[i * (n + 1) + j], read(&raster, p), "leaf {leaf:?}");
            }
        }
    }
    assert!(edge_children > 0 && checked > 0);
    assert_eq!(
        raster, decoded,
        "incremental refinement differs from the planet decoder"
    );
}

#[test]
fn planets_refined_one_diamond_at_a_time_equal_the_planet_decoder() {
    refine_everything(&planet(64, 8, RateMode::Lossless));
    refine_everything(&planet(128, 16, RateMode::RmsM(4.0)));
    refine_everything(&planet(64, 32, RateMode::MaxErrorM(3.0)));
}

#[test]
fn wrong_parents_and_planar_encodings_are_errors() {
    let enc = planet(64, 8, RateMode::Lossless);
    let r = SphereRefiner::from_encoded(&enc).unwrap();
    let roots = r.roots();
    let (a, ga) = roots[0];
    let ra = r.synthesize(a, ga, None).unwrap();
    let child = r.info(a).unwrap().children[0];
    let grandchild = r.info(child).unwrap().children[0];
    // A grandchild's grid cannot come from the root.
    assert!(matches!(
        r.partial_child_grid(grandchild, &[&ra]),
        Err(RefineError::NotAParent { .. })
    ));
    // One parent is not enough for a whole grid.
    assert!(matches!(
        r.child_grid(child, &[&ra]),
        Err(RefineError::MissingParent { .. })
    ));
    assert!(matches!(
        r.synthesize(a, &ga[1..], None),
        Err(RefineError::WrongLength { .. })
    ));
    assert!(r.decode(a, &[0u8; 3]).is_err());
    let mut planar = enc.clone();
    planar.domain = encode::EncodedDomain::Planar {
        width: 65,
        height: 65,
    };
    assert!(matches!(
        SphereRefiner::from_encoded(&planar),
        Err(RefineError::WrongDomain)
    ));
}

#[test]
fn children_alone_are_the_infos_children_on_sparse_and_dense_planets() {
    let (face_side, n) = (128, 8);
    let mut g = common::synthetic_planet(face_side, n).unwrap();
    let w = face_side + 1;
    // No data on face 1, a quarter of face 2 and a band of face 4: mixed, full and
    // empty diamonds, across cube edges.
    for (k, v) in g.values_m.iter_mut().enumerate() {
        let (face, rest) = (k / (w * w), k % (w * w));
        let (u, y) = (rest % w, rest / w);
        if face == 1
            || (face == 2 && u < w / 2 && y < w / 2)
            || (face == 4 && (40..70).contains(&y))
        {
            *v = f64::NAN;
        }
    }
    let sparse = encode::encode_sphere(
        &g,
        EncodeOptions {
            n,
            mode: RateMode::MaxErrorM(4.0),
            sparse: true,
            rdo: Default::default(),
        },
    )
    .unwrap();
    assert!(sparse.coverage.is_some());
    let dense = planet(face_side, n, RateMode::MaxErrorM(4.0));
    for enc in [&sparse, &dense] {
        let r = SphereRefiner::from_encoded(enc).unwrap();
        let mut ids: Vec<SphereId> = r.roots().iter().map(|(id, _)| *id).collect();
        let (mut checked, mut seen) = (0, std::collections::HashSet::new());
        while let Some(id) = ids.pop() {
            if !seen.insert(id) {
                continue;
            }
            let info = r.info(id).map(|i| i.children);
            assert_eq!(r.children(id), info, "{id:?}");
            checked += 1;
            // Leaves too (their children are `None`).
            ids.extend(info.unwrap_or_default());
        }
        assert!(checked > 1000, "{checked}");
    }
}
