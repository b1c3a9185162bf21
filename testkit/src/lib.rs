//! Test fixtures shared by the server's and the client's tests: two small repositories
//! of synthetic blobs (neither the server nor the fetch layer decodes, so any bytes do),
//! deterministic so two builds have the same content hash; and the parsed HTTP response
//! of their raw-socket clients ([`http::Response`]); `SKIP` lines ([`skip`]). Panics on
//! failure: test use only.
#![allow(clippy::unwrap_used, clippy::expect_used)]

pub mod http;
pub mod skip;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use quincunx_diamond::{PlanarDomain, PlanarId, SphereDomain, SphereId};
use quincunx_store::{Attribute, Metadata, NodataPolicy, RepositoryBuilder};

/// Planar fixture: m = 6, blobs on levels 0..PLANAR_LEVELS except [`PLANAR_LEAF`].
pub const PLANAR_M: u32 = 6;
/// Levels of the planar fixture.
pub const PLANAR_LEVELS: u32 = 4;
/// A level-2 diamond of the planar fixture that has no blob (a leaf), as a centre.
pub const PLANAR_LEAF: [i64; 3] = [16, 16, 0];
/// Sphere fixture: m = 3, blobs on levels 0..2.
pub const SPHERE_M: u32 = 3;
/// Levels of the sphere fixture.
pub const SPHERE_LEVELS: u32 = 2;

/// The bytes stored for a centre: distinct per diamond, 1..2000 bytes.
pub fn blob_for(c: [i64; 3]) -> Vec<u8> {
    let seed = (c[0] * 31 + c[1] * 1009 + c[2] * 7919).unsigned_abs();
    let len = 1 + (seed % 1999) as usize;
    (0..len).map(|i| (seed as usize + i * 7) as u8).collect()
}

fn metadata(domain: quincunx_store::Domain, m: u32, levels: u32) -> Metadata {
    Metadata {
        format_version: 0,
        complete: false,
        content_hash: String::new(),
        domain,
        m,
        n: 32,
        levels,
        attribute: Attribute {
            kind: quincunx_store::AttributeKind::Elevation,
            units: "m".into(),
        },
        extent: [1 << m, 1 << m],
        nodata: NodataPolicy {
            source_count: 0,
            handling: quincunx_store::NodataHandling::None,
        },
        georef: None,
        radius_m: (domain == quincunx_store::Domain::Sphere).then_some(6_371_000.0),
        channels: vec![],
        build: serde_json::json!({"fixture": true}),
        level_stats: vec![],
        coverage: None,
        inline_max_bytes: None,
        static_export: false,
    }
}

/// Every planar diamond above `levels`, by centre (z = 0), with its level.
pub fn planar_centres(m: u32, levels: u32) -> BTreeMap<[i64; 3], u32> {
    let d = PlanarDomain::new(m).unwrap();
    let mut out = BTreeMap::new();
    let mut frontier = vec![d.root()];
    while let Some(id) = frontier.pop() {
        let level = d.level(id).unwrap();
        if level >= levels || out.insert([id.x, id.y, 0], level).is_some() {
            continue;
        }
        frontier.extend(d.children(id).unwrap());
    }
    out
}

/// Every sphere diamond above `levels`, by centre, with its level.
pub fn sphere_centres(m: u32, levels: u32) -> BTreeMap<[i64; 3], u32> {
    let d = SphereDomain::new(m).unwrap();
    let mut out = BTreeMap::new();
    let mut frontier: Vec<SphereId> = d.roots().to_vec();
    while let Some(id) = frontier.pop() {
        let level = d.level(id).unwrap();
        if level >= levels || out.insert(id.c, level).is_some() {
            continue;
        }
        frontier.extend(d.children(id).unwrap());
    }
    out
}

/// Builds the planar (`plain`) and sphere (`globe`) fixtures under `dir`: their names
/// and paths.
pub fn build_fixtures(dir: &Path) -> Vec<(String, PathBuf)> {
    let planar = dir.join("plain");
    let d = PlanarDomain::new(PLANAR_M).unwrap();
    let mut b = RepositoryBuilder::create(&planar).unwrap();
    for (c, level) in planar_centres(PLANAR_M, PLANAR_LEVELS) {
        if c != PLANAR_LEAF {
            let id = PlanarId { x: c[0], y: c[1] };
            b.put(level, &d.key(id).unwrap(), &blob_for(c)).unwrap();
        }
    }
    b.publish(
        metadata(quincunx_store::Domain::Planar, PLANAR_M, PLANAR_LEVELS),
        false,
    )
    .unwrap();
    let sphere = dir.join("globe");
    let d = SphereDomain::new(SPHERE_M).unwrap();
    let mut b = RepositoryBuilder::create(&sphere).unwrap();
    for (c, level) in sphere_centres(SPHERE_M, SPHERE_LEVELS) {
        b.put(level, &d.key(SphereId { c }).unwrap(), &blob_for(c))
            .unwrap();
    }
    b.publish(
        metadata(quincunx_store::Domain::Sphere, SPHERE_M, SPHERE_LEVELS),
        false,
    )
    .unwrap();
    vec![("plain".into(), planar), ("globe".into(), sphere)]
}
