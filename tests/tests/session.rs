//! Streaming sessions end to end: a repository built from the bundled DEM, served by a
//! real server over loopback, streamed by `quincunx_client::session::Session`.
//!
//! - a jump flight: every frame's cut is crack-free and covers the raster once, every jump
//!   reaches full quality, and the final cut is bit-identical to refining with the
//!   repository read locally;
//! - a server killed mid-flight and restarted: no panic, every frame consistent, and the
//!   same final cut once it is back;
//! - `quincunx fly` with a flight file, and its errors;
//! - repositories the client cannot stream are refused with clear errors;
//! - the sans-IO core alone, fed answers from a local copy with made-up time, reaches the
//!   same cut.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use crate::common;

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use common::stream::{Served, converge, cut_of, reference_cut, view_of};
use quincunx_client::fetch::link::LinkProxy;
use quincunx_client::flight::{self, Flight, FlyOptions};
use quincunx_client::session::{
    PlanetSession, Session, SessionConfig, SessionError, Store, Stores, StreamConfig, StreamCore,
};
use std::collections::{HashMap, HashSet};
use std::sync::Arc;

use glam::DVec3;
use quincunx_client::fetch::{FetchStats, Key};
use quincunx_client::refine::Clock;
use quincunx_client::view::View;
use quincunx_codec::incremental::{Details, PlanarRefiner, Procedural, Refiner};
use quincunx_repo_tools::args::RefineArgs;
use quincunx_repo_tools::fly::{self, FlyArgs};
use quincunx_server::RepoConfig;
use quincunx_store::Repository;

const REPO: &str = "korea";

/// Builds the bundled 1025 x 1025 SRTM crop at 2 m RMS into `dir/built/korea`, served and
/// read locally at once.
fn build_korea(dir: &Path) -> (PathBuf, PathBuf) {
    common::stream::built_and_local(dir, REPO, common::build_bundled_korea)
}

/// The same crop at 0.25 m RMS, several times the 2 m build's bytes, for the tests that
/// need data still to come after the first views: the 2 m build is about 60 KB since blob
/// version 3, and its overviews and the flight's height-finding fetches (packages carry
/// small children) bring in nearly all of it.
fn build_korea_fine(dir: &Path) -> (PathBuf, PathBuf) {
    use quincunx_repo_tools::build::{self, BuildArgs};
    common::stream::built_and_local(dir, REPO, |output| {
        build::run(&BuildArgs {
            rms_m: Some(0.25),
            overwrite: true,
            ..BuildArgs::new(
                common::workspace_root().join("data/korea_srtm3_1025.json"),
                output,
            )
        })
        .unwrap();
    })
}

#[test]
fn a_jump_flight_is_crack_free_every_frame_and_ends_on_the_local_cut() {
    let dir = tempfile::tempdir().unwrap();
    let (built, local) = build_korea(dir.path());
    let server = Served::one("127.0.0.1:0".parse().unwrap(), REPO, &built);
    let mut session = Session::<PlanarRefiner>::open(
        &format!("http://{}", server.addr),
        REPO,
        SessionConfig::default(),
    )
    .unwrap();
    let flight = Flight::builtin_for("jump", &mut session, 7).unwrap();
    let opts = FlyOptions {
        check_every: 1,
        ..FlyOptions::default()
    };
    let mut frames = 0;
    let report = flight::fly(&mut session, &flight, &opts, |f| {
        frames += 1;
        assert_eq!((f.cracks, f.coverage_errors), (0, 0), "{f:?}");
    })
    .unwrap();
    assert_eq!(report.frames, frames);
    assert_eq!(report.frames_checked, frames);
    assert_eq!((report.cracks, report.coverage_errors), (0, 0));
    assert_eq!(report.jumps.len(), 6);
    assert_eq!(report.jumps_unfinished, 0, "{report:?}");
    assert_eq!(report.failures, 0);
    // Everything refinement used was fetched, once.
    assert!(report.bytes_in_final_cuts > 0);
    assert!(
        report.bytes_fetched >= report.bytes_in_final_cuts,
        "{report:?}"
    );
    assert!(
        report.leaves > 0,
        "a 2 m RMS repository has leaves: {report:?}"
    );

    // The last view, converged: the same cut, bit for bit, as refining locally.
    let last = view_of(&flight.legs.last().unwrap().from, &session.world());
    converge(&mut session, &last, Instant::now(), Duration::from_secs(30));
    let streamed = cut_of(session.dag());
    // The renderer's snapshot is that cut.
    let snapshot = session.snapshot();
    assert_eq!(snapshot.patches.len(), streamed.len());
    for (p, (id, half, grid)) in snapshot.patches.iter().zip(&streamed) {
        assert_eq!(
            (&p.id, &p.half, p.grid.as_slice()),
            (id, half, grid.as_slice())
        );
        assert_eq!(p.grid.len(), (snapshot.n + 1) * (snapshot.n + 1));
    }
    let world = session.world();
    drop(session);
    server.kill();
    let expected = reference_cut::<PlanarRefiner>(&local, REPO, &last, world);
    assert!(expected.len() > 100, "{}", expected.len());
    assert_eq!(streamed.len(), expected.len());
    assert!(
        streamed == expected,
        "the streamed cut differs from the local one"
    );
}

