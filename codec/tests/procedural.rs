//! Procedural levels below a repository's finest one (the paper's missing data): the
//! graph refines on with made-up details, seamlessly, without changing a decoded sample,
//! and the same diamond always gets the same detail.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use std::collections::HashMap;

use common::{bundled_korea, grid};
use quincunx_codec::encode::{
    EncodeOptions, Encoded, FromEncoded, RateMode, decode_integers, encode,
};
use quincunx_codec::incremental::{
    PlanarRefiner, Procedural, RefineError, Refined, Refiner, SphereRefiner,
};

fn options(n: usize, mode: RateMode) -> EncodeOptions {
    EncodeOptions {
        n,
        mode,
        sparse: false,
        rdo: Default::default(),
    }
}

/// A Korea crop that is not a power of two plus one (border diamonds have masks).
fn korea_crop(w: usize, h: usize, n: usize) -> Encoded {
    encode(
        &common::bundled_korea_crop(w, h),
        options(n, RateMode::MaxErrorM(1.0)),
    )
    .unwrap()
}

/// Every level's grids, refining everything refinable coarse to fine through the trait.
/// Checks that each assembled child covers its valid vertices and that, within a level,
/// every point shared by several diamonds has one value (seamless). `point(id, i, j)`
/// is the vertex position in a common unit (`None` outside the data).
fn refine_all<R: Refiner>(
    r: &R,
    blobs: &HashMap<Vec<u8>, Vec<u8>>,
    point: impl Fn(R::Id, usize, usize) -> Option<[i64; 3]>,
) -> Vec<HashMap<R::Id, Vec<i32>>> {
    let n = r.n();
    let mut levels: Vec<HashMap<R::Id, Vec<i32>>> = vec![
        r.roots()
            .into_iter()
            .map(|(id, g)| (id, g.to_vec()))
            .collect(),
    ];
    for level in 0..r.levels() {
        let mut refined: HashMap<R::Id, Refined<R::Id>> = HashMap::new();
        for (&id, g) in &levels[level] {
            let info = r.info(id).unwrap();
            assert_eq!(info.level, level);
            assert_eq!(info.procedural, level >= r.detail_levels());
            assert_eq!(r.is_coded(id), !info.procedural);
            assert!(r.is_refinable(id));
            let blob = (!info.procedural)
                .then(|| blobs.get(&info.key).map(Vec::as_slice))
                .flatten();
            let details = blob.map(|b| r.decode(id, b).unwrap());
            refined.insert(id, r.synthesize(id, g, details.as_ref()).unwrap());
        }
        let mut next: HashMap<R::Id, Vec<i32>> = HashMap::new();
        let mut at: HashMap<[i64; 3], i32> = HashMap::new();
        for id in levels[level].keys() {
            for child in r.info(*id).unwrap().children {
                if next.contains_key(&child) || !r.is_refinable(child) {
                    continue;
                }
                let parents: Vec<&Refined<R::Id>> = r
                    .parents(child)
                    .iter()
                    .filter_map(|p| refined.get(p))
                    .collect();
                let (g, written) = r.partial_child_grid(child, &parents).unwrap();
                let mask = r.info(child).unwrap().mask;
                for i in 0..=n {
                    for j in 0..=n {
                        if mask.as_ref().is_none_or(|m| m.vertex(i, j)) {
                            assert!(written[i * (n + 1) + j], "{child:?} ({i},{j}) unwritten");
                            let p = point(child, i, j).expect("valid vertex has a position");
                            let v = g[i * (n + 1) + j];
                            assert_eq!(*at.entry(p).or_insert(v), v, "{child:?} seam at {p:?}");
                        }
                    }
                }
                next.insert(child, g);
            }
        }
        if level + 1 < r.levels() {
            assert!(!next.is_empty(), "level {} is empty", level + 1);
            levels.push(next);
        }
    }
    levels
}

#[test]
fn planar_procedural_levels_keep_every_decoded_sample_and_stay_seamless() {
    let (w, h, n) = (150, 97, 8);
    let enc = korea_crop(w, h, n);
    let decoded = decode_integers(&enc).unwrap();
    let r = PlanarRefiner::from_encoded(&enc)
        .unwrap()
        .with_procedural_levels(3, Procedural::Zero)
        .unwrap();
    let coded = r.detail_levels();
    assert_eq!(r.levels(), coded + 3);
    let domain = r.domain();
    let ni = n as i64;
    // Vertex positions in 1/N sample units.
    let point = |id, i: usize, j: usize| {
        let c = domain.corners(id).ok()?;
        let p = [0, 1].map(|k| {
            c[0][k] * ni + i as i64 * (c[1][k] - c[0][k]) + j as i64 * (c[3][k] - c[0][k])
        });
        let inside =
            (0..=(w as i64 - 1) * ni).contains(&p[0]) && (0..=(h as i64 - 1) * ni).contains(&p[1]);
        inside.then_some([p[0], p[1], 0])
    };
    let levels = refine_all(&r, &enc.blobs_by_key().unwrap(), point);
    // Zero details interpolate: wherever a procedural vertex falls on a sample of the
    // raster, it carries exactly the decoded value.
    let mut on_samples = 0;
    for grids in &levels[coded..] {
        for (&id, g) in grids {
            for i in 0..=n {
                for j in 0..=n {
                    if let Some(p) = point(id, i, j)
                        && p[0] % ni == 0
                        && p[1] % ni == 0
                    {
                        let (x, y) = ((p[0] / ni) as usize, (p[1] / ni) as usize);
                        assert_eq!(g[i * (n + 1) + j], decoded[y * w + x], "{id:?} ({i},{j})");
                        on_samples += 1;
                    }
                }
            }
        }
    }
    assert!(on_samples > w * h, "{on_samples}");
    // Two levels below the first procedural one: about four times as many diamonds
    // (fewer along the raster's edges).
    let deepest = levels.last().unwrap();
    assert_eq!(levels.len(), coded + 3);
    assert!(deepest.len() > 3 * levels[coded].len(), "{}", deepest.len());
}

