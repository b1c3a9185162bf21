//! `quincunx demo`: builds the bundled sample repositories (a planar SRTM crop and the
//! ETOPO20 planet) if they are missing, verifies them against their sources and shows a
//! few point queries. The README's main job.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};

use crate::build::{self, BuildArgs};
use crate::verify::{self, VerifyArgs};
use crate::{planet, query};

/// The bundled data folder of a source checkout.
pub fn bundled_data() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../data")
}

struct Sample {
    name: &'static str,
    source: &'static str,
    planet: bool,
    colour: bool,
    rms_m: Option<f64>,
    max_error_m: Option<f64>,
}

const SAMPLES: [Sample; 3] = [
    Sample {
        name: "korea",
        source: "korea_srtm3_1025.json",
        planet: false,
        colour: false,
        rms_m: Some(2.0),
        max_error_m: None,
    },
    Sample {
        name: "earth",
        source: "etopo20_global.json",
        planet: true,
        colour: false,
        rms_m: None,
        max_error_m: Some(2.0),
    },
    // The planet's colour (Blue Marble), 4 levels RMS per channel.
    Sample {
        name: "earth_colour",
        source: "bmng_global_1080x540.jpg",
        planet: true,
        colour: true,
        rms_m: Some(4.0),
        max_error_m: None,
    },
];

/// `quincunx demo` options.
#[derive(clap::Args, Debug, Clone)]
pub struct DemoArgs {
    /// Where the sample repositories go.
    #[arg(long, default_value = "quincunx-demo")]
    pub dir: PathBuf,
    /// Folder with the bundled data (default: the source checkout's `data/`).
    #[arg(long)]
    pub data: Option<PathBuf>,
    /// Address the server listens on.
    #[arg(long, default_value = "127.0.0.1:8080")]
    pub addr: std::net::SocketAddr,
    /// Request the example URLs over a real socket, check the answers, and stop instead
    /// of serving until Ctrl-C (used by CI).
    #[arg(long)]
    pub smoke: bool,
    /// Build and verify the sample repositories, then stop (no queries, no server).
    #[arg(long)]
    pub build_only: bool,
}

/// Runs `quincunx demo`.
pub fn run(args: &DemoArgs) -> Result<()> {
    let dir = args.dir.as_path();
    let data = args.data.clone().unwrap_or_else(bundled_data);
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    for s in &SAMPLES {
        let repo = dir.join(s.name);
        let source = data.join(s.source);
        if quincunx_store::Repository::open(&repo).is_ok() {
            outln!("{} exists", repo.display());
            continue;
        }
        outln!("building {} from {} ...", repo.display(), source.display());
        build::run(&BuildArgs {
            planet: s.planet,
            colour: s.colour,
            rms_m: s.rms_m,
            max_error_m: s.max_error_m,
            overwrite: true,
            bounds: build::Bounds::Measured,
            ..BuildArgs::new(source.clone(), repo.clone())
        })?;
        outln!("verifying {} against {} ...", s.name, s.source);
        verify::run(&VerifyArgs {
            repo: repo.clone(),
            source: Some(source),
            json: false,
            stream: false,
        })?;
    }
    if args.build_only {
        return Ok(());
    }
    let earth = dir.join("earth");
    outln!("heights on the bundled planet (lat lon [m]):");
    let places = [(27.988, 86.925), (11.35, 142.2), (90.0, 0.0), (-90.0, 0.0)];
    query::run(&earth, &places, false)?;
    outln!(
        "radius {} m",
        planet::body_radius_m("earth").unwrap_or_default()
    );
    serve(args)
}

/// Starts the server on the sample repositories and prints example requests.
fn serve(args: &DemoArgs) -> Result<()> {
    let repos: Vec<quincunx_server::RepoConfig> = SAMPLES
        .iter()
        .map(|s| quincunx_server::RepoConfig {
            name: s.name.to_string(),
            path: args.dir.join(s.name),
        })
        .collect();
    let mut config = quincunx_server::ServerConfig {
        addr: args.addr,
        repos,
        ..Default::default()
    };
    config.cache_bytes = 64 << 20;
    let examples = example_paths(&config)?;
    let runtime = tokio::runtime::Runtime::new().context("starting the runtime")?;
    runtime.block_on(async move {
        let server = quincunx_server::Server::bind(config)
            .await
            .with_context(|| {
                format!(
                    "starting the server (pass --addr to use another address than {})",
                    args.addr
                )
            })?;
        let addr = server.local_addr()?;
        outln!("\nserving the sample repositories on http://{addr}/");
        outln!("fly over them in a browser (WebGL2):");
        outln!("  http://{addr}/view?repo=korea&uv=0.5,0.5&height_m=3000&pitch_deg=-30");
        outln!(
            "  http://{addr}/view?repo=earth&colour=earth_colour&lat_lon=36,128&height_m=2000000&pitch_deg=-60"
        );
        outln!("example requests:");
        for (path, _) in &examples {
            outln!("  curl -sI http://{addr}{path}");
        }
        outln!(
            "  quincunx loadtest --url http://{addr} --repo korea --connections 64 --duration-s 10"
        );
        let smoke = args.smoke;
        let (done_tx, done_rx) = tokio::sync::oneshot::channel::<()>();
        let serving = tokio::spawn(server.run(async move {
            if smoke {
                let _ = done_rx.await;
            } else {
                quincunx_server::shutdown_signal().await;
            }
        }));
        let checked = async {
            if smoke {
                let examples = examples.clone();
                tokio::task::spawn_blocking(move || smoke_check(addr, &examples))
                    .await
                    .context("smoke check panicked")??;
            }
            tokio::task::spawn_blocking(move || demo_flight(addr))
                .await
                .context("the streaming client panicked")?
        }
        .await;
        if smoke {
            let _ = done_tx.send(());
        } else {
            if let Err(e) = &checked {
                outln!("streaming client failed: {e:#}");
            }
            outln!("press Ctrl-C to stop");
        }
        serving.await.context("server task failed")?;
        if smoke { checked } else { Ok(()) }
    })
}