#[test]
fn a_server_killed_mid_flight_and_restarted_costs_nothing_but_time() {
    let dir = tempfile::tempdir().unwrap();
    let (built, local) = build_korea_fine(dir.path());
    let server = Served::one("127.0.0.1:0".parse().unwrap(), REPO, &built);
    let addr = server.addr;
    // A slow link, so the kill lands while data is still coming.
    let link = LinkProxy::start(addr, 1_000.0, Duration::from_millis(40)).unwrap();
    let config = SessionConfig {
        timeout: Duration::from_secs(2),
        ..SessionConfig::default()
    };
    let mut session =
        Session::<PlanarRefiner>::open(&format!("http://{}", link.local_addr()), REPO, config)
            .unwrap();
    let flight = Flight::builtin_for("jump", &mut session, 3).unwrap();
    // A view away from the first one (whose data finding the flight's heights fetched).
    let leg = flight.legs.iter().rfind(|l| l.jump).unwrap();
    let view = view_of(&leg.from, &session.world());
    let before = session.fetch_stats().responses;
    let start = Instant::now();
    let frame = |session: &mut Session| {
        let f = session
            .update(&view, start.elapsed(), Duration::from_millis(8))
            .unwrap();
        let check = session.dag().check_cut();
        assert!(check.ok(), "{check:?}");
        std::thread::sleep(Duration::from_millis(10));
        f
    };
    // Until some, not all, data has arrived.
    let t0 = Instant::now();
    loop {
        let f = frame(&mut session);
        // Packages bring a diamond's small children in its answer: a few answers are
        // a good part of the view.
        if session.fetch_stats().responses >= before + 4 {
            assert!(
                !f.refine.converged,
                "converged before the kill: {f:?} {:?}",
                session.fetch_stats()
            );
            break;
        }
        assert!(t0.elapsed() < Duration::from_secs(30), "no data: {f:?}");
    }
    server.kill();
    let down = Instant::now();
    while down.elapsed() < Duration::from_millis(1500) {
        frame(&mut session);
    }
    let stats = session.fetch_stats();
    assert!(
        stats.errors.total() > 0 || session.failures() > 0,
        "the outage went unnoticed: {stats:?}"
    );
    let restarted = Served::one(addr, REPO, &built);
    converge(&mut session, &view, start, Duration::from_secs(90));
    let streamed = cut_of(session.dag());
    let world = session.world();
    drop(session);
    restarted.kill();
    assert!(streamed == reference_cut::<PlanarRefiner>(&local, REPO, &view, world));
}

