//! `quincunx`: build, inspect, verify and export quincunx repositories.
//!
//! Exit codes: 0 success, 1 a failure (message on stderr), 2 bad command line (clap).

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};

#[cfg(feature = "render")]
use quincunx_repo_tools::trade;
use quincunx_repo_tools::{
    build, demo, export, fly, info, loadtest, outln, preview, query, shard, verify,
};
#[cfg(feature = "render")]
use quincunx_repo_tools::{render, view};

/// Streams compressed multiresolution terrain: repository tools.
#[derive(Parser, Debug)]
#[command(name = "quincunx", version, about)]
struct Cli {
    /// Log filter (tracing `EnvFilter` syntax), e.g. `info`, `quincunx=debug`.
    /// Default: `info` for `serve` and `demo`, `warn` otherwise.
    #[arg(long, global = true)]
    log: Option<String>,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Build the bundled sample repositories (planar SRTM crop, ETOPO20 planet) if they
    /// are missing, verify them and query a few places.
    Demo(demo::DemoArgs),
    /// Serve repositories over HTTP/1.1 (pipelined) and HTTP/2 (docs/http-api.md).
    Serve(quincunx_server::ServeArgs),
    /// Build a repository from a DEM (raw + JSON sidecar, GeoTIFF, 16-bit PNG, SRTM .hgt)
    /// or from RGB imagery (JPEG/PNG, `--colour`).
    Build(build::BuildArgs),
    /// Publish one repository from the parts of a sharded build (`build --shard K/N`):
    /// the same content hash as one `build` with the same options.
    Merge(shard::MergeArgs),
    /// Measure every diamond's error bound against the repository's full-resolution
    /// decode and write them into its blobs (the last step of every build; for
    /// repositories built before it). Colour repositories are left as they are.
    Bounds {
        /// Repository directory (replaced in place, atomically).
        repo: PathBuf,
        /// One JSON object instead of text.
        #[arg(long)]
        json: bool,
        /// Side of the tiles the pass measures one at a time, in samples: it holds one
        /// tile's decode and the lattices over it. The bounds do not depend on it.
        #[arg(long, default_value_t = quincunx_repo_tools::bounds::TILE_SAMPLES)]
        tile_samples: i64,
    },
    /// Print a repository's metadata, levels, blob counts and sizes.
    Info {
        /// Repository directory.
        repo: PathBuf,
        /// One JSON object instead of text.
        #[arg(long)]
        json: bool,
    },
    /// Fly a camera path with a headless streaming client against a server, in real
    /// time (optionally through an emulated link), and measure it.
    Fly(fly::FlyArgs),
    #[cfg(feature = "render")]
    /// The speed/accuracy trade: for each tolerance, fly the same path and render the
    /// same views; triangles, ms, bytes, time to full quality and the image error
    /// against a full-resolution reference (docs/trade.md).
    Trade(trade::TradeArgs),
    #[cfg(feature = "render")]
    /// Stream a served repository to full quality for one camera and write the frame as
    /// a PNG (rendered offscreen with wgpu; docs/rendering.md).
    Render(render::RenderArgs),
    /// `render`, `view` and `trade` in a build without the renderer: a clear error.
    #[cfg(not(feature = "render"))]
    #[command(name = "render", aliases = ["view", "trade"], hide = true)]
    WithoutRenderer {
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        rest: Vec<String>,
    },
    #[cfg(feature = "render")]
    /// A window over a served repository: orbit, pan, zoom and fly while it streams,
    /// with the live figures in the title (controls: `quincunx view --help`).
    View(view::ViewArgs),
    /// Check and decode every blob; with `--source`, reconstruct at full resolution and
    /// measure the error against the source.
    Verify(verify::VerifyArgs),
    /// Values of a planet repository at latitude/longitude points (bilinear on the
    /// decoded cube).
    Query {
        /// Repository directory.
        repo: PathBuf,
        /// `LAT,LON` in degrees (repeatable), e.g. `27.988,86.925`.
        #[arg(long = "at", required = true, value_parser = parse_lat_lon, allow_hyphen_values = true)]
        at: Vec<(f64, f64)>,
        /// One JSON array instead of text.
        #[arg(long)]
        json: bool,
    },
    /// A PNG picture of a repository's decoded data (elevation hillshaded and tinted, a
    /// planet as an equirectangular map, colour as is).
    Preview {
        /// Repository directory.
        repo: PathBuf,
        /// Output PNG.
        #[arg(short, long)]
        output: PathBuf,
        /// Picture width in pixels.
        #[arg(long, default_value_t = 1024)]
        width: usize,
    },
    /// Write one static file per blob (paths mirror the server's blob URLs) plus the
    /// metadata, for any static web server or object store.
    Export {
        /// Repository directory.
        repo: PathBuf,
        /// Output directory.
        dir: PathBuf,
        /// Repository name used in the paths (default: the repository directory's name).
        #[arg(long)]
        name: Option<String>,
    },
    /// Simulated view-dependent clients against a server (or a static export behind any
    /// web server): N persistent, optionally pipelined connections replaying flights.
    Loadtest(loadtest::LoadtestArgs),
}

fn parse_lat_lon(s: &str) -> Result<(f64, f64), String> {
    let (lat, lon) = s
        .split_once(',')
        .ok_or_else(|| format!("{s:?} is not LAT,LON"))?;
    let parse = |t: &str| t.trim().parse::<f64>().map_err(|e| format!("{t:?}: {e}"));
    let (lat, lon) = (parse(lat)?, parse(lon)?);
    query::check_point(lat, lon)?;
    Ok((lat, lon))
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let default_log = match cli.command {
        Command::Serve(_) | Command::Demo(_) => "info",
        _ => "warn",
    };
    let filter = tracing_subscriber::EnvFilter::try_new(cli.log.as_deref().unwrap_or(default_log))
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("warn"));
    tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .init();
    let result = match cli.command {
        Command::Build(args) => build::run(&args),
        Command::Merge(args) => shard::merge(&args),
        Command::Demo(args) => demo::run(&args),
        Command::Serve(args) => quincunx_server::run_cli(&args, |addr, scheme| {
            outln!("serving on {scheme}://{addr}/  (repositories: {scheme}://{addr}/repos)");
        })
        .map_err(anyhow::Error::from),
        Command::Bounds {
            repo,
            json,
            tile_samples,
        } => quincunx_repo_tools::bounds::run(&repo, json, tile_samples),
        Command::Info { repo, json } => info::run(&repo, json),
        Command::Verify(args) => verify::run(&args),
        Command::Export { repo, dir, name } => export::run(&repo, &dir, name.as_deref()),
        Command::Query { repo, at, json } => query::run(&repo, &at, json),
        Command::Loadtest(args) => loadtest::run(&args),
        Command::Fly(args) => fly::run(&args),
        #[cfg(feature = "render")]
        Command::Trade(args) => trade::run(&args),
        #[cfg(feature = "render")]
        Command::Render(args) => render::run(&args),
        #[cfg(feature = "render")]
        Command::View(args) => view::run(&args),
        #[cfg(not(feature = "render"))]
        Command::WithoutRenderer { .. } => Err(anyhow::anyhow!(
            "render, view and trade need quincunx built with its default features \
             (`render`, `charts`); this one was built with --no-default-features"
        )),
        Command::Preview {
            repo,
            output,
            width,
        } => preview::run(&repo, &output, width),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}