/// Streaming client sessions against the demo server, through an emulated 4 Mbit/s,
/// 100 ms link: the first three views of the `jump` flight over the SRTM crop, then over
/// the planet with its colour; every frame's cut checked.
fn demo_flight(addr: std::net::SocketAddr) -> Result<()> {
    use quincunx_client::session::{AnySession, SessionConfig};
    for (repo, colour) in [("korea", None), ("earth", Some("earth_colour"))] {
        let (link, url) = crate::fly::start_link(&format!("http://{addr}"), (4_000.0, 100.0))?;
        match AnySession::open_with_colour(&url, repo, colour, SessionConfig::default())? {
            AnySession::Planar(s) => demo_jumps(s, repo, addr, &link)?,
            AnySession::Planet(s) => demo_jumps(s, repo, addr, &link)?,
        }
    }
    Ok(())
}

/// Three jumps of the built-in `jump` flight with `session`, reported.
fn demo_jumps<R: quincunx_client::flight::BuiltinFlights>(
    mut session: quincunx_client::session::Session<R>,
    repo: &str,
    addr: std::net::SocketAddr,
    link: &quincunx_client::fetch::link::LinkProxy,
) -> Result<()> {
    use quincunx_client::flight::{self, Flight, FlyOptions};
    let mut f = Flight::builtin_for("jump", &mut session, 1)?;
    f.legs.truncate(3);
    outln!(
        "\nstreaming client: {} low views of {repo} ({}{}) at 1920x1080, 1 px tolerance, \
         through an emulated 4 Mbit/s, 100 ms link",
        f.legs.len(),
        R::KIND,
        session
            .colour()
            .map_or(String::new(), |(c, _)| format!(", colour from {c}"))
    );
    let r = flight::fly(&mut session, &f, &FlyOptions::default(), |_| {})?;
    for j in &r.jumps {
        match j.time_to_full_quality_s {
            Some(t) => outln!("  view {}: full quality after {t:.2} s", j.leg),
            None => outln!("  view {}: not at full quality within its leg", j.leg),
        }
    }
    outln!(
        "  {} frames, {} cut halves (median), refinement {:.2} ms per frame (median), \
         {} blob bytes ({} on the link), {} cracks",
        r.frames,
        r.diamonds_per_frame_p50,
        r.refine_ms_p50,
        r.bytes_fetched,
        link.bytes_down(),
        r.cracks + r.coverage_errors
    );
    let colour = session
        .colour()
        .map_or(String::new(), |(c, _)| format!(" --color {c}"));
    outln!(
        "  quincunx fly --url http://{addr} --repo {repo}{colour} --path jump --link 4000,100 --json"
    );
    anyhow::ensure!(
        r.cracks == 0 && r.coverage_errors == 0 && r.jumps_unfinished == 0,
        "the streamed cut of {repo} was inconsistent or incomplete: {r:?}"
    );
    Ok(())
}

/// URL paths worth trying, with the status each must answer: the listing, metadata, the
/// root blobs, a leaf too deep to hold data (empty 200) and a non-centre (400).
fn example_paths(config: &quincunx_server::ServerConfig) -> Result<Vec<(String, u16)>> {
    use quincunx_codec::diamond::{PlanarDomain, SphereDomain};
    let mut paths = vec![("/repos".to_string(), 200), ("/healthz".to_string(), 200)];
    for rc in &config.repos {
        let repo = quincunx_store::Repository::open(&rc.path)?;
        let meta = repo.metadata();
        let base = format!("/repos/{}", rc.name);
        let v = &meta.content_hash[..16.min(meta.content_hash.len())];
        paths.push((format!("{base}/metadata.json"), 200));
        if meta.domain == quincunx_store::Domain::Sphere {
            let [x, y, z] = SphereDomain::new(meta.m)?.roots()[0].c;
            paths.push((format!("{base}/v/{v}/d/{x}/{y}/{z}"), 200));
        } else {
            let domain = PlanarDomain::new(meta.m)?;
            let root = domain.root();
            paths.push((format!("{base}/v/{v}/d/{}/{}", root.x, root.y), 200));
            paths.push((format!("{base}/v/{v}/d/0/0"), 400));
        }
    }
    Ok(paths)
}

/// Requests every example over a real socket and checks its status.
fn smoke_check(addr: std::net::SocketAddr, examples: &[(String, u16)]) -> Result<()> {
    use std::io::{Read, Write};
    for (path, want) in examples {
        let mut stream = std::net::TcpStream::connect(addr)?;
        stream.set_read_timeout(Some(std::time::Duration::from_secs(10)))?;
        write!(
            stream,
            "GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n"
        )?;
        let mut response = Vec::new();
        stream.read_to_end(&mut response)?;
        let head = String::from_utf8_lossy(&response[..response.len().min(64)]).into_owned();
        let status: u16 = head
            .split(' ')
            .nth(1)
            .and_then(|s| s.parse().ok())
            .with_context(|| format!("GET {path}: no status line in {head:?}"))?;
        anyhow::ensure!(
            status == *want,
            "GET {path}: status {status}, expected {want}"
        );
        outln!("  GET {path} -> {status} ({} bytes)", response.len());
    }
    outln!("smoke check passed");
    Ok(())
}
