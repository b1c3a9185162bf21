//! One diamond at a time, as a streaming client refines: the grids assembled from refined
//! parents equal the whole-raster decoder's, shared edges agree bit for bit in every cut,
//! and bad input is an error.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use std::collections::HashMap;

use quincunx_codec::diamond::PlanarId;
use quincunx_codec::encode::{
    EncodeOptions, Encoded, FromEncoded, RateMode, decode_integers, encode,
};
use quincunx_codec::incremental::{PlanarRefiner, RefineError, Refined};
use quincunx_codec::raster::RasterGeometry;

fn korea(mode: RateMode, n: usize) -> Encoded {
    // A crop that is not a power of two plus one: border diamonds have masks.
    let g = common::bundled_korea_crop(700, 513);
    encode(
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

/// Refines every diamond, coarse to fine (parents first), from grids assembled by
/// `child_grid`; checks each grid against the raster decoder's state at that point and
/// the final values against `decode_integers`.
fn refine_everything(enc: &Encoded) -> HashMap<PlanarId, Refined> {
    let r = PlanarRefiner::from_encoded(enc).unwrap();
    let n = r.n();
    let domain = r.domain();
    let mut refined: HashMap<PlanarId, Refined> = HashMap::new();
    let mut raster = vec![0i32; enc.width * enc.height];
    let decoded = decode_integers(enc).unwrap();
    let at = |p: [i64; 2]| -> Option<usize> {
        let (x, y) = (p[0] / (2 * n as i64), p[1] / (2 * n as i64));
        (x >= 0 && y >= 0 && (x as usize) < enc.width && (y as usize) < enc.height)
            .then(|| y as usize * enc.width + x as usize)
    };
    let blobs = enc.blobs_by_key().unwrap();
    let mut level_ids: Vec<Vec<PlanarId>> = vec![vec![r.root().0]];
    for level in 0..r.detail_levels() {
        let mut next = Vec::new();
        for &id in &level_ids[level] {
            let info = r.info(id).unwrap();
            assert_eq!(info.level, level);
            let grid = if level == 0 {
                r.root().1.to_vec()
            } else {
                let parents: Vec<&Refined> = domain
                    .parents(id)
                    .unwrap()
                    .iter()
                    .filter_map(|p| refined.get(p))
                    .collect();
                r.child_grid(id, &parents).unwrap()
            };
            // The assembled grid equals the raster state at the diamond's valid vertices.
            for i in 0..=n {
                for j in 0..=n {
                    if info.mask.as_ref().is_some_and(|m| !m.vertex(i, j)) {
                        continue;
                    }
                    let k = at(domain.vertex_position(id, n, i, j).unwrap()).unwrap();
                    if level == 0 {
                        raster[k] = grid[i * (n + 1) + j];
                    } else {
                        assert_eq!(grid[i * (n + 1) + j], raster[k], "{id:?} vertex ({i},{j})");
                    }
                }
            }
            let blob = blobs.get(&info.key).map(Vec::as_slice);
            let out = r.refine(id, &grid, blob).unwrap();
            for i in 0..=n {
                for j in 0..=n {
                    if info.mask.as_ref().is_none_or(|m| m.vertex(i, j)) {
                        let k = at(domain.vertex_position(id, n, i, j).unwrap()).unwrap();
                        raster[k] = out.vertices[i * (n + 1) + j];
                    }
                }
            }
            for i in 0..n {
                for j in 0..n {
                    if info.mask.as_ref().is_none_or(|m| m.cell(i, j)) {
                        let k = at(domain.cell_position(id, n, i, j).unwrap()).unwrap();
                        raster[k] = out.cells[i * n + j];
                    }
                }
            }
            for c in &info.children {
                if !next.contains(c) {
                    next.push(*c);
                }
            }
            refined.insert(id, out);
        }
        if level + 1 < r.detail_levels() {
            level_ids.push(next);
        }
    }
    assert_eq!(
        raster, decoded,
        "incremental refinement differs from the raster decoder"
    );
    refined
}

#[test]
fn refining_one_diamond_at_a_time_reproduces_the_raster_decoder_lossless() {
    let enc = korea(RateMode::Lossless, 32);
    refine_everything(&enc);
}

#[test]
fn refining_one_diamond_at_a_time_reproduces_the_raster_decoder_rms_and_n64() {
    refine_everything(&korea(RateMode::RmsM(3.0), 32));
    refine_everything(&korea(RateMode::MaxErrorM(2.0), 64));
}

#[test]
fn bad_input_is_an_error_never_a_panic() {
    let enc = korea(RateMode::RmsM(3.0), 32);
    let r = PlanarRefiner::from_encoded(&enc).unwrap();
    let n = r.n();
    let domain = r.domain();
    let (root, root_grid) = r.root();
    let root_blob = enc.blobs[0][0].as_deref();
    // Wrong grid size, unknown or too fine ids.
    assert!(matches!(
        r.refine(root, &root_grid[1..], root_blob),
        Err(RefineError::WrongLength { .. })
    ));
    assert!(matches!(
        r.refine(PlanarId { x: 1, y: 1 }, root_grid, None),
        Err(RefineError::NotRefinable(_))
    ));
    // A corrupted blob, a truncated one, and another diamond's blob are caught by the
    // checksum over key and content.
    let mut bad = root_blob.unwrap().to_vec();
    let last = bad.len() - 1;
    bad[last] ^= 0x40;
    assert!(matches!(
        r.refine(root, root_grid, Some(&bad)),
        Err(RefineError::Decode(_))
    ));
    assert!(r.refine(root, root_grid, Some(&bad[..2])).is_err());
    let refined_root = r.refine(root, root_grid, root_blob).unwrap();
    let child = r.info(root).unwrap().children[0];
    let child_info = r.info(child).unwrap();
    let blobs = enc.blobs_by_key().unwrap();
    let other = blobs
        .iter()
        .filter(|(k, _)| **k != child_info.key)
        .min_by_key(|(k, _)| k.as_slice())
        .map(|(_, b)| b.as_slice());
    let grid = r.child_grid(child, &[&refined_root]).unwrap();
    if let Some(other) = other {
        assert!(matches!(
            r.refine(child, &grid, Some(other)),
            Err(RefineError::Decode(_))
        ));
    }
    // A lattice that is not the child's parent, and a missing parent.
    let grandchild = child_info.children[0];
    assert!(matches!(
        r.child_grid(grandchild, &[&refined_root]),
        Err(RefineError::NotAParent { .. })
    ));
    let refined_child = r
        .refine(child, &grid, blobs.get(&child_info.key).map(Vec::as_slice))
        .unwrap();
    let parents = domain.parents(grandchild).unwrap();
    if parents.len() == 2 && r.info(grandchild).is_some_and(|i| i.mask.is_none()) {
        assert!(matches!(
            r.child_grid(grandchild, &[&refined_child]),
            Err(RefineError::MissingParent { .. })
        ));
    }
    assert_eq!(refined_child.vertices.len(), (n + 1) * (n + 1));
}

#[test]
fn side_information_names_the_owned_children() {
    let enc = korea(RateMode::RmsM(3.0), 32);
    let r = PlanarRefiner::from_encoded(&enc).unwrap();
    let (root, grid) = r.root();
    let refined = r.refine(root, grid, enc.blobs[0][0].as_deref()).unwrap();
    let children = r.info(root).unwrap().children;
    assert!(!refined.child_classes.is_empty());
    for (child, _) in &refined.child_classes {
        assert!(
            children.contains(child),
            "{child:?} is not a child of the root"
        );
    }
}

/// The no-data flags are exact where they are given: a flagged child has no blob and
/// neither has any descendant; an unflagged child with a nonzero class has a blob itself
/// or below. Every child without data below and with a nonzero class is flagged.
#[test]
fn no_data_flags_name_exactly_the_empty_subtrees() {
    let enc = korea(RateMode::RmsM(9.0), 32);
    let r = PlanarRefiner::from_encoded(&enc).unwrap();
    // Whether a diamond or any descendant has a blob, bottom-up over the levels.
    let levels = r.detail_levels();
    // The encoder's order of each level's diamonds.
    let geom = RasterGeometry::new(enc.width, enc.height, enc.n).unwrap();
    let mut data: HashMap<PlanarId, bool> = HashMap::new();
    for l in (0..levels).rev() {
        for (i, blob) in enc.blobs[l].iter().enumerate() {
            let id = geom.level(l)[i].id;
            let below = r
                .info(id)
                .unwrap()
                .children
                .iter()
                .any(|c| data.get(c).copied().unwrap_or(false));
            data.insert(id, blob.is_some() || below);
        }
    }
    let (mut flagged, mut unflagged) = (0, 0);
    for l in 0..levels {
        for (i, blob) in enc.blobs[l].iter().enumerate() {
            let Some(blob) = blob else { continue };
            let id = geom.level(l)[i].id;
            let d = r.decode(id, blob).unwrap();
            for &(child, class) in &d.child_classes {
                let empty = d.empty_children.contains(&child);
                assert!(!(empty && class == 0), "class 0 carries no flag");
                if class > 0 {
                    assert_eq!(empty, !data[&child], "{child:?}");
                    if empty {
                        flagged += 1;
                    } else {
                        unflagged += 1;
                    }
                }
            }
        }
    }
    assert!(flagged > 10 && unflagged > 10, "{flagged} {unflagged}");
}
