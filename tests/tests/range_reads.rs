//! Repository files read straight from a static server with HTTP range requests, no
//! quincunx process serving them (`docs/hosting.md`):
//! - sessions (planar, and a planet with its colour) stream `repository.pack` files from
//!   nginx, crack-free at every frame, and every blob read that way is the stored one;
//!   `quincunx loadtest --mode fly` reads them too;
//! - a file replaced mid-session is an error (nginx's 412 on `If-Match`), never a mix of
//!   two builds;
//! - servers that break the range rules (ignore `Range`, 403, 404, 416, 500, truncated
//!   bodies, wrong `Content-Range`, wrong bytes) give clear errors or correct retries,
//!   never a wrong blob.
//!
//! Prints `SKIP range_reads...: ...` and passes when nginx is not installed (the fake
//! server's test always runs).
#![allow(clippy::unwrap_used, clippy::expect_used)]

use crate::common;

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::path::Path;
use std::sync::atomic::{AtomicU8, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use common::nginx::{Nginx, find_nginx, free_port};
use common::pack_reads::{
    assert_clean, assert_reads_stored, build, fetch_all, fly_checked, raw_fetcher, stored,
};
use common::put_file;
use quincunx_client::fetch::{FetchError, Fetched, Key, Remote};
use quincunx_repo_tools::build::BuildArgs;

/// nginx serving `www` as plain files on a free port, ready once `ready` answers.
fn static_nginx(binary: &Path, dir: &Path, www: &Path, ready: &str) -> Nginx {
    let addr = free_port();
    let snippet = format!(
        "access_log {}/access.log;\nserver {{ listen {addr}; root {}; }}",
        dir.display(),
        www.display()
    );
    Nginx::run(binary, dir, addr, &snippet, ready)
}

#[test]
fn sessions_stream_repository_files_from_nginx_crack_free_and_blobs_read_back_exactly() {
    let Some(nginx) = find_nginx("range_reads") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    let built = root.join("built");
    common::build_bundled_korea(&built.join("korea"));
    build(&built.join("earth"), "etopo20_global.json", |a| BuildArgs {
        planet: true,
        rms_m: Some(10.0),
        ..a
    });
    build(
        &built.join("earth_colour"),
        "bmng_global_1080x540.jpg",
        |a| BuildArgs {
            planet: true,
            colour: true,
            rms_m: Some(4.0),
            ..a
        },
    );
    // The files as a host would upload them: one folder of `.pack` files.
    let www = root.join("www");
    std::fs::create_dir_all(www.join("planets")).unwrap();
    for (name, to) in [
        ("korea", "korea.pack"),
        ("earth", "planets/earth.pack"),
        ("earth_colour", "planets/earth_colour.pack"),
    ] {
        std::fs::copy(built.join(name).join("repository.pack"), www.join(to)).unwrap();
    }
    let server = static_nginx(&nginx, &root.join("nginx"), &www, "/korea.pack");
    let url = format!("http://{}", server.addr);

    let planets = format!("{url}/planets");
    let open_bytes = |url: &str, name: &str| {
        let (remote, _) = Remote::open(url, name, Duration::from_secs(5)).unwrap();
        remote.pack.unwrap().open_bytes
    };
    let korea = fly_checked(&url, "korea.pack", None);
    assert_clean("korea", &korea);
    let planet = fly_checked(&planets, "earth.pack", Some("earth_colour.pack"));
    assert_clean("planet", &planet);
    for (name, r, opened) in [
        ("korea", &korea, open_bytes(&url, "korea.pack")),
        (
            "planet",
            &planet,
            open_bytes(&planets, "earth.pack") + open_bytes(&planets, "earth_colour.pack"),
        ),
    ] {
        // The bundled repositories are small: opening them (root directory and metadata)
        // is a good part of a flight's bytes. Past that, gaps and checksums stay within a
        // fifth of the blobs (the bar's figures: `benches/hosting`, full-size data).
        let needed = r.bytes_fetched - r.overhead_bytes;
        let ratio = r.bytes_fetched as f64 / needed as f64;
        assert!(r.overhead_bytes >= opened, "{name}: {r:?}");
        assert!(
            (r.overhead_bytes - opened) * 5 < needed,
            "{name}: {} bytes besides opening for {needed}",
            r.overhead_bytes - opened
        );
        println!(
            "range_reads: {name}: {} requests, {} bytes fetched, {} of them directories, \
             gaps and checksums ({ratio:.3}x the blobs), 0 cracks",
            r.requests, r.bytes_fetched, r.overhead_bytes
        );
    }

    // `quincunx loadtest --mode fly`: simulated clients read the file with ranges too.
    #[derive(clap::Parser)]
    struct Cli {
        #[command(flatten)]
        args: quincunx_repo_tools::loadtest::LoadtestArgs,
    }
    let log = root.join("nginx/access.log");
    let ranged = || {
        std::fs::read_to_string(&log)
            .unwrap()
            .lines()
            .filter(|l| l.contains("/korea.pack") && l.contains("\" 206 "))
            .count()
    };
    let before = ranged();
    let argv = [
        "loadtest",
        "--url",
        &url,
        "--repo",
        "korea.pack",
        "--mode",
        "fly",
        "--legs",
        "1",
        "--connections",
        "2",
        "--duration-s",
        "3",
        "--json",
        "--quiet",
    ];
    quincunx_repo_tools::loadtest::run(&<Cli as clap::Parser>::parse_from(argv).args).unwrap();
    assert!(ranged() > before, "loadtest read no ranges");

    // Every blob read with ranges is the stored one, and every other diamond a leaf.
    let want = stored(&built.join("korea"));
    let (remote, _) = Remote::open(&url, "korea.pack", Duration::from_secs(5)).unwrap();
    let pack = remote.pack.clone().unwrap();
    assert_eq!(pack.open_requests, 1, "korea opens in one read");
    assert_reads_stored(remote, &want);
    // The planet's colour metadata exceeds the first read: two round trips to open.
    let (remote, _) = Remote::open(&planets, "earth_colour.pack", Duration::from_secs(5)).unwrap();
    let pack = remote.pack.unwrap();
    assert_eq!(pack.open_requests, 2, "{}", pack.open_bytes);
    // Not a file there: a clear error.
    let err = Remote::open(&url, "nothing.pack", Duration::from_secs(5)).unwrap_err();
    assert!(err.to_string().contains("status 404"), "{err}");
    drop(server);
}

#[test]
fn a_file_replaced_mid_session_is_an_error_never_a_mix_of_two_builds() {
    let Some(nginx) = find_nginx("range_reads_replaced") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    let (old, new) = (root.join("old"), root.join("new"));
    common::build_bundled_korea(&old);
    build(&new, "korea_srtm3_1025.json", |a| BuildArgs {
        rms_m: Some(8.0),
        ..a
    });
    let www = root.join("www");
    put_file(&old, &www, "korea.pack");
    let server = static_nginx(&nginx, &root.join("nginx"), &www, "/korea.pack");
    let url = format!("http://{}", server.addr);
    let (remote, _) = Remote::open(&url, "korea.pack", Duration::from_secs(5)).unwrap();
    assert!(
        remote.pack.as_ref().unwrap().etag.is_some(),
        "nginx gives an ETag"
    );
    let fetcher = raw_fetcher(remote);
    let want = stored(&old);
    let keys: Vec<Key> = want.keys().copied().collect();
    let (first, rest) = keys.split_at(keys.len() / 4);
    let got = fetch_all(&fetcher, first, Duration::from_secs(30));
    assert!(got.values().all(|r| matches!(r, Fetched::Data(_))));
    // Published the way `quincunx build --overwrite` publishes: one rename.
    let staged = www.join("korea.pack.new");
    std::fs::copy(new.join("repository.pack"), &staged).unwrap();
    std::fs::rename(&staged, www.join("korea.pack")).unwrap();
    let got = fetch_all(&fetcher, rest, Duration::from_secs(30));
    let mut changed = 0;
    for (k, r) in &got {
        match r {
            Fetched::Data(v) => assert_eq!(&v[..], &want[k][..], "a blob of the new build"),
            Fetched::Failed(FetchError::Changed(msg)) => {
                assert!(msg.contains("changed since it was opened"), "{msg}");
                changed += 1;
            }
            // nginx closes a connection after a 412; requests pipelined behind it can
            // meet the reset on every attempt (2 here): an error, never a wrong blob.
            Fetched::Failed(FetchError::Connection(_)) => {}
            other => panic!("{k:?}: {other:?}"),
        }
    }
    assert!(changed > 0, "no request saw the new file");
    drop(server);
}

/// How the fake server misbehaves.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(u8)]
enum Fault {
    None,
    IgnoreRange,
    Forbidden,
    NotFound,
    Unsatisfiable,
    ServerError,
    Truncated,
    WrongRange,
    WrongBytes,
}

const FAULTS: [Fault; 9] = [
    Fault::None,
    Fault::IgnoreRange,
    Fault::Forbidden,
    Fault::NotFound,
    Fault::Unsatisfiable,
    Fault::ServerError,
    Fault::Truncated,
    Fault::WrongRange,
    Fault::WrongBytes,
];

/// A static file server over a real socket that answers ranges of `file` honestly or
/// with `fault`, keep-alive and pipelined.
struct FakeFiles {
    addr: SocketAddr,
    fault: Arc<AtomicU8>,
    requests: Arc<Mutex<u64>>,
}

impl FakeFiles {
    fn start(file: Vec<u8>) -> FakeFiles {
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let addr = listener.local_addr().unwrap();
        let fault = Arc::new(AtomicU8::new(Fault::None as u8));
        let requests = Arc::new(Mutex::new(0));
        let file = Arc::new(file);
        let (f, r) = (Arc::clone(&fault), Arc::clone(&requests));
        std::thread::spawn(move || {
            for stream in listener.incoming() {
                let Ok(stream) = stream else { continue };
                let (file, f, r) = (Arc::clone(&file), Arc::clone(&f), Arc::clone(&r));
                std::thread::spawn(move || serve(stream, &file, &f, &r));
            }
        });
        FakeFiles {
            addr,
            fault,
            requests,
        }
    }

    fn set(&self, fault: Fault) {
        self.fault.store(fault as u8, Ordering::SeqCst);
    }
}

fn serve(mut s: TcpStream, file: &[u8], fault: &AtomicU8, requests: &Mutex<u64>) {
    let mut buf = Vec::new();
    let mut chunk = [0u8; 8192];
    loop {
        let Some(end) = buf.windows(4).position(|w| w == b"\r\n\r\n") else {
            match s.read(&mut chunk) {
                Ok(0) | Err(_) => return,
                Ok(n) => buf.extend_from_slice(&chunk[..n]),
            }
            continue;
        };
        let head = String::from_utf8_lossy(&buf[..end]).into_owned();
        buf.drain(..end + 4);
        *requests.lock().unwrap() += 1;
        let range = head.lines().find_map(|l| {
            let v = l.strip_prefix("Range: bytes=")?;
            let (a, b) = v.split_once('-')?;
            Some((a.parse::<usize>().ok()?, b.parse::<usize>().ok()?))
        });
        let n = file.len();
        let fault = FAULTS[usize::from(fault.load(Ordering::SeqCst))];
        let answer = match (fault, range) {
            (Fault::Forbidden, _) => status(403),
            (Fault::NotFound, _) => status(404),
            (Fault::ServerError, _) => status(500),
            (Fault::Unsatisfiable, _) => format!(
                "HTTP/1.1 416 Range Not Satisfiable\r\nContent-Range: bytes */{n}\r\n\
                 Content-Length: 0\r\n\r\n"
            )
            .into_bytes(),
            (Fault::IgnoreRange, _) | (_, None) => {
                let mut a = format!("HTTP/1.1 200 OK\r\nContent-Length: {n}\r\n\r\n").into_bytes();
                a.extend_from_slice(file);
                a
            }
            (_, Some((a, b))) => {
                let b = b.min(n - 1);
                let mut body = file[a..=b].to_vec();
                let (mut first, mut last) = (a, b);
                match fault {
                    Fault::WrongRange if a > 0 => (first, last) = (a - 1, b - 1),
                    Fault::WrongRange => (first, last) = (a + 1, b + 1),
                    // A blob's first byte, or the root directory's at open.
                    Fault::WrongBytes => body[if a == 0 { 200 } else { 0 }] ^= 0x20,
                    _ => {}
                }
                let len = body.len();
                if fault == Fault::Truncated {
                    body.truncate(len / 2);
                }
                let mut out = format!(
                    "HTTP/1.1 206 Partial Content\r\nETag: \"v1\"\r\n\
                     Content-Range: bytes {first}-{last}/{n}\r\nContent-Length: {len}\r\n\r\n"
                )
                .into_bytes();
                out.extend_from_slice(&body);
                out
            }
        };
        if s.write_all(&answer).is_err() || fault == Fault::Truncated {
            return;
        }
    }
}

fn status(code: u16) -> Vec<u8> {
    format!("HTTP/1.1 {code} X\r\nContent-Length: 0\r\n\r\n").into_bytes()
}

#[test]
fn servers_that_break_the_range_rules_give_clear_errors_never_wrong_blobs() {
    let dir = tempfile::tempdir().unwrap();
    let repo = dir.path().join("korea");
    common::build_bundled_korea(&repo);
    let want = stored(&repo);
    let file = std::fs::read(repo.join("repository.pack")).unwrap();
    let server = FakeFiles::start(file);
    let url = format!("http://{}", server.addr);
    let open = || Remote::open(&url, "korea.pack", Duration::from_secs(5));

    // Opening: each fault is a clear error.
    for (fault, words) in [
        (Fault::IgnoreRange, "ignored the Range header"),
        (Fault::Forbidden, "status 403"),
        (Fault::NotFound, "status 404"),
        (Fault::Unsatisfiable, "status 416"),
        (Fault::ServerError, "status 500"),
        (Fault::WrongRange, "Content-Range"),
        (Fault::Truncated, "closed"),
    ] {
        server.set(fault);
        let err = open().unwrap_err().to_string();
        assert!(err.contains(words), "{fault:?}: {err}");
    }
    // A damaged header or root directory fails its checksum.
    server.set(Fault::WrongBytes);
    let err = open().unwrap_err().to_string();
    assert!(err.contains("checksum"), "{err}");

    // Mid-session: every fault fails the keys it hits, never hands on other bytes.
    let keys: Vec<Key> = want.keys().copied().collect();
    // Every fault but `None` (the first).
    for (i, fault) in FAULTS.into_iter().skip(1).enumerate() {
        server.set(Fault::None);
        let (remote, _) = open().unwrap();
        let fetcher = raw_fetcher(remote);
        server.set(fault);
        // A different slice of keys each time (nothing cached).
        let slice: Vec<Key> = keys.iter().skip(i).step_by(7).copied().collect();
        let got = fetch_all(&fetcher, &slice, Duration::from_secs(30));
        assert_eq!(got.len(), slice.len(), "{fault:?}: every key answered");
        let mut failed = Vec::new();
        for (k, r) in &got {
            match r {
                // A coalesced request's other blobs are right: handed on, exactly.
                Fetched::Data(v) => assert_eq!(&v[..], &want[k][..], "{fault:?}: {k:?}"),
                Fetched::Leaf => panic!("{fault:?}: {k:?} called a leaf"),
                Fetched::Failed(e) => failed.push(e.to_string()),
            }
        }
        assert!(!failed.is_empty(), "{fault:?}: no key failed");
        let words = match fault {
            Fault::IgnoreRange => "ignored the Range header",
            Fault::Forbidden => "403",
            Fault::NotFound => "404",
            Fault::Unsatisfiable => "changed since it was opened",
            Fault::ServerError => "500",
            Fault::Truncated => "connection",
            Fault::WrongRange => "asked for bytes",
            _ => "checksum mismatch",
        };
        assert!(
            failed.iter().all(|m| m.contains(words)),
            "{fault:?}: {failed:?}"
        );
        // And back to honest: the same keys read back exactly.
        server.set(Fault::None);
        let fetcher = raw_fetcher(open().unwrap().0);
        let got = fetch_all(&fetcher, &slice, Duration::from_secs(30));
        for (k, r) in &got {
            let Fetched::Data(v) = r else {
                panic!("{k:?}: {r:?}")
            };
            assert_eq!(&v[..], &want[k][..]);
        }
    }
    assert!(*server.requests.lock().unwrap() > 0);
}