#[test]
fn lookahead_follows_the_measured_link() {
    let dir = tempfile::tempdir().unwrap();
    let (built, _) = build_korea_fine(dir.path());
    let server = Served::one("127.0.0.1:0".parse().unwrap(), REPO, &built);
    // (kbit/s, lookahead expected once the link is measured): 20 Mbit/s x 100 ms carries
    // hundreds of blobs per round trip; 300 kbit/s about twenty, fewer than the 32 below
    // which lookahead would only queue ahead of wanted data.
    for (kbit_s, expected) in [(20_000.0, 2), (300.0, 0)] {
        let link = LinkProxy::start(server.addr, kbit_s, Duration::from_millis(100)).unwrap();
        let mut session = Session::<PlanarRefiner>::open(
            &format!("http://{}", link.local_addr()),
            REPO,
            SessionConfig::default(),
        )
        .unwrap();
        assert_eq!(session.lookahead_levels(), 2, "unmeasured: as configured");
        session.warm_up(Duration::from_secs(3)).unwrap();
        // The overviews alone move too little (tens of KB) to find out what a fast link
        // can carry: also stream a close view at half a pixel for up to 2 s.
        let flight = Flight::builtin_for("jump", &mut session, 7).unwrap();
        let close = quincunx_client::view::View {
            tolerance_px: 0.5,
            ..view_of(&flight.legs.last().unwrap().from, &session.world())
        };
        let t0 = Instant::now();
        while t0.elapsed() < Duration::from_secs(2) {
            let f = session
                .update(&close, t0.elapsed(), Duration::from_millis(8))
                .unwrap();
            if f.refine.full_quality {
                break;
            }
            std::thread::sleep(Duration::from_millis(5));
        }
        let stats = session.fetch_stats();
        assert!(
            stats.rtt.is_some() && stats.bandwidth_bit_s > 0.0,
            "{stats:?}"
        );
        assert_eq!(
            session.lookahead_levels(),
            expected,
            "{kbit_s} kbit/s: {stats:?}"
        );
    }
    server.kill();
}

fn fly_args(url: &str, path: &str) -> FlyArgs {
    FlyArgs {
        refine: RefineArgs {
            tolerance_px: 2.0,
            ..RefineArgs::default()
        },
        frame_budget_ms: 8.0,
        viewport: [1280, 720],
        json: true,
        ..FlyArgs::new(url, REPO, path)
    }
}

#[test]
fn quincunx_fly_runs_a_flight_file_and_refuses_what_it_cannot_do() {
    let dir = tempfile::tempdir().unwrap();
    let (built, _local) = build_korea(dir.path());
    let server = Served::one("127.0.0.1:0".parse().unwrap(), REPO, &built);
    let url = format!("http://{}", server.addr);

    // A two-leg flight file over the raster (about 94 km across): a move, then a jump.
    let file = dir.path().join("flight.json");
    std::fs::write(
        &file,
        r#"{"legs": [
            {"duration_s": 1.0, "from": {"eye": [20000, 20000, 4000], "target": [30000, 30000, 0]},
             "to": {"eye": [30000, 25000, 3000], "target": [40000, 35000, 0]}},
            {"duration_s": 5.0, "from": {"eye": [70000, 70000, 3000], "target": [60000, 60000, 0]},
             "jump": true, "settle_s": 0.2}
        ]}"#,
    )
    .unwrap();
    fly::run(&fly_args(&url, file.to_str().unwrap())).unwrap();
    // Through an emulated link too.
    let mut linked = fly_args(&url, file.to_str().unwrap());
    linked.link = Some((20_000.0, 10.0));
    fly::run(&linked).unwrap();

    let err = |args: FlyArgs| format!("{:#}", fly::run(&args).unwrap_err());
    assert!(err(fly_args(&url, "nowhere")).contains("built-in flights are approach"));
    let bad = dir.path().join("bad.json");
    std::fs::write(
        &bad,
        r#"{"legs": [{"duration_s": -1, "from": {"eye": [0,0,0], "target": [1,1,1]}}]}"#,
    )
    .unwrap();
    assert!(err(fly_args(&url, bad.to_str().unwrap())).contains("durations must be positive"));
    std::fs::write(&bad, "{").unwrap();
    assert!(err(fly_args(&url, bad.to_str().unwrap())).contains("flight file"));
    let mut colour = fly_args(&url, "jump");
    colour.server.colour = Some("imagery".into());
    // A colour layer the server does not have.
    assert!(err(colour).contains("opening korea with colour imagery"));
    let mut missing = fly_args(&url, "jump");
    missing.server.repo = "nope".into();
    assert!(err(missing).contains("404"));
    assert!(err(fly_args("http://127.0.0.1:1", "jump")).contains("opening korea"));
    server.kill();
}

