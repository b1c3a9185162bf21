//! PNG line charts for measurement reports (`quincunx loadtest --plot`).
//!
//! Drawn with `plotters` on its bitmap backend and encoded with `png`; text uses DejaVu Sans
//! embedded in the binary (`assets/DejaVuSans.ttf`), so a chart looks the same on every
//! machine and nothing is looked up on the system at run time.
//!
//! Invariants: points that cannot be drawn (non-finite, or non-positive on a log axis) are
//! skipped, never drawn at a made-up place; a chart left with no point is an error naming
//! it, not an empty picture.

use std::io::BufWriter;
use std::ops::Range;
use std::path::Path;
use std::sync::OnceLock;

use anyhow::{Context, Result, anyhow, bail};
use plotters::coord::ranged1d::{Ranged, ValueFormatter};
use plotters::coord::types::RangedCoordf64;
use plotters::prelude::*;

/// One line of a chart: its legend name and its `(x, y)` points, drawn in the given order.
#[derive(Clone, Debug, PartialEq)]
pub struct Series {
    /// Name in the legend.
    pub name: String,
    /// Points, joined in this order.
    pub points: Vec<(f64, f64)>,
}

/// What to draw.
#[derive(Clone, Copy, Debug)]
pub struct Chart<'a> {
    /// Caption above the plot.
    pub title: &'a str,
    /// Horizontal axis description.
    pub x_label: &'a str,
    /// Vertical axis description.
    pub y_label: &'a str,
    /// Logarithmic horizontal axis.
    pub log_x: bool,
    /// Logarithmic vertical axis.
    pub log_y: bool,
    /// The lines, coloured in order from [`PALETTE`].
    pub series: &'a [Series],
}

/// Series colours in order (repeating): distinct from each other and from the black, grey
/// and white of axes, grid and text.
pub const PALETTE: [[u8; 3]; 8] = [
    [31, 119, 180],
    [255, 127, 14],
    [44, 160, 44],
    [214, 39, 40],
    [148, 103, 189],
    [140, 86, 75],
    [227, 119, 194],
    [23, 190, 207],
];

/// The colour of series `index`.
pub fn series_colour(index: usize) -> [u8; 3] {
    PALETTE[index % PALETTE.len()]
}

/// Smallest and largest side of a chart, pixels (smaller leaves no room for the plot).
pub const SIDE_PX: Range<u32> = 200..8193;

const FONT: &[u8] = include_bytes!("../assets/DejaVuSans.ttf");

/// Registers the embedded font as plotters' `sans-serif`, once.
fn register_font() -> Result<()> {
    static DONE: OnceLock<Result<(), String>> = OnceLock::new();
    DONE.get_or_init(|| {
        plotters::style::register_font("sans-serif", FontStyle::Normal, FONT)
            .map_err(|_| "the embedded DejaVu Sans font does not parse".to_string())
    })
    .clone()
    .map_err(|e| anyhow!(e))
}

