//! Embedding the client: stream a served repository into a frame loop and hand the cut to
//! a renderer.
//!
//! Start a server first, e.g. the README's main job (`quincunx demo`, which serves the
//! bundled SRTM crop as `korea` on port 8080), then:
//!
//! `cargo run --release -p quincunx-client --example session -- http://127.0.0.1:8080 korea`
//!
//! The camera circles over the raster for five seconds at 60 frames per second. Every
//! frame gets 4 ms for refinement and never waits for the network. Once a second it
//! prints what the frame loop and a renderer would see.

use std::collections::HashSet;
use std::time::{Duration, Instant};

use glam::DVec3;
use quincunx_client::dag::Half;
use quincunx_client::session::{Session, SessionConfig};
use quincunx_client::view::View;
use quincunx_codec::diamond::PlanarId;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let url = args
        .next()
        .unwrap_or_else(|| "http://127.0.0.1:8080".into());
    let repo = args.next().unwrap_or_else(|| "korea".into());
    let mut session = Session::open(&url, &repo, SessionConfig::default())?;
    // The root refined: the height bounds are conservative from here on.
    session.warm_up(Duration::from_secs(10))?;
    let bounds = session.bounds();
    let centre = (bounds.min + bounds.max) / 2.0;
    let radius = 0.3 * (bounds.max - bounds.min).truncate().length();
    println!(
        "{repo}: {} x {} samples, {:.0} m apart, heights {:.0}..{:.0} m",
        session.metadata().extent[0],
        session.metadata().extent[1],
        session.world().spacing_m,
        bounds.min.z,
        bounds.max.z
    );

    // What a renderer has uploaded: patches by (id, half, generation).
    let mut uploaded: HashSet<(PlanarId, Half, u64)> = HashSet::new();
    let start = Instant::now();
    let mut next_report = Duration::from_secs(1);
    while start.elapsed() < Duration::from_secs(5) {
        let frame_start = Instant::now();
        let t = start.elapsed().as_secs_f64();
        let angle = 0.2 * t;
        let eye = centre + DVec3::new(radius * angle.cos(), radius * angle.sin(), 0.0);
        let eye = DVec3::new(eye.x, eye.y, bounds.max.z + 500.0);
        let view = View {
            eye,
            target: DVec3::new(centre.x, centre.y, bounds.min.z),
            up: DVec3::Z,
            fov_y_rad: 60f64.to_radians(),
            viewport_px: [1920, 1080],
            tolerance_px: 1.0,
        };
        let frame = session.update(&view, start.elapsed(), Duration::from_millis(4))?;

        // The renderer's side: upload what changed, drop what left the cut.
        let snapshot = session.snapshot();
        let now: HashSet<_> = snapshot
            .patches
            .iter()
            .map(|p| (p.id, p.half, p.generation))
            .collect();
        let new = now.difference(&uploaded).count();
        uploaded = now;

        if start.elapsed() >= next_report {
            next_report += Duration::from_secs(1);
            let fetch = session.fetch_stats();
            println!(
                "t={t:4.1}s  cut {:5} patches ({new:4} new)  refined {:3}  waiting {:4}  \
                 full quality {:5}  fetched {:8} B  in flight {:3}",
                snapshot.patches.len(),
                frame.refine.refined,
                frame.refine.pending,
                frame.refine.full_quality,
                fetch.bytes_fetched,
                fetch.in_flight
            );
        }
        if let Some(rest) = Duration::from_micros(16_667).checked_sub(frame_start.elapsed()) {
            std::thread::sleep(rest);
        }
    }
    let check = session.dag().check_cut();
    println!(
        "final cut: {} halves, {} shared edge vertices, {} cracks",
        check.halves, check.shared_vertices, check.cracks
    );
    Ok(())
}
