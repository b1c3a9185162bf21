//! Reading repository files with range requests (`tests/range_reads.rs`, `tests/s3.rs`):
//! building from the bundled data, crack-checked flights, and every blob read back.

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};

use bytes::Bytes;
use quincunx_client::fetch::tls::ConnectOptions;
use quincunx_client::fetch::{FetchConfig, FetchStats, Fetched, Fetcher, Key, Remote, Transport};
use quincunx_client::flight::{self, FlightReport};
use quincunx_client::session::AnySession;
use quincunx_repo_tools::args::{RefineArgs, ServerArgs};
use quincunx_repo_tools::build::{self, BuildArgs};
use quincunx_repo_tools::fly::{self, FlyArgs};
use quincunx_store::Repository;
use quincunx_store::answer::IdSpace;

use super::workspace_root;

/// Builds the bundled `data/{input}` into `out` with `args`.
pub fn build(out: &Path, input: &str, args: impl FnOnce(BuildArgs) -> BuildArgs) {
    build::run(&args(BuildArgs {
        overwrite: true,
        ..BuildArgs::new(workspace_root().join("data").join(input), out)
    }))
    .unwrap();
}

/// Flies the built-in jump path with every frame checked for cracks.
pub fn fly_checked(url: &str, repo: &str, colour: Option<&str>) -> FlightReport {
    fly_checked_with(url, repo, colour, ConnectOptions::default())
}

/// [`fly_checked`] with `connect` settings (a bucket's credentials and endpoint).
pub fn fly_checked_with(
    url: &str,
    repo: &str,
    colour: Option<&str>,
    connect: ConnectOptions,
) -> FlightReport {
    let args = FlyArgs {
        server: ServerArgs {
            colour: colour.map(Into::into),
            ..ServerArgs::new(url, repo)
        },
        refine: RefineArgs {
            tolerance_px: 2.0,
            ..RefineArgs::default()
        },
        ..FlyArgs::new(url, repo, "jump")
    };
    let mut config = fly::session_config(&args);
    config.connect = connect;
    let session = AnySession::open_with_colour(url, repo, colour, config).unwrap();
    let opts = fly::fly_options(&args);
    match session {
        AnySession::Planar(mut s) => {
            let f = fly::load_flight(&args.path, &mut s, args.seed).unwrap();
            flight::fly(&mut s, &f, &opts, |_| {}).unwrap()
        }
        AnySession::Planet(mut s) => {
            let f = fly::load_flight(&args.path, &mut s, args.seed).unwrap();
            flight::fly(&mut s, &f, &opts, |_| {}).unwrap()
        }
    }
}

pub fn assert_clean(name: &str, r: &FlightReport) {
    assert_eq!((r.cracks, r.coverage_errors), (0, 0), "{name}: {r:?}");
    assert_eq!((r.fetch_errors, r.failures), (0, 0), "{name}: {r:?}");
    assert_eq!(r.jumps_unfinished, 0, "{name}: {r:?}");
    assert!(r.frames_checked > 0, "{name}");
}

/// Every stored blob of `repo`, by centre.
pub fn stored(repo: &Path) -> BTreeMap<Key, Bytes> {
    let repo = Repository::open(repo).unwrap();
    let space = IdSpace::of(repo.metadata()).unwrap();
    repo.blobs()
        .map(|kv| {
            let (k, v) = kv.unwrap();
            let c = match &space {
                IdSpace::Planar(d) => {
                    let id = d.id_from_key(&k).unwrap();
                    [id.x, id.y, 0]
                }
                IdSpace::Sphere(d) => d.id_from_key(&k).unwrap().c,
            };
            (c, v)
        })
        .collect()
}

/// A fetcher of raw blobs (no decoding) from `remote`, with short timeouts and few
/// attempts.
pub fn raw_fetcher(remote: Remote) -> Fetcher<Vec<u8>> {
    raw_fetcher_over(remote, Transport::Pipelined)
}

/// [`raw_fetcher`] over `transport`.
pub fn raw_fetcher_over(remote: Remote, transport: Transport) -> Fetcher<Vec<u8>> {
    let config = FetchConfig {
        transport,
        request_timeout: Duration::from_secs(2),
        max_attempts: 2,
        retry_backoff: Duration::from_millis(10),
        max_backoff: Duration::from_millis(50),
        ..FetchConfig::new(remote)
    };
    Fetcher::spawn(config, Arc::new(|_key, bytes: Bytes| Ok(bytes.to_vec()))).unwrap()
}

/// Submits `keys` until each has an answer (or `limit` passes): the data, leaves and
/// failures.
pub fn fetch_all(
    fetcher: &Fetcher<Vec<u8>>,
    keys: &[Key],
    limit: Duration,
) -> BTreeMap<Key, Fetched<Vec<u8>>> {
    let mut out = BTreeMap::new();
    let started = Instant::now();
    while out.len() < keys.len() && started.elapsed() < limit {
        let wants: Vec<(Key, f32)> = keys
            .iter()
            .filter(|k| !out.contains_key(*k))
            .map(|&k| (k, 1.0))
            .collect();
        fetcher.submit(wants);
        std::thread::sleep(Duration::from_millis(5));
        for (k, r) in fetcher.poll() {
            out.entry(k).or_insert(r);
        }
    }
    out
}

/// Reads every blob of `want` through `remote` and checks each against the stored one;
/// neighbours are coalesced, so there are fewer requests than blobs (how many join depends
/// on what the bandwidth window releases at once, which is timing; the reader's unit tests
/// pin the rule). Returns the fetcher's figures.
pub fn assert_reads_stored(remote: Remote, want: &BTreeMap<Key, Bytes>) -> FetchStats {
    assert_reads_stored_over(remote, Transport::Pipelined, want)
}

/// [`assert_reads_stored`] over `transport`.
pub fn assert_reads_stored_over(
    remote: Remote,
    transport: Transport,
    want: &BTreeMap<Key, Bytes>,
) -> FetchStats {
    let fetcher = raw_fetcher_over(remote, transport);
    let keys: Vec<Key> = want.keys().copied().collect();
    let got = fetch_all(&fetcher, &keys, Duration::from_secs(60));
    assert_eq!(got.len(), keys.len());
    for (k, r) in &got {
        match r {
            Fetched::Data(v) => assert_eq!(&v[..], &want[k][..], "{k:?}"),
            other => panic!("{k:?}: {other:?}"),
        }
    }
    let stats = fetcher.stats();
    assert!(
        stats.requests < keys.len() as u64,
        "{} requests for {} blobs: coalesced",
        stats.requests,
        keys.len()
    );
    stats
}
