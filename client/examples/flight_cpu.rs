//! Refinement CPU per frame in a steady low flight over a real DEM, without a network
//! (details decoded on demand from an in-memory encoding, as the network thread would
//! hand them over). Prints one JSON object.
//!
//! `cargo run --release -p quincunx-client --example flight_cpu -- [grid.json] [--tolerance-px 1] [--frames 300]`
//! (default grid: the bundled `data/korea_srtm3_1025.json`; a raw int16 grid with sidecar).

use std::collections::HashMap;
use std::sync::Arc;
use std::time::{Duration, Instant};

use glam::DVec3;
use quincunx_client::dag::Dag;
use quincunx_client::refine::{Availability, DetailSource, Refinement, SystemClock};
use quincunx_client::view::{PlanarWorld, View};
use quincunx_codec::diamond::PlanarId;
use quincunx_codec::encode::{EncodeOptions, FromEncoded, Grid, RateMode, encode};
use quincunx_codec::incremental::{Details, PlanarRefiner};

struct Decoded {
    blobs: HashMap<Vec<u8>, Vec<u8>>,
    refiner: Arc<PlanarRefiner>,
    cache: HashMap<PlanarId, Option<Arc<Details>>>,
    decode_time: Duration,
}

impl DetailSource for Decoded {
    fn details(&mut self, id: PlanarId, _priority: f64) -> Availability {
        if let Some(d) = self.cache.get(&id) {
            return Availability::Ready(d.clone());
        }
        // Decoding belongs to the network thread: it is timed apart from refinement.
        let start = Instant::now();
        let d = self.refiner.info(id).and_then(|info| {
            let blob = self.blobs.get(&info.key)?;
            self.refiner.decode(id, blob).ok().map(Arc::new)
        });
        self.decode_time += start.elapsed();
        self.cache.insert(id, d.clone());
        Availability::Ready(d)
    }
}

fn percentile(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return 0.0;
    }
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let flag = |name: &str| {
        args.iter()
            .position(|a| a == name)
            .and_then(|i| args.get(i + 1))
            .and_then(|v| v.parse::<f64>().ok())
    };
    let tolerance_px = flag("--tolerance-px").unwrap_or(1.0);
    let frames = flag("--frames").unwrap_or(300.0) as usize;
    let sidecar = args
        .iter()
        .find(|a| a.ends_with(".json"))
        .cloned()
        .unwrap_or_else(|| {
            concat!(env!("CARGO_MANIFEST_DIR"), "/../data/korea_srtm3_1025.json").into()
        });
    let meta: serde_like::Sidecar = serde_like::read(&sidecar)?;
    let raw = std::fs::read(std::path::Path::new(&sidecar).with_extension("i16"))?;
    let values_m = raw
        .chunks_exact(2)
        .map(|b| match i16::from_le_bytes([b[0], b[1]]) {
            -32768 => f64::NAN,
            v => f64::from(v),
        })
        .collect();
    let grid = Grid {
        width: meta.width,
        height: meta.height,
        values_m,
        quantum_m: Some(1.0),
    };
    let enc = Arc::new(encode(
        &grid,
        EncodeOptions {
            n: 32,
            mode: RateMode::RmsM(2.0),
            sparse: false,
            rdo: Default::default(),
        },
    )?);
    let refiner = Arc::new(PlanarRefiner::from_encoded(&enc)?);
    let mut dag = Dag::new(refiner.clone());
    let mut source = Decoded {
        blobs: enc.blobs_by_key()?,
        refiner,
        cache: HashMap::new(),
        decode_time: Duration::ZERO,
    };
    let world = PlanarWorld {
        spacing_m: 90.0,
        value_scale_m: enc.value_scale_m,
        value_offset_m: enc.value_offset_m,
    };
    let extent = [meta.width as f64 * 90.0, meta.height as f64 * 90.0];
    let mut refinement = Refinement::default();
    let clock = SystemClock(Instant::now());
    let mut times = Vec::new();
    let mut halves = Vec::new();
    let mut refined_total = 0;
    // A steady flight: 600 m above sea level, 40 m per frame (144 km/h at 60 fps).
    for k in 0..frames {
        let t = k as f64 * 40.0;
        let eye = DVec3::new(
            0.15 * extent[0] + t * 0.8,
            0.2 * extent[1] + t * 0.6,
            1_500.0,
        );
        let view = View {
            eye,
            target: eye + DVec3::new(800.0, 600.0, -300.0),
            up: DVec3::Z,
            fov_y_rad: 60f64.to_radians(),
            viewport_px: [1920, 1080],
            tolerance_px,
        };
        let before = source.decode_time;
        let start = Instant::now();
        let stats = refinement.update(
            &mut dag,
            &view,
            world,
            &mut source,
            &clock,
            Duration::from_secs(1),
        )?;
        let ms = (start.elapsed() - (source.decode_time - before)).as_secs_f64() * 1e3;
        // The first frames build the cut from the root: steady flight starts after them.
        if k >= 10 {
            times.push(ms);
            halves.push(stats.cut_halves as f64);
        }
        refined_total += stats.refined;
    }
    let check = dag.check_cut();
    times.sort_by(f64::total_cmp);
    halves.sort_by(f64::total_cmp);
    println!(
        "{{\"grid\":\"{sidecar}\",\"tolerance_px\":{tolerance_px},\"frames\":{frames},\"refine_ms_p50\":{:.4},\"refine_ms_p99\":{:.4},\"refine_ms_max\":{:.4},\"cut_halves_p50\":{},\"refined_total\":{refined_total},\"decode_s_total\":{:.3},\"dag_nodes\":{},\"dag_mb\":{:.2},\"cracks\":{},\"coverage_ok\":{}}}",
        percentile(&times, 0.5),
        percentile(&times, 0.99),
        times.last().copied().unwrap_or(0.0),
        percentile(&halves, 0.5),
        source.decode_time.as_secs_f64(),
        dag.len(),
        dag.memory_bytes() as f64 / 1e6,
        check.cracks,
        check.uncovered == 0 && check.overlaps == 0,
    );
    Ok(())
}

/// The two sidecar fields this example needs, without a JSON dependency.
mod serde_like {
    pub struct Sidecar {
        pub width: usize,
        pub height: usize,
    }

    pub fn read(path: &str) -> Result<Sidecar, Box<dyn std::error::Error>> {
        let text = std::fs::read_to_string(path)?;
        let field = |name: &str| -> Result<usize, Box<dyn std::error::Error>> {
            let at = text
                .find(&format!("\"{name}\""))
                .ok_or_else(|| format!("{path}: no {name}"))?;
            let rest = &text[at + name.len() + 2..];
            let digits: String = rest
                .chars()
                .skip_while(|c| !c.is_ascii_digit())
                .take_while(char::is_ascii_digit)
                .collect();
            Ok(digits.parse()?)
        };
        Ok(Sidecar {
            width: field("width")?,
            height: field("height")?,
        })
    }
}