#[test]
fn noise_is_bounded_zero_centred_and_the_same_every_time() {
    let enc = korea_crop(65, 65, 8);
    let amplitude = 5;
    let noisy = PlanarRefiner::from_encoded(&enc)
        .unwrap()
        .with_procedural_levels(1, Procedural::Noise { amplitude, seed: 7 })
        .unwrap();
    let zero = PlanarRefiner::from_encoded(&enc)
        .unwrap()
        .with_procedural_levels(1, Procedural::Zero)
        .unwrap();
    let domain = noisy.domain();
    let point = |id, i: usize, j: usize| {
        let c = domain.corners(id).ok()?;
        Some([0, 1, 2].map(|k| {
            if k == 2 {
                return 0;
            }
            c[0][k] * 8 + i as i64 * (c[1][k] - c[0][k]) + j as i64 * (c[3][k] - c[0][k])
        }))
    };
    let levels = refine_all(&zero, &enc.blobs_by_key().unwrap(), point);
    let finest = levels.last().unwrap();
    let (mut sum, mut count, mut differ) = (0i64, 0, 0);
    for (&id, g) in finest {
        let a = noisy.synthesize(id, g, None).unwrap();
        let b = noisy.synthesize(id, g, None).unwrap();
        let z = zero.synthesize(id, g, None).unwrap();
        assert_eq!(a, b, "deterministic");
        // Cells are predicted plus the detail, from vertices that the update moved by a
        // fraction of the neighbouring details.
        for (x, y) in a.cells.iter().zip(&z.cells) {
            let d = (x - y) as i64;
            assert!(d.abs() <= 2 * amplitude as i64, "{d}");
            sum += d;
            count += 1;
            differ += usize::from(d != 0);
        }
    }
    assert!(differ > count / 2, "{differ} of {count}");
    assert!(
        (sum as f64 / count as f64).abs() < 0.5,
        "mean {}",
        sum as f64 / count as f64
    );
    // Another seed gives other detail.
    let other = PlanarRefiner::from_encoded(&enc)
        .unwrap()
        .with_procedural_levels(1, Procedural::Noise { amplitude, seed: 8 })
        .unwrap();
    let (&id, g) = finest.iter().next().unwrap();
    assert_ne!(
        other.synthesize(id, g, None).unwrap(),
        noisy.synthesize(id, g, None).unwrap()
    );
}

#[test]
fn planet_procedural_levels_stay_seamless_across_cube_edges_and_corners() {
    let (face_side, n) = (16, 8);
    let g = common::synthetic_planet(face_side, n).unwrap();
    let enc = quincunx_codec::encode::encode_sphere(&g, options(n, RateMode::Lossless)).unwrap();
    let r = SphereRefiner::from_encoded(&enc)
        .unwrap()
        .with_procedural_levels(4, Procedural::Zero)
        .unwrap();
    // Positions in 1/N sample units: the same diamond in a domain N times larger.
    let big = quincunx_codec::diamond::SphereDomain::new(r.domain().m() + 3).unwrap();
    let point = |id: quincunx_codec::diamond::SphereId, i, j| {
        let scaled = quincunx_codec::diamond::SphereId::new(id.c.map(|x| x * n as i64));
        big.vertex_position(scaled, n, i, j).ok()
    };
    let levels = refine_all(&r, &enc.blobs_by_key().unwrap(), point);
    assert_eq!(levels.len(), r.detail_levels() + 4);
}

#[test]
fn procedural_levels_beyond_the_id_space_or_on_sparse_data_are_errors() {
    let enc = korea_crop(65, 65, 8);
    let r = PlanarRefiner::from_encoded(&enc).unwrap();
    let max = r.domain().max_level() as usize;
    let coded = r.detail_levels();
    assert!(
        PlanarRefiner::from_encoded(&enc)
            .unwrap()
            .with_procedural_levels(max - coded, Procedural::Zero)
            .is_ok()
    );
    let err = r
        .with_procedural_levels(max - coded + 1, Procedural::Zero)
        .unwrap_err();
    assert!(matches!(err, RefineError::Procedural(_)), "{err}");
    let mut g = grid(&bundled_korea());
    // A sparse encoding: the left half has no data.
    for y in 0..g.height {
        for x in 0..g.width / 2 {
            g.values_m[y * g.width + x] = f64::NAN;
        }
    }
    let sparse = encode(
        &g,
        EncodeOptions {
            n: 32,
            mode: RateMode::MaxErrorM(2.0),
            sparse: true,
            rdo: Default::default(),
        },
    )
    .unwrap();
    let err = PlanarRefiner::from_encoded(&sparse)
        .unwrap()
        .with_procedural_levels(1, Procedural::Zero)
        .unwrap_err();
    assert!(err.to_string().contains("sparse"), "{err}");
    // Zero extra levels are always fine.
    assert!(
        PlanarRefiner::from_encoded(&sparse)
            .unwrap()
            .with_procedural_levels(0, Procedural::Zero)
            .is_ok()
    );
}
