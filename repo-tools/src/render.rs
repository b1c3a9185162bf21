//! `quincunx render`: streams a served repository to full quality for one camera and
//! writes the frame as a PNG, rendered offscreen by `quincunx-render`.

use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use clap::Args;
use quincunx_client::refine::RefineConfig;
use quincunx_client::session::{AnySession, Session, SessionConfig};
use quincunx_render::domain::RenderDomain;
use quincunx_render::offscreen::Gpu;
use quincunx_render::scene::{Picture, PictureOptions, Place, Shot, Streamed, picture};
use quincunx_render::{Modes, RendererConfig};

/// `quincunx render` options.
#[derive(Args, Debug, Clone)]
pub struct RenderArgs {
    /// Where to stream from.
    #[command(flatten)]
    pub server: crate::args::ServerArgs,
    /// Where the camera is and where it looks.
    #[command(flatten)]
    pub camera: crate::args::CameraArgs,
    /// Metres above the streamed terrain under the camera.
    #[arg(long)]
    pub height_m: f64,
    /// Image size `WxH`.
    #[arg(long, default_value = "1920x1080", value_parser = crate::fly::parse_viewport)]
    pub size: [u32; 2],
    /// What the tolerance bounds.
    #[command(flatten)]
    pub refine: crate::args::RefineArgs,
    /// Background `R,G,B` (0-255).
    #[arg(long, default_value = "135,170,210", value_parser = parse_rgb)]
    pub background: [u8; 3],
    /// Seconds to stream before rendering whatever has arrived.
    #[arg(long, default_value_t = 30.0)]
    pub wait_s: f64,
    /// GPU memory budget for patches, MB.
    #[arg(long, default_value_t = 128.0)]
    pub gpu_budget_mb: f64,
    /// Grid lines over the shading.
    #[arg(long)]
    pub wireframe: bool,
    /// Colour each level.
    #[arg(long)]
    pub colour_by_level: bool,
    /// Output PNG.
    #[arg(short, long)]
    pub output: PathBuf,
    /// Print one JSON object with the figures.
    #[arg(long)]
    pub json: bool,
}

fn parse_rgb(s: &str) -> Result<[u8; 3], String> {
    let parts: Vec<&str> = s.split(',').collect();
    if parts.len() != 3 {
        return Err(format!("{s:?} is not R,G,B"));
    }
    let mut out = [0u8; 3];
    for (o, t) in out.iter_mut().zip(parts) {
        *o = t
            .trim()
            .parse::<u8>()
            .map_err(|_| format!("{t:?} is not a channel value 0..=255"))?;
    }
    Ok(out)
}