#[test]
fn repositories_the_client_cannot_stream_are_refused_clearly() {
    let dir = tempfile::tempdir().unwrap();
    let repos = quincunx_testkit::build_fixtures(dir.path())
        .into_iter()
        .map(|(name, path)| RepoConfig { name, path })
        .collect();
    let server = Served::start("127.0.0.1:0".parse().unwrap(), repos);
    let url = format!("http://{}", server.addr);
    // A planet is not planar, and a planar repository is no planet.
    match Session::<PlanarRefiner>::open(&url, "globe", SessionConfig::default()) {
        Err(SessionError::Unsupported { reason, .. }) => {
            assert!(
                reason.contains("open it with the planet session"),
                "{reason}"
            )
        }
        other => panic!("{:?}", other.err()),
    }
    match PlanetSession::open(&url, "plain", SessionConfig::default()) {
        Err(SessionError::Unsupported { reason, .. }) => {
            assert!(
                reason.contains("open it with the planar session"),
                "{reason}"
            )
        }
        other => panic!("{:?}", other.err()),
    }
    // The fixture planet has no channels.
    match PlanetSession::open(&url, "globe", SessionConfig::default()) {
        Err(SessionError::Metadata { reason, .. }) => assert!(reason.contains("no channels")),
        other => panic!("{:?}", other.err()),
    }
    // Synthetic metadata without a real codec model.
    match Session::<PlanarRefiner>::open(&url, "plain", SessionConfig::default()) {
        Err(SessionError::Metadata { reason, .. }) => assert!(!reason.is_empty()),
        other => panic!("{:?}", other.err()),
    }
    server.kill();
}

/// The korea crop built in `dir`, served, and a session on it with the default config.
fn served_korea(dir: &Path) -> (Served, Session<PlanarRefiner>) {
    let (built, _local) = build_korea(dir);
    let server = Served::one("127.0.0.1:0".parse().unwrap(), REPO, &built);
    let session =
        Session::<PlanarRefiner>::open(&server.url(), REPO, SessionConfig::default()).unwrap();
    (server, session)
}

/// One hold leg of `duration_s` over the middle of the korea crop.
fn hold_flight(duration_s: f64) -> Flight {
    Flight::from_json(
        "hold",
        &format!(
            r#"{{"legs": [{{"duration_s": {duration_s},
                "from": {{"eye": [40000, 30000, 4000], "target": [50000, 40000, 0]}}}}]}}"#
        ),
    )
    .unwrap()
}

#[test]
fn the_runners_checks_are_kept_off_the_flight_clock_and_reported_apart() {
    let dir = tempfile::tempdir().unwrap();
    let (server, mut session) = served_korea(dir.path());
    // Every frame checked, and every check made 60 ms slower than it is: were the checks
    // on the flight's clock, a 2 s leg would hold at most 2 / 0.06 = 33 frames.
    let delay = Duration::from_millis(60);
    let leg_s = 2.0;
    let opts = FlyOptions {
        check_every: 1,
        check_delay: delay,
        viewport_px: [1280, 720],
        tolerance_px: 2.0,
        ..FlyOptions::default()
    };
    let wall = Instant::now();
    let mut last_t = 0.0f64;
    let report = flight::fly(&mut session, &hold_flight(leg_s), &opts, |f| {
        assert_eq!((f.cracks, f.coverage_errors), (0, 0), "{f:?}");
        assert!(f.check_ms >= 60.0, "{f:?}");
        last_t = last_t.max(f.t_s);
    })
    .unwrap();
    let wall_s = wall.elapsed().as_secs_f64();
    let bound = (leg_s / delay.as_secs_f64()).floor() as usize;
    assert!(
        report.frames > bound + 7,
        "{} frames: the checks were counted in the flight's time ({report:?})",
        report.frames
    );
    assert_eq!(report.frames_checked, report.frames);
    // The flight's own clock ran for the leg; the checks' time is reported apart.
    assert!(last_t < leg_s, "{last_t}");
    assert!(report.seconds < leg_s + 1.0, "{report:?}");
    assert!(
        report.check_ms_total >= 60.0 * report.frames as f64,
        "{report:?}"
    );
    assert!(report.check_ms_p50 >= 60.0 && report.check_ms_max >= report.check_ms_p50);
    let accounted = report.seconds + report.check_ms_total / 1e3;
    assert!((report.wall_seconds - accounted).abs() < 0.05, "{report:?}");
    assert!(report.wall_seconds <= wall_s);
    assert!(report.frames_per_s > bound as f64 / leg_s);
    // With a share, the checks stop where they would take more than it of the flight
    // (one check past it at most), and the frames not checked are counted as such.
    let capped = FlyOptions {
        check_max_share: Some(0.25),
        ..opts
    };
    let report = flight::fly(&mut session, &hold_flight(leg_s), &capped, |_| {}).unwrap();
    let one_check_ms = report.check_ms_max;
    assert!(
        report.check_ms_total <= 0.25 * report.seconds * 1e3 + one_check_ms,
        "{report:?}"
    );
    assert!(report.frames_checked > 0 && report.frames_checked < report.frames);
    server.kill();
}

