//! The refiners hold no tables of the repository's diamonds: what they derive of a
//! diamond from its id (whether it carries details, its level, key, mask and children)
//! equals what the encoder's full geometry tables say, for every diamond of every level,
//! with raster edges, odd sizes and coverages; and one opens at once whatever the
//! repository's size.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use std::collections::HashMap;

use quincunx_codec::coverage::Coverage;
use quincunx_codec::diamond::{PlanarId, SphereId};
use quincunx_codec::entropy::CodecModel;
use quincunx_codec::incremental::{PlanarRefiner, Refiner, SphereRefiner};
use quincunx_codec::raster::RasterGeometry;
use quincunx_codec::sphere_raster::{SphereFrame, SphereGeometry};

use common::planar_refiner;

fn sphere_refiner(face_side: usize, n: usize, coverage: Option<&Coverage>) -> SphereRefiner {
    let levels = SphereFrame::new(face_side, n, None)
        .unwrap()
        .detail_levels();
    SphereRefiner::new(
        face_side,
        n,
        coverage,
        vec![256; levels],
        CodecModel::default(),
        vec![vec![0; (n + 1) * (n + 1)]; 6],
    )
    .unwrap()
}

/// Every id of the planar domain at `level` (its lattice of centres), coded or not.
fn planar_ids(r: &PlanarRefiner, level: u32) -> Vec<PlanarId> {
    let d = r.domain();
    let h = 1usize << d.level_exponent(level);
    let s = d.size();
    (0..=s)
        .step_by(h)
        .flat_map(|y| (0..=s).step_by(h).map(move |x| PlanarId::new(x, y)))
        .filter(|&id| d.level(id).ok() == Some(level))
        .collect()
}

fn check_planar(w: usize, h: usize, n: usize, coverage: Option<&Coverage>) {
    let table = match coverage {
        Some(c) => RasterGeometry::with_coverage(w, h, n, c).unwrap(),
        None => RasterGeometry::new(w, h, n).unwrap(),
    };
    let r = planar_refiner(w, h, n, coverage);
    assert_eq!(r.detail_levels(), table.detail_levels());
    let mut coded = 0;
    for level in 0..table.detail_levels() {
        let slots: HashMap<PlanarId, usize> = table
            .level(level)
            .iter()
            .enumerate()
            .map(|(k, s)| (s.id, k))
            .collect();
        for id in planar_ids(&r, level as u32) {
            let Some(&k) = slots.get(&id) else {
                assert!(!r.is_coded(id), "{w}x{h} N={n}: {id:?} is not in the table");
                assert!(r.info(id).is_none(), "{id:?}");
                continue;
            };
            let s = &table.level(level)[k];
            assert!(r.is_coded(id), "{w}x{h} N={n}: {id:?} is in the table");
            let info = r.info(id).unwrap();
            assert_eq!(info.level, level);
            assert_eq!(info.key, s.key, "{id:?}");
            assert_eq!(info.mask, s.mask, "{w}x{h} N={n}: mask of {id:?}");
            if level + 1 < table.detail_levels() {
                let children: Vec<PlanarId> = s
                    .children
                    .iter()
                    .map(|&c| table.level(level + 1)[c].id)
                    .collect();
                assert_eq!(info.children, children, "{id:?}");
            }
            coded += 1;
        }
    }
    let all: usize = (0..table.detail_levels())
        .map(|l| table.level(l).len())
        .sum();
    assert_eq!(coded, all, "{w}x{h} N={n}: every table slot was visited");
}

#[test]
fn planar_diamonds_derived_from_their_ids_equal_the_geometry_tables() {
    for (w, h, n) in [
        (1025, 1025, 32),
        (700, 513, 32),
        (37, 1000, 16),
        (300, 200, 16),
        (2, 2, 2),
    ] {
        check_planar(w, h, n, None);
    }
    // Coverages with holes of whole blocks, of a pattern and of half the raster.
    let cov = Coverage::of_raster(700, 513, 32, |k| (k % 700 / 40 + k / 700 / 40) % 3 != 0);
    check_planar(700, 513, 32, Some(&cov));
    let half = Coverage::of_raster(300, 200, 16, |k| k % 300 < 150);
    check_planar(300, 200, 16, Some(&half));
}