/// Runs `quincunx render`.
pub fn run(args: &RenderArgs) -> Result<()> {
    args.refine.check().map_err(anyhow::Error::msg)?;
    let place = match (args.camera.lat_lon, args.camera.uv) {
        (Some((lat, lon)), None) => Place::LatLon(lat, lon),
        (None, Some((u, v))) => Place::Uv(u, v),
        _ => bail!("give the camera's place: --lat-lon LAT,LON (planets) or --uv U,V (planar)"),
    };
    if !(args.wait_s.is_finite() && args.wait_s > 0.0 && args.wait_s <= 86_400.0) {
        bail!("--wait-s {} must be above 0 and at most 86400", args.wait_s);
    }
    if !(args.gpu_budget_mb.is_finite()
        && args.gpu_budget_mb > 0.0
        && args.gpu_budget_mb <= 65_536.0)
    {
        bail!(
            "--gpu-budget-mb {} must be above 0 and at most 65536",
            args.gpu_budget_mb
        );
    }
    let shot = Shot {
        place,
        height_m: args.height_m,
        heading_deg: args.camera.heading_deg,
        pitch_deg: args.camera.pitch_deg,
        fov_deg: args.camera.fov_deg,
        size: args.size,
        tolerance_px: args.refine.tolerance_px,
    };
    shot.validate()?;
    let session = AnySession::open_with_colour(
        &args.server.url,
        &args.server.repo,
        args.server.colour.as_deref(),
        SessionConfig {
            connect: crate::fly::link_options(args.server.ca_cert.as_ref(), None),
            refine: RefineConfig {
                metric: args.refine.metric,
                ..RefineConfig::default()
            },
            ..SessionConfig::default()
        },
    )
    .with_context(|| format!("opening {} at {}", args.server.repo, args.server.url))?;
    // After the session: a repository the client refuses is named before a GPU is needed.
    let gpu = Gpu::headless().context("starting the renderer")?;
    let options = PictureOptions {
        renderer: RendererConfig {
            gpu_budget_bytes: (args.gpu_budget_mb * 1_048_576.0) as u64,
            ..RendererConfig::default()
        },
        background: args.background,
        modes: Modes {
            wireframe: args.wireframe,
            colour_by_level: args.colour_by_level,
            no_colour: false,
        },
        ..PictureOptions::default()
    };
    let wait = Duration::from_secs_f64(args.wait_s);
    let (pic, streamed, cracks) = match session {
        AnySession::Planar(s) => shoot(&gpu, s, &shot, wait, &options)?,
        AnySession::Planet(s) => shoot(&gpu, s, &shot, wait, &options)?,
    };
    pic.image
        .write_png(&args.output)
        .with_context(|| format!("writing {}", args.output.display()))?;
    let failure = if cracks > 0 {
        Some(format!("the cut had {cracks} cracks"))
    } else if !streamed.full_quality && !streamed.budget_limited {
        Some(format!(
            "not at full quality after --wait-s {} s ({} frames): the picture is coarser \
             than --tolerance-px {}",
            args.wait_s, streamed.frames, args.refine.tolerance_px
        ))
    } else {
        None
    };
    if args.json {
        let v = serde_json::json!({
            "failure": failure,
            "width": pic.image.width,
            "height": pic.image.height,
            "triangles": pic.stats.triangles,
            "patches": pic.stats.patches,
            "draw_calls": pic.stats.draw_calls,
            "full_quality": streamed.full_quality,
            "budget_limited": streamed.budget_limited,
            "time_to_full_quality_s": streamed.full_quality.then_some(streamed.seconds),
            "frames": streamed.frames,
            "cut_cracks": cracks,
            "upload_bytes": pic.upload_bytes,
            "cpu_frame_ms": pic.stats.cpu_ms,
            "gpu_frame_ms": pic.timing.gpu_ms,
            "gpu_bytes_used": pic.stats.gpu_bytes_used,
            "gpu_budget_bytes": pic.stats.gpu_bytes_allocated,
            "ground_m": streamed.ground_m,
            "adapter": gpu.describe(),
            "output": args.output.display().to_string(),
        });
        println!("{v}");
    } else {
        outln!(
            "{}: {}x{}, {} patches, {} triangles, {} draw call(s), {} ({:.2} s), adapter {}",
            args.output.display(),
            pic.image.width,
            pic.image.height,
            pic.stats.patches,
            pic.stats.triangles,
            pic.stats.draw_calls,
            if streamed.full_quality {
                "full quality"
            } else if streamed.budget_limited {
                "the finest cut --gpu-budget-mb holds (coarser than the tolerance)"
            } else {
                "NOT at full quality (--wait-s ran out)"
            },
            streamed.seconds,
            gpu.describe()
        );
    }
    match failure {
        Some(why) => bail!("{why} ({} was written)", args.output.display()),
        None => Ok(()),
    }
}

fn shoot<R: RenderDomain>(
    gpu: &Gpu,
    mut session: Session<R>,
    shot: &Shot,
    wait: Duration,
    options: &PictureOptions,
) -> Result<(Picture, Streamed, usize)> {
    let start = Instant::now();
    let (pic, streamed, _view) = picture(gpu, &mut session, shot, wait, options)?;
    let check = session.dag().check_cut();
    tracing::debug!(elapsed = ?start.elapsed(), "rendered");
    Ok((pic, streamed, check.cracks + check.colour_cracks))
}