/// Writes `chart` as an RGB PNG of `size` (width, height) pixels to `path`.
pub fn write_png(path: &Path, chart: &Chart, size: (u32, u32)) -> Result<()> {
    let (w, h) = size;
    if !SIDE_PX.contains(&w) || !SIDE_PX.contains(&h) {
        bail!(
            "chart {:?}: size {w}x{h} is out of range (each side {}..={} pixels)",
            chart.title,
            SIDE_PX.start,
            SIDE_PX.end - 1
        );
    }
    let series = plottable(chart);
    let all = || series.iter().flat_map(|s| s.iter());
    if all().next().is_none() {
        bail!(
            "chart {:?} has no point to plot (every point is non-finite{})",
            chart.title,
            if chart.log_x || chart.log_y {
                " or not positive on a log axis"
            } else {
                ""
            }
        );
    }
    register_font()?;
    let xs = span(all().map(|p| p.0), chart.log_x);
    let ys = span(all().map(|p| p.1), chart.log_y);
    let mut rgb = vec![0u8; w as usize * h as usize * 3];
    {
        let root = BitMapBackend::with_buffer(&mut rgb, size).into_drawing_area();
        let drawn = match (chart.log_x, chart.log_y) {
            (false, false) => draw(&root, chart, &series, linear(xs), linear(ys)),
            (true, false) => draw(&root, chart, &series, log(xs), linear(ys)),
            (false, true) => draw(&root, chart, &series, linear(xs), log(ys)),
            (true, true) => draw(&root, chart, &series, log(xs), log(ys)),
        };
        drawn.map_err(|e| anyhow!("drawing chart {:?}: {e}", chart.title))?;
        root.present()
            .map_err(|e| anyhow!("drawing chart {:?}: {e}", chart.title))?;
    }
    let file =
        std::fs::File::create(path).with_context(|| format!("creating {}", path.display()))?;
    let mut encoder = png::Encoder::new(BufWriter::new(file), w, h);
    encoder.set_color(png::ColorType::Rgb);
    encoder.set_depth(png::BitDepth::Eight);
    let mut writer = encoder
        .write_header()
        .with_context(|| format!("writing {}", path.display()))?;
    writer
        .write_image_data(&rgb)
        .with_context(|| format!("writing {}", path.display()))?;
    writer
        .finish()
        .with_context(|| format!("writing {}", path.display()))?;
    Ok(())
}

/// Each series' points that can be placed on the chart's axes.
fn plottable(chart: &Chart) -> Vec<Vec<(f64, f64)>> {
    let fits = |v: f64, log: bool| v.is_finite() && (!log || v > 0.0);
    chart
        .series
        .iter()
        .map(|s| {
            s.points
                .iter()
                .copied()
                .filter(|&(x, y)| fits(x, chart.log_x) && fits(y, chart.log_y))
                .collect()
        })
        .collect()
}

/// The axis range of `values` (not empty), padded so no point sits on the frame: by 5 % of
/// the span (of its logarithm on a log axis), or around a single value.
fn span(values: impl Iterator<Item = f64>, log: bool) -> Range<f64> {
    let (lo, hi) = values.fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
        (lo.min(v), hi.max(v))
    });
    if log {
        let (a, b) = (lo.log10(), hi.log10());
        let pad = if b > a { 0.05 * (b - a) } else { 0.3 };
        10f64.powf(a - pad)..10f64.powf(b + pad)
    } else {
        let pad = if hi > lo {
            0.05 * (hi - lo)
        } else {
            (0.1 * lo.abs()).max(1.0)
        };
        lo - pad..hi + pad
    }
}

fn linear(r: Range<f64>) -> RangedCoordf64 {
    r.into()
}

fn log(r: Range<f64>) -> LogCoord<f64> {
    r.log_scale().into()
}

/// Tick labels: short decimals, exponents for very large or small values.
fn tick(v: &f64) -> String {
    let a = v.abs();
    if a == 0.0 {
        return "0".into();
    }
    if !(1e-3..1e6).contains(&a) {
        return format!("{v:.1e}");
    }
    let s = format!("{v:.3}");
    s.trim_end_matches('0').trim_end_matches('.').to_string()
}

type Area<'a> = DrawingArea<BitMapBackend<'a>, plotters::coord::Shift>;
type DrawResult<'a> =
    Result<(), DrawingAreaErrorKind<<BitMapBackend<'a> as DrawingBackend>::ErrorType>>;

