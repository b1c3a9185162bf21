//! Packages (`quincunx_store::answer`, `docs/blob-format.md`): a diamond's blob with its
//! small owned children's, one answer instead of several.
//!
//! - every package of a repository built from the bundled SRTM crop at 9 m RMS (blobs of
//!   tens of bytes) follows the rule: it holds the diamond's own blob, and exactly the
//!   owned children whose package fits the inlining limit, recursively;
//! - the server serves bare blobs at `.../d/` and packages at `.../p/`, with different
//!   validators, and `.../p/` is a 404 for a repository built without a limit;
//! - a session that asks for packages converges to the same cut as one that does not and
//!   as the local reference, with no crack in any frame, in fewer requests.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use crate::common;

use std::path::Path;
use std::time::{Duration, Instant};

use common::stream::{Served, built_and_local, converge, cut_of, reference_cut, view_of};
use quincunx_client::flight::Flight;
use quincunx_client::session::{Session, SessionConfig};
use quincunx_codec::diamond::PlanarDomain;
use quincunx_repo_tools::build::{self, BuildArgs};
use quincunx_store::Repository;
use quincunx_store::answer::{self, IdSpace};

fn build_korea(out: &Path, inline_bytes: u64) {
    build::run(&BuildArgs {
        rms_m: Some(9.0),
        inline_bytes,
        overwrite: true,
        ..BuildArgs::new(
            common::workspace_root().join("data/korea_srtm3_1025.json"),
            out,
        )
    })
    .unwrap();
}

/// Checks the package of `c` against the rule; returns the blobs it carries.
fn check_package(
    repo: &Repository,
    domain: &IdSpace,
    c: [i64; 3],
    bytes: &[u8],
    limit: usize,
) -> usize {
    let parsed = answer::parse(bytes, true).unwrap();
    let (key, _) = domain.key_level(c).unwrap();
    assert_eq!(parsed.blob, &repo.get(&key).unwrap().unwrap()[..], "{c:?}");
    let owned = domain.owned_children(c).unwrap();
    let mut carried = 0;
    for (i, &child) in owned.iter().enumerate() {
        let full = repo.package(domain, child).unwrap();
        match parsed.children.iter().find(|(j, _)| *j == i) {
            Some(&(_, inner)) => {
                assert!(
                    inner.len() <= limit,
                    "{child:?} carried at {} bytes",
                    inner.len()
                );
                assert_eq!(Some(inner), full.as_deref(), "{child:?}");
                carried += 1 + check_package(repo, domain, child, inner, limit);
            }
            // Not carried: no blob, or too large.
            None => assert!(full.is_none_or(|p| p.len() > limit), "{child:?} left out"),
        }
    }
    carried
}

#[test]
fn packages_follow_the_rule_and_stream_the_same_cut_in_fewer_requests() {
    let dir = tempfile::tempdir().unwrap();
    let (built, local) = built_and_local(dir.path(), "korea", |out| build_korea(out, 512));
    let (limit, blobs) = {
        let repo = Repository::open(&local).unwrap();
        let meta = repo.metadata();
        let limit = meta.inline_max_bytes.expect("default builds have a limit") as usize;
        let domain = IdSpace::of(meta).unwrap();
        let planar = PlanarDomain::new(meta.m).unwrap();
        let mut carried = 0;
        let mut blobs = Vec::new();
        for kv in repo.blobs() {
            let (key, blob) = kv.unwrap();
            let id = planar.id_from_key(&key).unwrap();
            let c = [id.x, id.y, 0];
            let package = repo.package(&domain, c).unwrap().unwrap();
            carried += check_package(&repo, &domain, c, &package, limit);
            blobs.push((c, blob.to_vec(), package));
        }
        assert!(
            carried * 4 > blobs.len(),
            "{carried} of {} carried",
            blobs.len()
        );
        (limit, blobs)
    };
    assert_eq!(limit, 512);

    let server = Served::one("127.0.0.1:0".parse().unwrap(), "korea", &built);
    let remote =
        quincunx_client::fetch::Remote::open(&server.url(), "korea", Duration::from_secs(10))
            .unwrap()
            .0;
    for (c, blob, package) in blobs.iter().step_by(97) {
        let d = common::get(server.addr, &remote.blob_path(*c), &[]);
        let p = common::get(server.addr, &remote.package_path(*c), &[]);
        assert_eq!((d.status, p.status), (200, 200));
        assert_eq!(&d.body, blob);
        assert_eq!(&p.body, package);
        assert_ne!(d.header("etag"), p.header("etag"));
        assert!(p.header("cache-control").unwrap().contains("immutable"));
    }

    // One jump view, with and without packages.
    let mut packaged: Session =
        Session::open(&server.url(), "korea", SessionConfig::default()).unwrap();
    let mut bare: Session = Session::open(
        &server.url(),
        "korea",
        SessionConfig {
            package_factor: None,
            ..SessionConfig::default()
        },
    )
    .unwrap();
    let flight = Flight::builtin_for("jump", &mut packaged, 2).unwrap();
    let leg = flight.legs.iter().find(|l| l.jump).unwrap();
    let world = packaged.world();
    let view = view_of(&leg.from, &world);
    let start = Instant::now();
    converge(&mut packaged, &view, start, Duration::from_secs(60));
    converge(&mut bare, &view, start, Duration::from_secs(60));
    let reference =
        reference_cut::<quincunx_codec::incremental::PlanarRefiner>(&local, "korea", &view, world);
    assert_eq!(cut_of(packaged.dag()), reference);
    assert_eq!(cut_of(bare.dag()), reference);
    let (p, b) = (packaged.fetch_stats(), bare.fetch_stats());
    assert_eq!(b.carried, 0);
    assert!(p.carried > 0, "{p:?}");
    assert!(p.requests < b.requests, "packaged {p:?}\nbare {b:?}");
    assert_eq!(packaged.failures() + bare.failures(), 0);
}

#[test]
fn a_repository_built_without_a_limit_serves_no_packages() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("korea");
    build_korea(&out, 0);
    assert_eq!(
        Repository::open(&out).unwrap().metadata().inline_max_bytes,
        None
    );
    let server = Served::one("127.0.0.1:0".parse().unwrap(), "korea", &out);
    let remote =
        quincunx_client::fetch::Remote::open(&server.url(), "korea", Duration::from_secs(10))
            .unwrap()
            .0;
    let root = [512, 512, 0];
    assert_eq!(
        common::get(server.addr, &remote.blob_path(root), &[]).status,
        200
    );
    let p = common::get(server.addr, &remote.package_path(root), &[]);
    assert_eq!(p.status, 404, "{}", p.text());
    // A session asks for bare blobs only.
    let mut session: Session =
        Session::open(&server.url(), "korea", SessionConfig::default()).unwrap();
    let flight = Flight::builtin_for("jump", &mut session, 2).unwrap();
    let leg = flight.legs.iter().find(|l| l.jump).unwrap();
    let view = view_of(&leg.from, &session.world());
    converge(&mut session, &view, Instant::now(), Duration::from_secs(60));
    assert_eq!(session.fetch_stats().carried, 0);
    assert_eq!(session.failures(), 0);
}
