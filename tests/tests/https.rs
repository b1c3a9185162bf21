//! HTTPS end to end: a CA and certificates made here (rcgen), a real server terminating TLS
//! on loopback, and the client's transports, `fly`, `render` and `loadtest` over it. HTTP/2
//! is negotiated by ALPN; a wrong host name, an unknown CA and an expired certificate each
//! fail with an error naming the cause, never a fallback to plain HTTP. A repository file
//! on nginx over TLS (HTTP/2 and HTTP/1.1 offered by ALPN) is read by ranges with every
//! transport, the HTTP/2 one multiplexing them over HTTP/2.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use crate::common;

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use clap::Parser;
use common::nginx::{Nginx, find_nginx, free_port};
use common::pack_reads::{assert_clean, assert_reads_stored_over, fly_checked_with, stored};
use quincunx_client::fetch::http1::{self, Endpoint};
use quincunx_client::fetch::tls::ConnectOptions;
use quincunx_client::fetch::{Remote, Transport};
use quincunx_client::session::{Session, SessionConfig};
use quincunx_codec::incremental::PlanarRefiner;
use quincunx_repo_tools::args::ServerArgs;
use quincunx_repo_tools::fly::{CaCert, FlyArgs};
use quincunx_server::{RepoConfig, Server, ServerConfig, TlsConfig};
use rcgen::{
    BasicConstraints, CertificateParams, DnType, IsCa, KeyPair, KeyUsagePurpose, date_time_ymd,
};

const REPO: &str = "korea";

/// A CA and a certificate it signed, as PEM files in a directory.
struct Pki {
    ca_pem: String,
    cert: PathBuf,
    key: PathBuf,
}

/// A CA, and a certificate for `localhost` signed by it (valid now, or long expired).
fn pki(dir: &Path, tag: &str, expired: bool) -> Pki {
    let ca_key = KeyPair::generate().unwrap();
    let mut ca = CertificateParams::new(Vec::<String>::new()).unwrap();
    ca.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
    ca.distinguished_name
        .push(DnType::CommonName, format!("quincunx test CA {tag}"));
    ca.key_usages = vec![KeyUsagePurpose::KeyCertSign, KeyUsagePurpose::CrlSign];
    let ca_cert = ca.self_signed(&ca_key).unwrap();
    let key = KeyPair::generate().unwrap();
    let mut leaf = CertificateParams::new(vec!["localhost".to_string()]).unwrap();
    leaf.distinguished_name
        .push(DnType::CommonName, "localhost");
    if expired {
        leaf.not_before = date_time_ymd(2001, 1, 1);
        leaf.not_after = date_time_ymd(2002, 1, 1);
    }
    let cert = leaf.signed_by(&key, &ca_cert, &ca_key).unwrap();
    let (cert_path, key_path) = (
        dir.join(format!("{tag}.pem")),
        dir.join(format!("{tag}.key")),
    );
    std::fs::write(&cert_path, cert.pem()).unwrap();
    std::fs::write(&key_path, key.serialize_pem()).unwrap();
    Pki {
        ca_pem: ca_cert.pem(),
        cert: cert_path,
        key: key_path,
    }
}

/// A TLS server of `repo` on its own runtime.
struct Served {
    addr: SocketAddr,
    runtime: Option<tokio::runtime::Runtime>,
}

impl Served {
    fn start(repo: &Path, pki: &Pki, max_connections_per_ip: Option<usize>) -> Served {
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .enable_all()
            .build()
            .unwrap();
        let mut config = ServerConfig {
            addr: "127.0.0.1:0".parse().unwrap(),
            repos: vec![RepoConfig {
                name: REPO.into(),
                path: repo.to_path_buf(),
            }],
            workers: 1,
            tls: Some(TlsConfig {
                cert: pki.cert.clone(),
                key: pki.key.clone(),
            }),
            ..Default::default()
        };
        if let Some(n) = max_connections_per_ip {
            config.limits.max_connections_per_ip = n;
        }
        let server = runtime.block_on(Server::bind(config)).unwrap();
        assert_eq!(server.scheme(), "https");
        let addr = server.local_addr().unwrap();
        runtime.spawn(server.run(std::future::pending()));
        Served {
            addr,
            runtime: Some(runtime),
        }
    }

