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
    rms_m: Option<f64>,
    max_error_m: Option<f64>,
}

const SAMPLES: [Sample; 2] = [
    Sample {
        name: "korea",
        source: "korea_srtm3_1025.json",
        planet: false,
        rms_m: Some(2.0),
        max_error_m: None,
    },
    Sample {
        name: "earth",
        source: "etopo20_global.json",
        planet: true,
        rms_m: None,
        max_error_m: Some(2.0),
    },
];

/// Runs `quincunx demo`.
pub fn run(dir: &Path, data: Option<&Path>) -> Result<()> {
    let data = data.map_or_else(bundled_data, Path::to_path_buf);
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    for s in &SAMPLES {
        let repo = dir.join(s.name);
        let source = data.join(s.source);
        if quincunx_store::Repository::open(&repo).is_err() {
            outln!("building {} from {} ...", repo.display(), source.display());
            build::run(&BuildArgs {
                input: source.clone(),
                output: repo.clone(),
                colour: false,
                planet: s.planet,
                radius_m: None,
                body: "earth".into(),
                face_side: None,
                sparse: false,
                diamond_size: None,
                lossless: false,
                rms_m: s.rms_m,
                max_error_m: s.max_error_m,
                threads: None,
                memory_budget_mb: None,
                overwrite: true,
                json: false,
                stall_after_blobs: None,
            })?;
        } else {
            outln!("{} exists", repo.display());
        }
        outln!("verifying {} against {} ...", s.name, s.source);
        verify::run(&VerifyArgs {
            repo: repo.clone(),
            source: Some(source),
            json: false,
        })?;
    }
    let earth = dir.join("earth");
    outln!("heights on the bundled planet (lat lon [m]):");
    let places = [(27.988, 86.925), (11.35, 142.2), (90.0, 0.0), (-90.0, 0.0)];
    query::run(&earth, &places, false)?;
    outln!(
        "radius {} m; try: quincunx info {}  |  quincunx export {} <dir>",
        planet::body_radius_m("earth").unwrap_or_default(),
        earth.display(),
        earth.display()
    );
    Ok(())
}