#[test]
fn the_frame_rate_never_exceeds_the_pace_when_legs_end_at_full_quality() {
    let dir = tempfile::tempdir().unwrap();
    let (_server, mut session) = served_korea(dir.path());
    // Ten jumps to one high view, each ended as soon as it is at full quality: after the
    // first, every leg is one frame. Each frame still holds the screen for its period.
    let leg = r#"{"duration_s": 5, "jump": true, "settle_s": 0,
        "from": {"eye": [40000, 30000, 60000], "target": [40000, 30001, 0]}}"#;
    let legs = [leg; 10].join(",");
    let flight = Flight::from_json("jumps", &format!(r#"{{"legs": [{legs}]}}"#)).unwrap();
    let opts = FlyOptions {
        viewport_px: [640, 360],
        ..FlyOptions::default()
    };
    let report = flight::fly(&mut session, &flight, &opts, |_| {}).unwrap();
    assert_eq!(report.jumps_unfinished, 0, "{report:?}");
    assert!(report.frames >= 10, "{report:?}");
    // The period's rounding to nanoseconds is the margin.
    assert!(
        report.frames_per_s > 0.0 && report.frames_per_s <= opts.fps * 1.000_01,
        "{} frames in {} s",
        report.frames,
        report.seconds
    );
    assert!(report.seconds >= report.frames as f64 / opts.fps * 0.999_99);
}

/// A server that answers the metadata of `repo` from `upstream` at once and every other
/// request with a head announcing 100 000 bytes and a body trickling a byte every 50 ms.
fn start_trickler(upstream: std::net::SocketAddr, repo: &str) -> std::net::SocketAddr {
    use std::io::{Read, Write};
    let meta_path = format!("/repos/{repo}/metadata.json");
    let meta = common::get(upstream, &meta_path, &[]).body;
    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = listener.local_addr().unwrap();
    std::thread::spawn(move || {
        for s in listener.incoming() {
            let Ok(mut s) = s else { return };
            let (meta, meta_path) = (meta.clone(), meta_path.clone());
            std::thread::spawn(move || {
                let mut buf = [0u8; 8192];
                let Ok(n) = s.read(&mut buf) else { return };
                let head = String::from_utf8_lossy(&buf[..n]).into_owned();
                if head.starts_with(&format!("GET {meta_path} ")) {
                    let mut reply =
                        format!("HTTP/1.1 200 OK\r\nContent-Length: {}\r\n\r\n", meta.len())
                            .into_bytes();
                    reply.extend_from_slice(&meta);
                    let _ = s.write_all(&reply);
                    return;
                }
                quincunx_testkit::http::trickle_answer(&mut s);
            });
        }
    });
    addr
}

#[test]
fn a_flight_against_a_trickling_server_reports_its_timeouts() {
    let dir = tempfile::tempdir().unwrap();
    let (built, _local) = build_korea(dir.path());
    let server = Served::one("127.0.0.1:0".parse().unwrap(), REPO, &built);
    let trickler = start_trickler(server.addr, REPO);
    let url = format!("http://{trickler}");
    let config = SessionConfig {
        request_deadline: Duration::from_secs(1),
        ..SessionConfig::default()
    };
    let mut session = Session::<PlanarRefiner>::open(&url, REPO, config).unwrap();
    let opts = FlyOptions {
        viewport_px: [1280, 720],
        tolerance_px: 2.0,
        ..FlyOptions::default()
    };
    let report = flight::fly(&mut session, &hold_flight(4.0), &opts, |_| {}).unwrap();
    assert_eq!(report.bytes_fetched, 0, "{report:?}");
    assert!(report.fetch_timeouts > 0, "{report:?}");
    assert!(report.fetch_errors >= report.fetch_timeouts, "{report:?}");
    // `quincunx fly` says so instead of ending quietly.
    let file = dir.path().join("hold.json");
    std::fs::write(&file, serde_json::to_string(&hold_flight(4.0)).unwrap()).unwrap();
    let args = FlyArgs {
        deadline_s: 1.0,
        ..fly_args(&url, file.to_str().unwrap())
    };
    let err = format!("{:#}", fly::run(&args).unwrap_err());
    assert!(
        err.contains("fetched nothing") && err.contains("timeouts"),
        "{err}"
    );
    server.kill();
}

/// The answers a test hands the core: what a data access layer would hold.
#[derive(Default)]
struct Answers {
    values: std::cell::RefCell<HashMap<Key, Arc<Details>>>,
    leaves: std::cell::RefCell<HashSet<Key>>,
}

impl Store<Details> for Answers {
    fn is_leaf(&self, key: Key) -> bool {
        self.leaves.borrow().contains(&key)
    }

    fn cached(&self, key: Key) -> Option<Arc<Details>> {
        self.values.borrow().get(&key).cloned()
    }

    fn contains(&self, key: Key) -> bool {
        self.values.borrow().contains_key(&key)
    }
}

/// A clock that never moves: every frame may refine all it can.
struct Frozen;

impl Clock for Frozen {
    fn now(&self) -> Duration {
        Duration::ZERO
    }
}

#[test]
fn the_core_alone_streams_to_the_cut_refining_locally_gives() {
    // No server, socket, thread or clock: each frame's requests are answered from a local
    // copy before the next frame (one round trip a frame), time is made up.
    let dir = tempfile::tempdir().unwrap();
    let (_, local) = build_korea(dir.path());
    let repo = Repository::open(&local).unwrap();
    let mut core = StreamCore::<PlanarRefiner>::new(
        REPO,
        repo.metadata(),
        None,
        StreamConfig::default(),
        None,
        Procedural::Zero,
    )
    .unwrap();
    let b = core.bounds();
    let view = View {
        eye: DVec3::new(b.min.x, b.min.y, b.max.z + 2_000.0),
        target: (b.min + b.max) / 2.0,
        up: DVec3::Z,
        fov_y_rad: 60f64.to_radians(),
        viewport_px: [1920, 1080],
        tolerance_px: 1.0,
    };
    let answers = Answers::default();
    let mut pending: Vec<Key> = Vec::new();
    let mut asked: HashSet<Key> = HashSet::new();
    for frame in 0..400u64 {
        for key in pending.drain(..) {
            let id = PlanarRefiner::id_of(key);
            let info = core.refiner().info(id).unwrap();
            let value = repo
                .get(&info.key)
                .unwrap()
                .map(|blob| Arc::new(core.refiner().decode(id, &blob).unwrap()));
            match &value {
                Some(v) => answers.values.borrow_mut().insert(key, Arc::clone(v)),
                None => {
                    answers.leaves.borrow_mut().insert(key);
                    None
                }
            };
            core.arrived(key, value);
        }
        let stores = Stores {
            elevation: &answers,
            colour: None,
        };
        let now = Duration::from_millis(16 * frame);
        let (f, requests) = core
            .frame(
                &view,
                now,
                Duration::from_secs(1),
                &Frozen,
                stores,
                FetchStats::default,
            )
            .unwrap();
        let check = core.dag().check_cut();
        assert!(check.ok(), "frame {frame}: {check:?}");
        let submit = requests.elevation;
        if f.refine.converged && submit.wants.is_empty() {
            let expected = reference_cut::<PlanarRefiner>(&local, REPO, &view, core.world());
            assert!(expected.len() > 100, "{}", expected.len());
            assert!(cut_of(core.dag()) == expected, "the core's cut differs");
            assert!(asked.len() > 100, "{}", asked.len());
            return;
        }
        // A want is never something held; prefetches may be (the network thread's
        // planner skips those, as here).
        for &(key, _) in &submit.wants {
            let held = answers.contains(key) || answers.is_leaf(key);
            assert!(!held, "frame {frame}: wants {key:?}, which it holds");
        }
        // A prefetch may name a want (routed to the owner whose package carries it): the
        // network thread's schedule keeps one request, as here.
        for &(key, _) in submit.wants.iter().chain(&submit.prefetch) {
            if answers.contains(key) || answers.is_leaf(key) || pending.contains(&key) {
                continue;
            }
            asked.insert(key);
            pending.push(key);
        }
    }
    panic!("the core did not converge in 400 frames");
}