    /// `https://localhost:port`: the name the certificate carries.
    fn url(&self) -> String {
        format!("https://localhost:{}", self.addr.port())
    }
}

impl Drop for Served {
    fn drop(&mut self) {
        if let Some(rt) = self.runtime.take() {
            rt.shutdown_timeout(Duration::from_secs(5));
        }
    }
}

fn build_korea(dir: &Path) -> PathBuf {
    let out = dir.join("korea");
    common::build_bundled_korea(&out);
    out
}

fn connect(ca: &Pki) -> ConnectOptions {
    ConnectOptions {
        ca_cert_pem: Some(ca.ca_pem.clone().into_bytes()),
        ..ConnectOptions::default()
    }
}

/// GET over https with the test CA: status and body.
fn get(url: &str, ca: &Pki, path: &str) -> (u16, Vec<u8>) {
    let endpoint = Endpoint::from_url_with(url, &connect(ca)).unwrap();
    http1::get_blocking(&endpoint, path, Duration::from_secs(10)).unwrap()
}

fn metric(url: &str, ca: &Pki, name: &str) -> u64 {
    let (_, body) = get(url, ca, "/metrics");
    common::metric(&String::from_utf8(body).unwrap(), name)
}

#[test]
fn every_transport_streams_real_blobs_over_https() {
    let dir = tempfile::tempdir().unwrap();
    let repo = build_korea(dir.path());
    let ca = pki(dir.path(), "good", false);
    let server = Served::start(&repo, &ca, None);
    for transport in Transport::ALL {
        let config = SessionConfig {
            transport,
            connect: connect(&ca),
            ..SessionConfig::default()
        };
        let mut session = Session::<PlanarRefiner>::open(&server.url(), REPO, config).unwrap();
        assert!(
            session.warm_up(Duration::from_secs(20)).unwrap(),
            "{transport:?}"
        );
        let stats = session.fetch_stats();
        assert!(
            stats.responses > 0 && stats.bytes_fetched > 0,
            "{transport:?}: {stats:?}"
        );
        assert_eq!(stats.errors.total(), 0, "{transport:?}: {stats:?}");
    }
    // The HTTP/2 transport got HTTP/2 by ALPN (the others offer only HTTP/1.1).
    assert!(metric(&server.url(), &ca, "quincunx_connections_h2_total") >= 1);
}

#[test]
fn http2_is_negotiated_by_alpn_and_http1_where_only_it_is_offered() {
    let dir = tempfile::tempdir().unwrap();
    let repo = build_korea(dir.path());
    let ca = pki(dir.path(), "good", false);
    let server = Served::start(&repo, &ca, None);
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    for (offer, want) in [
        (vec![b"h2".to_vec(), b"http/1.1".to_vec()], b"h2".to_vec()),
        (vec![b"http/1.1".to_vec()], b"http/1.1".to_vec()),
    ] {
        let got = rt.block_on(async {
            let mut roots = tokio_rustls::rustls::RootCertStore::empty();
            for cert in rustls_pem(&ca.ca_pem) {
                roots.add(cert).unwrap();
            }
            let mut config = tokio_rustls::rustls::ClientConfig::builder_with_provider(Arc::new(
                rustls_graviola::default_provider(),
            ))
            .with_safe_default_protocol_versions()
            .unwrap()
            .with_root_certificates(roots)
            .with_no_client_auth();
            config.alpn_protocols = offer.clone();
            let tcp = tokio::net::TcpStream::connect(server.addr).await.unwrap();
            let name = tokio_rustls::rustls::pki_types::ServerName::try_from("localhost").unwrap();
            let tls = tokio_rustls::TlsConnector::from(Arc::new(config))
                .connect(name, tcp)
                .await
                .unwrap();
            tls.get_ref().1.alpn_protocol().map(<[u8]>::to_vec)
        });
        assert_eq!(got, Some(want), "offered {offer:?}");
    }
}

fn rustls_pem(pem: &str) -> Vec<tokio_rustls::rustls::pki_types::CertificateDer<'static>> {
    use tokio_rustls::rustls::pki_types::pem::PemObject;
    tokio_rustls::rustls::pki_types::CertificateDer::pem_slice_iter(pem.as_bytes())
        .collect::<Result<_, _>>()
        .unwrap()
}