fn check_sphere(face_side: usize, n: usize, coverage: Option<&Coverage>) {
    let table = match coverage {
        Some(c) => SphereGeometry::with_coverage(face_side, n, c).unwrap(),
        None => SphereGeometry::new(face_side, n).unwrap(),
    };
    let r = sphere_refiner(face_side, n, coverage);
    assert_eq!(r.detail_levels(), table.detail_levels());
    let d = r.domain();
    for level in 0..table.detail_levels() {
        let slots = table.level(level);
        for s in slots {
            assert!(r.is_coded(s.id));
            let info = r.info(s.id).unwrap();
            assert_eq!(info.level, level);
            assert_eq!(info.key, s.key, "{:?}", s.id);
            assert_eq!(
                info.mask, s.mask,
                "face {face_side} N={n}: mask of {:?}",
                s.id
            );
            if level + 1 < table.detail_levels() {
                let children: Vec<SphereId> = s
                    .children
                    .iter()
                    .map(|&c| table.level(level + 1)[c].id)
                    .collect();
                assert_eq!(info.children, children, "{:?}", s.id);
            }
        }
        // Every diamond of the level is in the table, and nothing else is coded there.
        let step = 1usize << d.level_exponent(level as u32);
        let s2 = face_side as i64;
        let mut ids: Vec<SphereId> = (0..6u8)
            .flat_map(|f| {
                (0..=s2).step_by(step).flat_map(move |v| {
                    (0..=s2)
                        .step_by(step)
                        .filter_map(move |u| d.from_face_chart(f, [u, v]).ok())
                })
            })
            .filter(|&id| d.level(id).ok() == Some(level as u32))
            .collect();
        ids.sort_by_key(|id| id.c);
        ids.dedup();
        assert_eq!(ids.len(), slots.len(), "level {level}");
    }
    let finest = table.detail_levels();
    let below = r.info(table.level(finest - 1)[0].id).unwrap().children;
    assert!(below.iter().all(|&c| !r.is_coded(c) && r.info(c).is_none()));
}

#[test]
fn planet_diamonds_derived_from_their_ids_equal_the_geometry_tables() {
    check_sphere(64, 16, None);
    check_sphere(128, 32, None);
    check_sphere(64, 32, None);
    let cov = Coverage::of_cube(128, 16, |k| (k / 7) % 5 != 0);
    check_sphere(128, 16, Some(&cov));
    let some = Coverage::of_cube(64, 16, |k| k % 3 == 0);
    check_sphere(64, 16, Some(&some));
}

#[test]
fn a_refiner_of_the_largest_planet_and_raster_opens_and_answers_at_once() {
    // 2^24 samples per face side (1.7e15 samples) and a 2^24 x 2^24 raster: a table of
    // their diamonds would not fit in memory; a refiner holds none.
    let planet = sphere_refiner(1 << 24, 32, None);
    let raster = planar_refiner(1 << 24, 1 << 24, 32, None);
    assert_eq!(planet.detail_levels(), 38);
    assert_eq!(raster.detail_levels(), 38);
    // Down to the finest level, anywhere: along the last child of each diamond.
    let mut id = planet.roots()[5].0;
    for level in 0..planet.detail_levels() {
        let info = planet.info(id).unwrap();
        assert_eq!(info.level, level);
        id = *info.children.last().unwrap();
    }
    assert!(!planet.is_coded(id) && planet.info(id).is_none());
    let mut id = raster.root().0;
    for level in 0..raster.detail_levels() {
        let info = raster.info(id).unwrap();
        assert_eq!(info.level, level);
        id = *info.children.last().unwrap();
    }
    assert!(!raster.is_coded(id));
}
