//! `quincunx preview`: a PNG picture of a repository's decoded data: hillshaded,
//! hypsometrically tinted elevation (a planet as an equirectangular map), or colour as is.

use std::path::Path;

use anyhow::{Context, Result, bail};
use quincunx_store::Repository;

use crate::layout::Geometry;
use crate::{planet, verify};

/// Value of channel `c` at picture pixel `(x, y)`.
type Sampler<'a> = dyn Fn(usize, usize, usize) -> f64 + 'a;

/// Runs `quincunx preview`.
pub fn run(repo: &Path, out: &Path, width: usize) -> Result<()> {
    if !(16..=8192).contains(&width) {
        bail!("--width {width} must be between 16 and 8192 pixels");
    }
    let repo = Repository::open(repo).with_context(|| format!("opening {}", repo.display()))?;
    let meta = repo.metadata().clone();
    let decoded = verify::decode_repository(&repo)?;
    let channels: Vec<Vec<f64>> = (0..decoded.values.len())
        .map(|c| decoded.channel(c))
        .collect();
    // Sample every channel on the picture's grid.
    let (w, h, sample): (usize, usize, Box<Sampler>) = match &decoded.geom {
        Geometry::Sphere(g) => {
            let h = width / 2;
            let f = move |c: usize, x: usize, y: usize| {
                let lat = 90.0 - (y as f64 + 0.5) * 180.0 / h as f64;
                let lon = -180.0 + (x as f64 + 0.5) * 360.0 / width as f64;
                planet::query(g, &channels[c], lat, lon)
            };
            (width, h, Box::new(f))
        }
        Geometry::Planar(g) => {
            let (gw, gh) = (g.width(), g.height());
            let w = width.min(gw);
            let h = ((gh as f64 * w as f64 / gw as f64).round() as usize).max(1);
            let f = move |c: usize, x: usize, y: usize| {
                let col = ((x as f64 + 0.5) * gw as f64 / w as f64) as usize;
                let row = ((y as f64 + 0.5) * gh as f64 / h as f64) as usize;
                channels[c][row.min(gh - 1) * gw + col.min(gw - 1)]
            };
            (w, h, Box::new(f))
        }
    };
    let mut rgb = vec![0u8; w * h * 3];
    if meta.attribute.kind == quincunx_store::AttributeKind::Colour {
        for y in 0..h {
            for x in 0..w {
                let (r, g, b) = quincunx_codec::colour::ycocg_r_to_rgb(
                    sample(0, x, y).round() as i32,
                    sample(1, x, y).round() as i32,
                    sample(2, x, y).round() as i32,
                );
                let px = &mut rgb[(y * w + x) * 3..][..3];
                px.copy_from_slice(&[r, g, b].map(|v| v.clamp(0, 255) as u8));
            }
        }
    } else {
        let heights: Vec<f64> = (0..w * h).map(|k| sample(0, k % w, k / w)).collect();
        shade(&heights, w, h, &mut rgb);
    }
    write_png(out, w, h, &rgb)?;
    crate::outln!("wrote {} ({w} x {h})", out.display());
    Ok(())
}

/// Hypsometric tint (sea blues below 0, greens to browns to white above) times a
/// hillshade from the north-west.
fn shade(z: &[f64], w: usize, h: usize, rgb: &mut [u8]) {
    let (lo, hi) = z
        .iter()
        .filter(|v| v.is_finite())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| {
            (a.min(v), b.max(v))
        });
    let relief = (hi - lo).max(1.0);
    let at = |x: usize, y: usize| z[y.min(h - 1) * w + x.min(w - 1)];
    for y in 0..h {
        for x in 0..w {
            let v = at(x, y);
            let dx = at(x + 1, y) - at(x.saturating_sub(1), y);
            let dy = at(x, y + 1) - at(x, y.saturating_sub(1));
            // Exaggerate slopes relative to the picture's scale.
            let k = 40.0 * w.min(h) as f64 / relief / 4.0;
            let (nx, ny, nz) = (-dx * k, -dy * k, 1.0);
            let norm = (nx * nx + ny * ny + nz * nz).sqrt();
            let light = ((-nx - ny + nz) / (norm * 3f64.sqrt())).clamp(0.0, 1.0);
            let tint = tint(v, lo, hi);
            let s = 0.45 + 0.55 * light;
            let px = &mut rgb[(y * w + x) * 3..][..3];
            for c in 0..3 {
                px[c] = (tint[c] * s).clamp(0.0, 255.0) as u8;
            }
        }
    }
}

fn tint(v: f64, lo: f64, hi: f64) -> [f64; 3] {
    let lerp = |a: [f64; 3], b: [f64; 3], t: f64| {
        let t = t.clamp(0.0, 1.0);
        [0, 1, 2].map(|c| a[c] + (b[c] - a[c]) * t)
    };
    if !v.is_finite() {
        return [0.0; 3];
    }
    if v < 0.0 && lo < 0.0 {
        lerp([10.0, 30.0, 90.0], [90.0, 160.0, 220.0], 1.0 - v / lo)
    } else {
        let t = v / hi.max(1.0);
        if t < 0.4 {
            lerp([60.0, 140.0, 70.0], [200.0, 190.0, 110.0], t / 0.4)
        } else if t < 0.8 {
            lerp([200.0, 190.0, 110.0], [140.0, 100.0, 70.0], (t - 0.4) / 0.4)
        } else {
            lerp([140.0, 100.0, 70.0], [250.0, 250.0, 250.0], (t - 0.8) / 0.2)
        }
    }
}

fn write_png(path: &Path, w: usize, h: usize, rgb: &[u8]) -> Result<()> {
    let file =
        std::fs::File::create(path).with_context(|| format!("creating {}", path.display()))?;
    let mut enc = png::Encoder::new(std::io::BufWriter::new(file), w as u32, h as u32);
    enc.set_color(png::ColorType::Rgb);
    enc.set_depth(png::BitDepth::Eight);
    enc.set_compression(png::Compression::Best);
    let mut writer = enc
        .write_header()
        .with_context(|| format!("writing {}", path.display()))?;
    writer
        .write_image_data(rgb)
        .with_context(|| format!("writing {}", path.display()))?;
    Ok(())
}