fn open_error(url: &str, options: ConnectOptions, transport: Transport) -> String {
    let config = SessionConfig {
        transport,
        connect: options,
        timeout: Duration::from_secs(10),
        ..SessionConfig::default()
    };
    match Session::<PlanarRefiner>::open(url, REPO, config) {
        Ok(_) => panic!("{url}: opened"),
        Err(e) => e.to_string(),
    }
}

#[test]
fn certificate_failures_name_their_cause() {
    let dir = tempfile::tempdir().unwrap();
    let repo = build_korea(dir.path());
    let good = pki(dir.path(), "good", false);
    let other = pki(dir.path(), "other", false);
    let expired = pki(dir.path(), "expired", true);
    let server = Served::start(&repo, &good, None);
    let stale = Served::start(&repo, &expired, None);

    // No CA given: the system's roots do not know the test CA.
    let e = open_error(
        &server.url(),
        ConnectOptions::default(),
        Transport::Pipelined,
    );
    assert!(e.contains("unknown issuer"), "{e}");
    assert!(e.contains("--ca-cert"), "{e}");
    // Another CA than the one that signed the certificate.
    let e = open_error(&server.url(), connect(&other), Transport::Pipelined);
    assert!(e.contains("unknown issuer"), "{e}");
    // The certificate names localhost, the URL an address.
    let by_ip = format!("https://127.0.0.1:{}", server.addr.port());
    let e = open_error(&by_ip, connect(&good), Transport::Pipelined);
    assert!(e.contains("not valid for the host name 127.0.0.1"), "{e}");
    // Expired in 2002.
    let e = open_error(&stale.url(), connect(&expired), Transport::Pipelined);
    assert!(e.contains("has expired"), "{e}");
    // Plain HTTP to a TLS port is an error, and https to a plain port is never downgraded.
    let plain = common::stream::Served::one("127.0.0.1:0".parse().unwrap(), REPO, &repo);
    let e = open_error(
        &format!("https://localhost:{}", plain.addr.port()),
        connect(&good),
        Transport::Pipelined,
    );
    assert!(e.contains("TLS"), "{e}");
    plain.kill();

    // The blob transports name the cause too (the metadata fetched with a good CA, then a
    // transport told to trust another).
    let (remote, _) = quincunx_client::fetch::Remote::open_with(
        &server.url(),
        REPO,
        Duration::from_secs(10),
        &connect(&good),
    )
    .unwrap();
    let wrong = quincunx_client::fetch::Remote::open_with(
        &by_ip,
        REPO,
        Duration::from_secs(10),
        &connect(&good),
    );
    assert!(wrong.is_err());
    for transport in Transport::ALL {
        let mut config = quincunx_client::fetch::FetchConfig::new(remote.clone());
        config.transport = transport;
        config.remote.endpoint = Endpoint::from_url_with(&server.url(), &connect(&other)).unwrap();
        config.max_attempts = 1;
        let fetcher = quincunx_client::fetch::Fetcher::spawn(
            config,
            Arc::new(|_key, bytes: bytes::Bytes| Ok(bytes.to_vec())),
        )
        .unwrap();
        fetcher.submit(vec![([0, 0, 0], 1.0)]);
        let got = wait_failure(&fetcher);
        assert!(got.contains("unknown issuer"), "{transport:?}: {got}");
    }
}