fn draw<'a, X, Y>(
    root: &Area<'a>,
    chart: &Chart,
    series: &[Vec<(f64, f64)>],
    x: X,
    y: Y,
) -> DrawResult<'a>
where
    X: Ranged<ValueType = f64> + ValueFormatter<f64>,
    Y: Ranged<ValueType = f64> + ValueFormatter<f64>,
{
    root.fill(&WHITE)?;
    let (_, h) = root.dim_in_pixel();
    let text = (h / 32).clamp(12, 32);
    let mut ctx = ChartBuilder::on(root)
        .caption(chart.title, ("sans-serif", text + 4))
        .margin(text)
        .x_label_area_size(text * 3)
        .y_label_area_size(text * 4)
        .build_cartesian_2d(x, y)?;
    ctx.configure_mesh()
        .x_desc(chart.x_label)
        .y_desc(chart.y_label)
        .label_style(("sans-serif", text))
        // plotters crowds light lines on log axes into grey bands: bold lines only.
        .light_line_style(TRANSPARENT)
        .x_label_formatter(&tick)
        .y_label_formatter(&tick)
        .draw()?;
    for (i, (s, points)) in chart.series.iter().zip(series).enumerate() {
        let [r, g, b] = series_colour(i);
        let colour = RGBColor(r, g, b);
        ctx.draw_series(LineSeries::new(
            points.iter().copied(),
            colour.stroke_width(2),
        ))?
        .label(s.name.as_str())
        .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], colour.stroke_width(3)));
        ctx.draw_series(points.iter().map(|&p| Circle::new(p, 4, colour.filled())))?;
    }
    // The legend goes to the corner of the plot that covers the fewest points.
    let pixels: Vec<(i32, i32)> = series
        .iter()
        .flatten()
        .map(|p| ctx.backend_coord(p))
        .collect();
    let (xs, ys) = ctx.plotting_area().get_pixel_range();
    let longest = chart.series.iter().map(|s| s.name.chars().count()).max();
    let w = (longest.unwrap_or(0) as i32 * text as i32 * 3 / 5 + 3 * text as i32)
        .min(xs.end - xs.start);
    let h = (chart.series.len() as i32 * text as i32 * 3 / 2 + text as i32).min(ys.end - ys.start);
    let corners = [
        (
            SeriesLabelPosition::UpperLeft,
            xs.start..xs.start + w,
            ys.start..ys.start + h,
        ),
        (
            SeriesLabelPosition::UpperRight,
            xs.end - w..xs.end,
            ys.start..ys.start + h,
        ),
        (
            SeriesLabelPosition::LowerLeft,
            xs.start..xs.start + w,
            ys.end - h..ys.end,
        ),
        (
            SeriesLabelPosition::LowerRight,
            xs.end - w..xs.end,
            ys.end - h..ys.end,
        ),
    ];
    let covered = |(_, cx, cy): &(SeriesLabelPosition, Range<i32>, Range<i32>)| {
        pixels
            .iter()
            .filter(|(px, py)| cx.contains(px) && cy.contains(py))
            .count()
    };
    let corner = corners
        .iter()
        .min_by_key(|c| covered(c))
        .map_or(SeriesLabelPosition::UpperLeft, |c| c.0.clone());
    ctx.configure_series_labels()
        .position(corner)
        .label_font(("sans-serif", text))
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .draw()?;
    Ok(())
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]

    use super::*;

    /// Decodes an RGB PNG: its size and pixels.
    fn decode(path: &Path) -> ((u32, u32), Vec<[u8; 3]>) {
        let decoder = png::Decoder::new(std::fs::File::open(path).unwrap());
        let mut reader = decoder.read_info().unwrap();
        let mut buf = vec![0; reader.output_buffer_size()];
        let info = reader.next_frame(&mut buf).unwrap();
        assert_eq!(info.color_type, png::ColorType::Rgb);
        let pixels = buf[..info.buffer_size()]
            .chunks_exact(3)
            .map(|c| [c[0], c[1], c[2]])
            .collect();
        ((info.width, info.height), pixels)
    }

    fn series(name: &str, points: &[(f64, f64)]) -> Series {
        Series {
            name: name.into(),
            points: points.to_vec(),
        }
    }

    #[test]
    fn a_chart_decodes_to_its_size_with_every_series_colour() {
        let dir = tempfile::tempdir().unwrap();
        let lines = [
            series("p50", &[(1.0, 0.5), (4.0, 0.7), (16.0, 1.2), (64.0, 3.0)]),
            series("p95", &[(1.0, 0.9), (4.0, 1.4), (16.0, 2.5), (64.0, 8.0)]),
            // Only its finite, positive point can be drawn on log axes.
            series(
                "sparse",
                &[(f64::NAN, 1.0), (0.0, 2.0), (8.0, 2.0), (2.0, -1.0)],
            ),
        ];
        for (log_x, log_y, size) in [
            (true, false, (640, 400)),
            (true, true, (800, 500)),
            (false, false, (300, 200)),
        ] {
            let path = dir.path().join(format!("c-{log_x}-{log_y}.png"));
            let chart = Chart {
                title: "time to full quality",
                x_label: "clients",
                y_label: "seconds",
                log_x,
                log_y,
                series: &lines,
            };
            write_png(&path, &chart, size).unwrap();
            let (got, pixels) = decode(&path);
            assert_eq!(got, size);
            for i in 0..lines.len() {
                let c = series_colour(i);
                let n = pixels.iter().filter(|p| **p == c).count();
                assert!(n > 20, "series {i}: {n} pixels of {c:?} ({log_x}, {log_y})");
            }
            // No colour of a series that is not there.
            let absent = series_colour(lines.len());
            assert!(!pixels.contains(&absent));
            // Mostly background.
            let white = pixels.iter().filter(|p| **p == [255, 255, 255]).count();
            assert!(white > pixels.len() / 2);
        }
    }

    #[test]
    fn a_chart_without_a_plottable_point_is_an_error_naming_it() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("empty.png");
        let nothing = [series("a", &[]), series("b", &[(f64::INFINITY, 1.0)])];
        let non_positive = [series("c", &[(1.0, 0.0), (2.0, -3.0)])];
        for (series, log_y) in [
            (&nothing[..], false),
            (&[][..], false),
            (&non_positive[..], true),
        ] {
            let chart = Chart {
                title: "requests per second",
                x_label: "clients",
                y_label: "requests/s",
                log_x: false,
                log_y,
                series,
            };
            let e = write_png(&path, &chart, (400, 300))
                .unwrap_err()
                .to_string();
            assert!(e.contains("\"requests per second\""), "{e}");
            assert!(e.contains("no point"), "{e}");
            assert!(!path.exists());
        }
        // The same points are fine on a linear axis.
        let chart = Chart {
            title: "t",
            x_label: "x",
            y_label: "y",
            log_x: false,
            log_y: false,
            series: &non_positive,
        };
        write_png(&path, &chart, (400, 300)).unwrap();
        assert_eq!(decode(&path).0, (400, 300));
    }

    #[test]
    fn sizes_out_of_range_and_unwritable_paths_are_errors() {
        let dir = tempfile::tempdir().unwrap();
        let one = [series("a", &[(1.0, 1.0)])];
        let chart = Chart {
            title: "t",
            x_label: "x",
            y_label: "y",
            log_x: false,
            log_y: false,
            series: &one,
        };
        for size in [(0, 300), (400, 10), (100_000, 300)] {
            let e = write_png(&dir.path().join("a.png"), &chart, size).unwrap_err();
            assert!(e.to_string().contains("size"), "{e}");
        }
        let missing = dir.path().join("no/such/dir/a.png");
        let e = write_png(&missing, &chart, (400, 300)).unwrap_err();
        assert!(format!("{e:#}").contains("no/such/dir"), "{e:#}");
    }

    #[test]
    fn spans_are_padded_around_the_data() {
        let r = span([1.0, 3.0].into_iter(), false);
        assert!(r.start < 1.0 && r.end > 3.0);
        let r = span([5.0].into_iter(), false);
        assert!(r.start < 5.0 && r.end > 5.0);
        let r = span([1.0, 256.0].into_iter(), true);
        assert!(r.start < 1.0 && r.start > 0.0 && r.end > 256.0);
        let r = span([7.0].into_iter(), true);
        assert!(r.start > 0.0 && r.start < 7.0 && r.end > 7.0);
        assert_eq!(tick(&0.0), "0");
        assert_eq!(tick(&2.5), "2.5");
        assert_eq!(tick(&256.0), "256");
    }
}