fn wait_failure(fetcher: &quincunx_client::fetch::Fetcher<Vec<u8>>) -> String {
    let deadline = std::time::Instant::now() + Duration::from_secs(20);
    while std::time::Instant::now() < deadline {
        for (_, fetched) in fetcher.poll() {
            if let quincunx_client::fetch::Fetched::Failed(e) = fetched {
                return e.to_string();
            }
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    panic!("no failure reported");
}

#[test]
fn fly_render_and_loadtest_run_over_https() {
    let dir = tempfile::tempdir().unwrap();
    let repo = build_korea(dir.path());
    let ca = pki(dir.path(), "good", false);
    let ca_path = dir.path().join("ca.pem");
    std::fs::write(&ca_path, &ca.ca_pem).unwrap();
    let ca_cert = quincunx_repo_tools::fly::parse_ca_cert(ca_path.to_str().unwrap()).unwrap();
    let server = Served::start(&repo, &ca, None);
    let url = server.url();
    let requests_before = metric(
        &url,
        &ca,
        "quincunx_http_requests_total{route=\"blob\",status=\"200\"}",
    );

    // fly, also through an emulated link (the proxy carries the TLS bytes).
    for link in [None, Some((20_000.0, 20.0))] {
        let args = FlyArgs {
            server: ServerArgs {
                ca_cert: Some(ca_cert.clone()),
                ..ServerArgs::new(url.clone(), REPO)
            },
            json: true,
            link,
            ..FlyArgs::new(url.clone(), REPO, "jump")
        };
        quincunx_repo_tools::fly::run(&args).unwrap();
    }
    // Without the CA the same flight fails, naming why.
    let e = quincunx_repo_tools::fly::run(&FlyArgs::new(url.clone(), REPO, "jump")).unwrap_err();
    assert!(format!("{e:#}").contains("unknown issuer"), "{e:#}");

    // loadtest: replayed streams, then real sessions.
    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        args: quincunx_repo_tools::loadtest::LoadtestArgs,
    }
    let ca_arg = ca_path.to_str().unwrap();
    for extra in [
        &["--requests", "2000"][..],
        &["--mode", "fly", "--legs", "1"][..],
    ] {
        let mut argv = vec![
            "loadtest",
            "--url",
            &url,
            "--repo",
            REPO,
            "--ca-cert",
            ca_arg,
            "--connections",
            "4",
            "--duration-s",
            "5",
            "--json",
            "--quiet",
        ];
        argv.extend_from_slice(extra);
        quincunx_repo_tools::loadtest::run(&Cli::parse_from(argv).args).unwrap();
    }
    let requests = metric(
        &url,
        &ca,
        "quincunx_http_requests_total{route=\"blob\",status=\"200\"}",
    ) - requests_before;
    assert!(requests > 2000, "{requests} blob requests");

    // render: streams over https, then draws (needs a GPU adapter).
    if quincunx_render::offscreen::gpu_for_test("fly_render_and_loadtest_run_over_https")
        .unwrap()
        .is_some()
    {
        #[derive(Parser)]
        struct RenderCli {
            #[command(flatten)]
            args: quincunx_repo_tools::render::RenderArgs,
        }
        let out = dir.path().join("k.png");
        let argv = [
            "render",
            "--url",
            &url,
            "--repo",
            REPO,
            "--ca-cert",
            ca_arg,
            "--uv",
            "0.5,0.5",
            "--height-m",
            "5000",
            "--size",
            "160x90",
            "-o",
            out.to_str().unwrap(),
        ];
        quincunx_repo_tools::render::run(&RenderCli::parse_from(argv).args).unwrap();
        assert!(std::fs::metadata(&out).unwrap().len() > 0);
    }
}

#[test]
fn the_per_address_cap_answers_429_over_tls_naming_the_flag() {
    let dir = tempfile::tempdir().unwrap();
    let repo = build_korea(dir.path());
    let ca = pki(dir.path(), "good", false);
    let server = Served::start(&repo, &ca, Some(1));
    let endpoint = Endpoint::from_url_with(&server.url(), &connect(&ca)).unwrap();
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    rt.block_on(async {
        let limits = http1::Limits::default();
        let mut first = http1::Connection::open(&endpoint, limits).await.unwrap();
        let mut req = Vec::new();
        http1::write_get(&mut req, &endpoint.host, b"/repos");
        first.send(&req).await.unwrap();
        assert_eq!(first.read_response().await.unwrap().status, 200);
        // The second connection from the same address is over the cap of 1.
        let mut second = http1::Connection::open(&endpoint, limits).await.unwrap();
        let _ = second.send(&req).await;
        let r = second.read_response().await.unwrap();
        assert_eq!(r.status, 429);
        let body = String::from_utf8_lossy(r.body);
        assert!(body.contains("--max-connections-per-ip"), "{body}");
        assert!(body.contains("allows 1 per address"), "{body}");
    });
}

#[test]
fn unreadable_and_mismatched_certificate_files_are_clear_errors() {
    let dir = tempfile::tempdir().unwrap();
    let repo = build_korea(dir.path());
    let a = pki(dir.path(), "a", false);
    let b = pki(dir.path(), "b", false);
    let bind = |cert: &Path, key: &Path| {
        let config = ServerConfig {
            addr: "127.0.0.1:0".parse().unwrap(),
            repos: vec![RepoConfig {
                name: REPO.into(),
                path: repo.clone(),
            }],
            tls: Some(TlsConfig {
                cert: cert.to_path_buf(),
                key: key.to_path_buf(),
            }),
            ..Default::default()
        };
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .unwrap();
        match rt.block_on(Server::bind(config)) {
            Ok(_) => panic!("bound"),
            Err(e) => e.to_string(),
        }
    };
    let missing = dir.path().join("missing.pem");
    let e = bind(&missing, &a.key);
    assert!(
        e.contains("reading the certificate") && e.contains("missing.pem"),
        "{e}"
    );
    let e = bind(&a.cert, &b.key);
    assert!(e.contains("does not match"), "{e}");
    let e = bind(&a.key, &a.key);
    assert!(e.contains("no PEM certificate"), "{e}");
}

#[allow(dead_code)]
fn _ca_cert_is_public(c: CaCert) -> PathBuf {
    c.path
}

/// nginx serving `www` over TLS with `pki`'s certificate, offering HTTP/2 and HTTP/1.1 by
/// ALPN and logging each request's protocol and range; it answers `/ready` on a second,
/// plain listener. Returns nginx and the TLS address.
fn tls_nginx(binary: &Path, dir: &Path, www: &Path, pki: &Pki) -> (Nginx, SocketAddr) {
    let (plain, tls) = (free_port(), free_port());
    let d = dir.display();
    let snippet = format!(
        "log_format proto '$server_protocol $status \"$http_range\"';\n\
         access_log {d}/access.log proto;\n\
         server {{ listen {plain}; location = /ready {{ return 200; }} }}\n\
         server {{ listen {tls} ssl http2; ssl_certificate {}; ssl_certificate_key {}; root {}; }}",
        pki.cert.display(),
        pki.key.display(),
        www.display()
    );
    (Nginx::run(binary, dir, plain, &snippet, "/ready"), tls)
}

#[test]
fn a_repository_file_on_an_https_host_reads_by_ranges_with_http2_where_offered() {
    let Some(binary) = find_nginx("https_ranges") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let repo = build_korea(dir.path());
    let www = dir.path().join("www");
    common::put_file(&repo, &www, "korea.pack");
    let ca = pki(dir.path(), "good", false);
    let (server, tls) = tls_nginx(&binary, &dir.path().join("nginx"), &www, &ca);
    let url = format!("https://localhost:{}", tls.port());
    let ranges_logged = || -> Vec<String> {
        let mut lines = server.access_log();
        lines.retain(|l| l.contains("bytes="));
        lines
    };

    // The defaults (pipelined HTTP/1.1), every frame checked for cracks.
    let flight = fly_checked_with(&url, "korea.pack", None, connect(&ca));
    assert_clean("https ranges", &flight);

    // Every transport reads every blob back exactly; the HTTP/2 one gets HTTP/2, which
    // nginx offers by ALPN, and multiplexes its ranges on it.
    let want = stored(&repo);
    for transport in Transport::ALL {
        let (remote, _) =
            Remote::open_with(&url, "korea.pack", Duration::from_secs(10), &connect(&ca)).unwrap();
        // nginx logs a request just after it has sent the answer: let the opening's line
        // (always HTTP/1.1) and the last transport's land before counting.
        std::thread::sleep(Duration::from_millis(300));
        let before = ranges_logged().len();
        let stats = assert_reads_stored_over(remote, transport, &want);
        std::thread::sleep(Duration::from_millis(300));
        assert_eq!(stats.errors.total(), 0, "{transport:?}: {stats:?}");
        let lines = ranges_logged();
        let protocol = if transport == Transport::H2 {
            "HTTP/2.0 206 "
        } else {
            "HTTP/1.1 206 "
        };
        assert!(
            lines.len() > before,
            "{transport:?}: no range request logged"
        );
        for line in &lines[before..] {
            assert!(line.starts_with(protocol), "{transport:?}: {line}");
        }
        println!(
            "https ranges, {}: {} requests for {} blobs",
            transport.name(),
            lines.len() - before,
            want.len()
        );
    }
    drop(server);
}
