//! Tile mosaics: `quincunx build <dir | list file | pattern>` over a set of georeferenced
//! height tiles, each with its own extent and resolution.
//!
//! - **Which tiles.** Every height file of a directory (`.hgt`, `.tif`/`.tiff`, `.png`, and
//!   raw grids by their `.json` sidecar), the files of a list (`.txt` or `.list`: one path
//!   per line, relative to the list; blank lines and lines starting with `#` are skipped),
//!   or the files matching a pattern whose file name holds `*` or `?` (matched within its
//!   directory). Directory and pattern tiles are in file-name order, list tiles as listed.
//! - **Overlaps.** Where tiles overlap, the finer tile (the smaller sample cell,
//!   `dx * dy`) wins; between tiles of the same spacing, the first in order wins. A tile's
//!   nodata never wins: the next tile's value shows through it.
//! - **Holes.** Points no tile covers are nodata, and a mosaic builds a sparse repository:
//!   large uncovered areas are holes, not coded at all.
//! - **Coverage of a tile.** Its extent: up to the outer samples for node registration, up
//!   to the outer cell edges for cell registration (values there are the outer samples').
//! - **Reading.** First every tile's header (size and georeference: `.hgt` names, sidecars,
//!   GeoTIFF tags), which orders the tiles and sizes the output; then one tile at a time, in
//!   order of priority, resampled (bilinear) where nothing finer has written, and dropped
//!   before the next is read.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use quincunx_codec::encode::{CubeGrid, Grid, round};
use quincunx_codec::sphere_raster::{SphereFrame, SphereGeometry};
use quincunx_codec::stream::{CubeSource, IoError};
use rayon::prelude::*;

use crate::build::BUILD_BYTES_PER_SAMPLE;
use crate::input::{self, Georef, Registration};
use crate::planet::{self, CubeAngles};

/// Whether `input` names a mosaic (a directory, a list file or a pattern) rather than one
/// file.
pub fn is_mosaic(input: &Path) -> bool {
    input.is_dir() || is_list(input) || is_pattern(input)
}

fn is_list(input: &Path) -> bool {
    matches!(extension(input).as_deref(), Some("txt" | "list"))
}

fn is_pattern(input: &Path) -> bool {
    input
        .file_name()
        .and_then(|n| n.to_str())
        .is_some_and(|n| n.contains(['*', '?']))
}

fn extension(path: &Path) -> Option<String> {
    path.extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase)
}

/// Whether a directory entry is a height tile: a raw grid counts once, by its sidecar.
fn is_tile(path: &Path) -> bool {
    match extension(path).as_deref() {
        Some("hgt" | "tif" | "tiff" | "png") => true,
        Some("json") => ["i16", "f32"]
            .iter()
            .any(|ext| path.with_extension(ext).is_file()),
        _ => false,
    }
}

/// Matches a file name against a pattern of `*` (any run) and `?` (any one character).
fn matches(pattern: &[char], name: &[char]) -> bool {
    match pattern.split_first() {
        None => name.is_empty(),
        Some(('*', rest)) => (0..=name.len()).any(|k| matches(rest, &name[k..])),
        Some((&p, rest)) => name
            .split_first()
            .is_some_and(|(&c, tail)| (p == '?' || p == c) && matches(rest, tail)),
    }
}

/// The tile paths `input` names, in order (see the module docs).
pub fn tile_paths(input: &Path) -> Result<Vec<PathBuf>> {
    let mut paths = Vec::new();
    if input.is_dir() || is_pattern(input) {
        let (dir, pattern) = if input.is_dir() {
            (input.to_path_buf(), None)
        } else {
            let dir = input
                .parent()
                .filter(|p| !p.as_os_str().is_empty())
                .unwrap_or(Path::new("."));
            let name = input.file_name().and_then(|n| n.to_str()).unwrap_or("");
            (dir.to_path_buf(), Some(name.chars().collect::<Vec<_>>()))
        };
        let entries =
            std::fs::read_dir(&dir).with_context(|| format!("listing {}", dir.display()))?;
        for entry in entries {
            let path = entry
                .with_context(|| format!("listing {}", dir.display()))?
                .path();
            let name: Vec<char> = path
                .file_name()
                .map(|n| n.to_string_lossy().chars().collect())
                .unwrap_or_default();
            let wanted = match &pattern {
                Some(p) => matches(p, &name),
                None => is_tile(&path),
            };
            if wanted && path.is_file() {
                paths.push(path);
            }
        }
        paths.sort();
    } else {
        let text = std::fs::read_to_string(input)
            .with_context(|| format!("reading the tile list {}", input.display()))?;
        let base = input.parent().unwrap_or(Path::new("."));
        for line in text.lines().map(str::trim) {
            if !line.is_empty() && !line.starts_with('#') {
                paths.push(base.join(line));
            }
        }
    }
    if paths.is_empty() {
        bail!(
            "{}: no tiles (a mosaic reads .hgt, .tif, .tiff, .png and raw grids by their .json sidecar)",
            input.display()
        );
    }
    Ok(paths)
}

/// Where a tile's samples sit: the first sample's coordinates, the spacing, and the edges
/// of what the tile covers.
#[derive(Clone, Copy, Debug)]
struct Lattice {
    /// Easting (longitude) of column 0.
    x0: f64,
    dx: f64,
    /// Northing (latitude) of row 0.
    y0: f64,
    dy: f64,
    west: f64,
    east: f64,
    south: f64,
    north: f64,
}

impl Lattice {
    fn of(georef: &Georef, width: usize, height: usize) -> Lattice {
        let (across, down) = match georef.registration {
            Registration::Node => ((width - 1) as f64, (height - 1) as f64),
            Registration::Cell => (width as f64, height as f64),
        };
        let dx = (georef.east - georef.west) / across;
        let dy = (georef.north - georef.south) / down;
        let (x0, y0) = match georef.registration {
            Registration::Node => (georef.west, georef.north),
            Registration::Cell => (georef.west + dx / 2.0, georef.north - dy / 2.0),
        };
        Lattice {
            x0,
            dx,
            y0,
            dy,
            west: georef.west,
            east: georef.east,
            south: georef.south,
            north: georef.north,
        }
    }

    /// Easting of the last sample.
    fn x_last(&self, width: usize) -> f64 {
        self.x0 + (width - 1) as f64 * self.dx
    }

    /// Northing of the last row.
    fn y_last(&self, height: usize) -> f64 {
        self.y0 - (height - 1) as f64 * self.dy
    }
}

/// One tile of a mosaic, known from its header.
#[derive(Clone, Debug)]
pub struct Tile {
    /// The file.
    pub path: PathBuf,
    /// Samples per row.
    pub width: usize,
    /// Rows.
    pub height: usize,
    /// Where it lies.
    pub georef: Georef,
    lattice: Lattice,
    /// Whether it spans 360° of longitude (a global grid that wraps).
    wraps: bool,
}

impl Tile {
    /// Sample cell area, in the georeference's units squared: the overlap rule's measure.
    fn cell(&self) -> f64 {
        self.lattice.dx * self.lattice.dy
    }

    /// Whether a point (easting/longitude `x`, northing/latitude `y`) is on the tile; for
    /// a geographic tile, the longitude it is at (`x` or `x +- 360`).
    fn covers(&self, y: f64, x: f64, geographic: bool) -> Option<f64> {
        let l = &self.lattice;
        let (ex, ey) = (l.dx * 1e-6, l.dy * 1e-6);
        if y < l.south - ey || y > l.north + ey {
            return None;
        }
        if self.wraps {
            return Some(x);
        }
        let inside = |x: f64| (l.west - ex..=l.east + ex).contains(&x);
        if inside(x) {
            Some(x)
        } else if geographic {
            [x + 360.0, x - 360.0].into_iter().find(|&x| inside(x))
        } else {
            None
        }
    }
}

/// A set of tiles in order of priority (finest first, then input order).
#[derive(Clone, Debug)]
pub struct Mosaic {
    /// The tiles, highest priority first.
    pub tiles: Vec<Tile>,
    /// Samples of all tiles.
    pub source_samples: usize,
}

/// What a mosaic resampled into: values and the facts the metadata records.
pub struct Assembled {
    /// Vertical units of every tile.
    pub units: String,
    /// Output samples no tile gave a value (uncovered or nodata).
    pub nodata_count: usize,
    /// Source quantum when every tile has the same one.
    pub quantum_m: Option<f64>,
}

impl Mosaic {
    /// Reads the headers of the tiles `input` names and orders them by the overlap rule.
    pub fn open(input: &Path) -> Result<Mosaic> {
        let mut tiles = Vec::new();
        for path in tile_paths(input)? {
            let header = input::probe_heights(&path)
                .with_context(|| format!("reading the mosaic tile {}", path.display()))?;
            let Some(georef) = header.georef else {
                bail!(
                    "{}: no georeference: a mosaic tile needs one (an .hgt name like N37E127, \
                     GeoTIFF ModelTiepoint/ModelPixelScale tags, or a sidecar `georef`)",
                    path.display()
                );
            };
            if header.width < 2 || header.height < 2 {
                bail!(
                    "{}: a mosaic tile needs at least 2 x 2 samples, not {} x {}",
                    path.display(),
                    header.width,
                    header.height
                );
            }
            let lattice = Lattice::of(&georef, header.width, header.height);
            let sane = [lattice.dx, lattice.dy, lattice.x0, lattice.y0]
                .iter()
                .all(|v| v.is_finite())
                && lattice.dx > 0.0
                && lattice.dy > 0.0;
            if !sane {
                bail!(
                    "{}: the georeference ({}..{} E, {}..{} N) gives no positive sample spacing",
                    path.display(),
                    georef.west,
                    georef.east,
                    georef.south,
                    georef.north
                );
            }
            // As for a global grid (`planet::Equirect`): the samples span 360 degrees.
            let wraps = (header.width as f64 * lattice.dx - 360.0).abs() < lattice.dx * 0.01;
            tiles.push(Tile {
                path,
                width: header.width,
                height: header.height,
                georef,
                lattice,
                wraps,
            });
        }
        let source_samples = tiles.iter().map(|t| t.width * t.height).sum();
        // Finest first; a stable sort keeps input order among equal spacings. Cells are
        // compared in steps of 1e-9 in log2, so that the same lattice computed from
        // different extents (rounding in the last bits) compares equal.
        let key = |t: &Tile| (t.cell().log2() * 1e9).round() as i64;
        tiles.sort_by_key(key);
        Ok(Mosaic {
            tiles,
            source_samples,
        })
    }

    /// The finest tile's east-west spacing.
    pub fn finest_spacing(&self) -> f64 {
        self.tiles.first().map_or(1.0, |t| t.lattice.dx)
    }

    /// Checks every tile is a latitude/longitude grid a planet can be built from.
    pub fn check_planet(&self) -> Result<()> {
        for t in &self.tiles {
            planet::Equirect::new(t.width, t.height, &[], &t.georef)
                .with_context(|| format!("{}: not a planet tile", t.path.display()))?;
        }
        Ok(())
    }

    /// Resamples the tiles onto the cube raster of `geom`.
    pub fn to_cube(&self, geom: &SphereGeometry) -> Result<(CubeGrid, Assembled)> {
        self.check_planet()?;
        check_memory(geom.cube_len() as u64, "choose a coarser --face-side")?;
        let side = geom.face_side() + 1;
        let mut out = vec![f64::NAN; geom.cube_len()];
        let angles = CubeAngles::new(geom);
        let borders = FaceBorders::new(geom);
        let mut reader = TileReader::default();
        let pb = crate::progress::bar(self.tiles.len() as u64, "resampling", "tiles");
        for tile in &self.tiles {
            let grid = reader.read(tile)?;
            let sampler = Sampler::new(tile, &grid, true);
            for (face, bounds) in borders.boxes(tile, geom).into_iter().enumerate() {
                let Some([u0, u1, v0, v1]) = bounds else {
                    continue;
                };
                let rows = &mut out[(face * side + v0) * side..(face * side + v1 + 1) * side];
                rows.par_chunks_mut(side).enumerate().for_each_init(
                    || vec![(0.0, 0.0); u1 + 1 - u0],
                    |span, (i, row)| {
                        angles.row_span(face, v0 + i, u0, span);
                        for u in u0..=u1 {
                            let (lat, lon) = span[u - u0];
                            if row[u].is_nan()
                                && let Some(s) = sampler.sample(lat, lon)
                            {
                                row[u] = s;
                            }
                        }
                    },
                );
            }
            pb.inc(1);
        }
        pb.finish_and_clear();
        let assembled = reader.finish(&out);
        let quantum_m = assembled.quantum_m;
        Ok((
            CubeGrid {
                face_side: geom.face_side(),
                values_m: out,
                quantum_m,
            },
            assembled,
        ))
    }

    /// The planar output lattice: node-registered, on the finest tile's lattice, spanning
    /// every tile's samples. The tiles must share a CRS.
    fn plane(&self) -> Result<(Plane, Georef)> {
        let Some(finest) = self.tiles.first() else {
            bail!("a mosaic without tiles");
        };
        for t in &self.tiles[1..] {
            if t.georef.crs != finest.georef.crs {
                bail!(
                    "{}: CRS {:?} differs from {}'s {:?}: a planar mosaic needs one CRS (or build a planet)",
                    t.path.display(),
                    t.georef.crs.as_deref().unwrap_or("unknown"),
                    finest.path.display(),
                    finest.georef.crs.as_deref().unwrap_or("unknown")
                );
            }
        }
        let f = finest.lattice;
        let west = self
            .tiles
            .iter()
            .map(|t| t.lattice.x0)
            .fold(f64::INFINITY, f64::min);
        let east = self
            .tiles
            .iter()
            .map(|t| t.lattice.x_last(t.width))
            .fold(f64::NEG_INFINITY, f64::max);
        let north = self
            .tiles
            .iter()
            .map(|t| t.lattice.y0)
            .fold(f64::NEG_INFINITY, f64::max);
        let south = self
            .tiles
            .iter()
            .map(|t| t.lattice.y_last(t.height))
            .fold(f64::INFINITY, f64::min);
        // The finest lattice, extended to reach every tile's outer samples.
        let x0 = f.x0 - ((f.x0 - west) / f.dx - 1e-6).ceil().max(0.0) * f.dx;
        let y0 = f.y0 + ((north - f.y0) / f.dy - 1e-6).ceil().max(0.0) * f.dy;
        let width = ((east - x0) / f.dx + 1e-6).floor() + 1.0;
        let height = ((y0 - south) / f.dy + 1e-6).floor() + 1.0;
        let max = input::MAX_SIDE as f64;
        if width > max || height > max {
            bail!(
                "the mosaic spans {width} x {height} samples at its finest spacing; the largest \
                 side is {max}"
            );
        }
        let (width, height) = (width as usize, height as usize);
        let georef = Georef {
            crs: finest.georef.crs.clone(),
            west: x0,
            east: x0 + (width - 1) as f64 * f.dx,
            north: y0,
            south: y0 - (height - 1) as f64 * f.dy,
            registration: Registration::Node,
            projection: finest.georef.projection.clone(),
        };
        let plane = Plane {
            x0,
            y0,
            dx: f.dx,
            dy: f.dy,
            width,
            height,
        };
        Ok((plane, georef))
    }

    /// Resamples the tiles onto one planar grid in memory (see [`Mosaic::rows`] for the
    /// same values a band of rows at a time).
    pub fn to_grid(&self) -> Result<(Grid, Georef, Assembled)> {
        let (plane, georef) = self.plane()?;
        let (width, height) = (plane.width, plane.height);
        check_memory(
            width as u64 * height as u64,
            "build a planet or fewer tiles",
        )?;
        let mut values = vec![f64::NAN; width * height];
        let mut reader = TileReader::default();
        let pb = crate::progress::bar(self.tiles.len() as u64, "assembling", "tiles");
        for tile in &self.tiles {
            let grid = reader.read(tile)?;
            plane.paint(tile, &grid, 0, &mut values);
            pb.inc(1);
        }
        pb.finish_and_clear();
        let assembled = reader.finish(&values);
        Ok((
            Grid {
                width,
                height,
                values_m: values,
                quantum_m: assembled.quantum_m,
            },
            georef,
            assembled,
        ))
    }

    /// The planar grid of [`Mosaic::to_grid`] as a row source for the out-of-core encoder:
    /// each band of rows reads the tiles it meets (kept while later bands still meet
    /// them), never the whole grid.
    pub fn rows(&self) -> Result<(MosaicRows<'_>, Georef)> {
        let (plane, georef) = self.plane()?;
        let mut reader = TileReader::default();
        // The first tile now, so the quantum is known before the first read (the encoder
        // asks for it first): the same answer as in memory whether the tiles agree or not.
        let first = match self.tiles.first() {
            Some(t) => vec![(0, reader.read(t)?)],
            None => Vec::new(),
        };
        let held_bytes = plane.band_tile_bytes(&self.tiles);
        Ok((
            MosaicRows {
                mosaic: self,
                plane,
                reader,
                held: first,
                next_row: 0,
                nodata: 0,
                first_pass: true,
                held_bytes,
            },
            georef,
        ))
    }
}

/// The lattice a planar mosaic resamples onto.
#[derive(Clone, Copy, Debug)]
struct Plane {
    x0: f64,
    y0: f64,
    dx: f64,
    dy: f64,
    width: usize,
    height: usize,
}

impl Plane {
    /// The output rows `r0 ..= r1` and columns `c0 ..= c1` a tile may give values to (its
    /// edges with a margin of one sample, which `covers` trims); `None` off the plane.
    fn footprint(&self, tile: &Tile) -> Option<[usize; 4]> {
        let l = tile.lattice;
        let r0 = ((self.y0 - l.north) / self.dy).floor().max(0.0) as usize;
        let r1 = (((self.y0 - l.south) / self.dy).ceil() as usize).min(self.height - 1);
        let c0 = ((l.west - self.x0) / self.dx).floor().max(0.0) as usize;
        let c1 = (((l.east - self.x0) / self.dx).ceil() as usize).min(self.width - 1);
        (r0 <= r1 && c0 <= c1).then_some([r0, r1, c0, c1])
    }

    /// Gives the tile's values to the samples of `out` (rows `first ..`) that no tile
    /// before it gave one.
    fn paint(&self, tile: &Tile, grid: &Grid, first: usize, out: &mut [f64]) {
        let Some([r0, r1, c0, c1]) = self.footprint(tile) else {
            return;
        };
        let w = self.width;
        let rows = out.len() / w;
        let (from, to) = (r0.max(first), (r1 + 1).min(first + rows));
        if from >= to {
            return;
        }
        let sampler = Sampler::new(tile, grid, false);
        out[(from - first) * w..(to - first) * w]
            .par_chunks_mut(w)
            .enumerate()
            .for_each(|(i, row)| {
                let y = self.y0 - (from + i) as f64 * self.dy;
                for (c, v) in row.iter_mut().enumerate().take(c1 + 1).skip(c0) {
                    if v.is_nan()
                        && let Some(s) = sampler.sample(y, self.x0 + c as f64 * self.dx)
                    {
                        *v = s;
                    }
                }
            });
    }

    /// The most bytes of decoded tiles one output row meets (8 bytes a sample): what a
    /// [`MosaicRows`] holds at once, about.
    fn band_tile_bytes(&self, tiles: &[Tile]) -> usize {
        let mut events: Vec<(usize, bool, usize)> = Vec::new();
        for t in tiles {
            if let Some([r0, r1, ..]) = self.footprint(t) {
                let bytes = t.width * t.height * 8;
                events.push((r0, true, bytes));
                events.push((r1 + 1, false, bytes));
            }
        }
        // Ends before starts at the same row.
        events.sort_by_key(|&(r, start, _)| (r, start));
        let (mut held, mut most) = (0usize, 0usize);
        for (_, start, bytes) in events {
            if start {
                held += bytes;
                most = most.max(held);
            } else {
                held -= bytes;
            }
        }
        most
    }
}

/// A planar mosaic read a band of rows at a time ([`Mosaic::rows`]).
pub struct MosaicRows<'a> {
    mosaic: &'a Mosaic,
    plane: Plane,
    reader: TileReader,
    /// Decoded tiles that later rows still meet, by index in priority order.
    held: Vec<(usize, Grid)>,
    /// The row after the last read (a read from an earlier row starts a new pass).
    next_row: usize,
    /// Samples no tile gave a value, over the rows of the first pass.
    nodata: usize,
    /// Whether the reads so far are the first pass (rows in order from 0).
    first_pass: bool,
    held_bytes: usize,
}

impl MosaicRows<'_> {
    /// About the most bytes of decoded tiles held at once (8 a sample).
    pub fn held_bytes(&self) -> usize {
        self.held_bytes
    }

    /// What the metadata records, once a pass has read every row.
    pub fn assembled(&self) -> Assembled {
        self.reader.assembled(self.nodata)
    }

    fn fill(&mut self, first: usize, out: &mut [f64]) -> Result<()> {
        let rows = out.len() / self.plane.width;
        let last = first + rows - 1;
        if first < self.next_row {
            self.held.clear();
            self.first_pass = false;
        }
        // Drop what no later row meets.
        let plane = self.plane;
        let tiles = &self.mosaic.tiles;
        self.held
            .retain(|(k, _)| plane.footprint(&tiles[*k]).is_some_and(|f| f[1] >= first));
        out.iter_mut().for_each(|v| *v = f64::NAN);
        for (k, tile) in tiles.iter().enumerate() {
            let Some([r0, r1, ..]) = plane.footprint(tile) else {
                continue;
            };
            if r1 < first || r0 > last {
                continue;
            }
            if !self.held.iter().any(|(j, _)| *j == k) {
                let grid = self.reader.read(tile)?;
                self.held.push((k, grid));
            }
            if let Some((_, grid)) = self.held.iter().find(|(j, _)| *j == k) {
                plane.paint(tile, grid, first, out);
            }
        }
        if self.first_pass {
            self.nodata += out.iter().filter(|v| v.is_nan()).count();
        }
        self.next_row = first + rows;
        Ok(())
    }
}

impl quincunx_codec::stream::RowSource for MosaicRows<'_> {
    fn width(&self) -> usize {
        self.plane.width
    }
    fn height(&self) -> usize {
        self.plane.height
    }
    fn read_rows(&mut self, first: usize, count: usize, out: &mut [f64]) -> Result<(), IoError> {
        self.fill(first, &mut out[..count * self.plane.width])
            .map_err(Into::into)
    }
    fn quantum_m(&self) -> Option<f64> {
        self.reader.quantum.flatten()
    }
}

impl Mosaic {
    /// The cube raster of [`Mosaic::to_cube`] as a source for the out-of-core planet
    /// encoder: each band of a face's rows reads the tiles whose footprint on that face it
    /// meets (kept while later bands still meet them), never the whole cube.
    pub fn cube_rows(&self, frame: &SphereFrame) -> Result<MosaicCube<'_>> {
        self.check_planet()?;
        let borders = FaceBorders::new(frame);
        let boxes: Vec<[Option<[usize; 4]>; 6]> =
            self.tiles.iter().map(|t| borders.boxes(t, frame)).collect();
        let mut reader = TileReader::default();
        // The first tile now, so the quantum is known before the first read.
        if let Some(t) = self.tiles.first() {
            reader.read(t)?;
        }
        // The most bytes of decoded tiles a band of up to 256 rows meets.
        let w = frame.face_side() + 1;
        let mut held_bytes = 0;
        for face in 0..6 {
            for first in (0..w).step_by(256) {
                let last = (first + 255).min(w - 1);
                let bytes: usize = boxes
                    .iter()
                    .zip(&self.tiles)
                    .filter(|(b, _)| {
                        b[face].is_some_and(|[_, _, v0, v1]| v1 >= first && v0 <= last)
                    })
                    .map(|(_, t)| t.width * t.height * 8)
                    .sum();
                held_bytes = held_bytes.max(bytes);
            }
        }
        Ok(MosaicCube {
            mosaic: self,
            angles: CubeAngles::new(frame),
            face_side: frame.face_side(),
            boxes,
            reader,
            held: Vec::new(),
            next: (0, 0),
            nodata: 0,
            first_pass: true,
            held_bytes,
        })
    }
}

/// A planet mosaic's cube raster, a band of face rows at a time ([`Mosaic::cube_rows`]).
pub struct MosaicCube<'a> {
    mosaic: &'a Mosaic,
    angles: CubeAngles,
    face_side: usize,
    /// Per tile, its footprint `[u0, u1, v0, v1]` on each face.
    boxes: Vec<[Option<[usize; 4]>; 6]>,
    reader: TileReader,
    /// Decoded tiles that later bands of the face still meet, by index in priority order.
    held: Vec<(usize, Grid)>,
    /// `(face, row)` after the last read (a read before it starts a new pass).
    next: (usize, usize),
    nodata: usize,
    first_pass: bool,
    held_bytes: usize,
}

impl MosaicCube<'_> {
    /// About the most bytes of decoded tiles held at once (8 a sample).
    pub fn held_bytes(&self) -> usize {
        self.held_bytes
    }

    /// What the metadata records, once a pass has read every row.
    pub fn assembled(&self) -> Assembled {
        self.reader.assembled(self.nodata)
    }

    fn fill(&mut self, face: usize, first: usize, out: &mut [f64]) -> Result<()> {
        let w = self.face_side + 1;
        let rows = out.len() / w;
        let last = first + rows - 1;
        if (face, first) < self.next {
            self.first_pass = false;
        }
        if (face, first) < self.next || face != self.next.0 {
            self.held.clear();
        }
        let boxes = &self.boxes;
        self.held
            .retain(|(k, _)| boxes[*k][face].is_some_and(|b| b[3] >= first));
        out.iter_mut().for_each(|v| *v = f64::NAN);
        for (k, tile) in self.mosaic.tiles.iter().enumerate() {
            let Some([u0, u1, v0, v1]) = self.boxes[k][face] else {
                continue;
            };
            if v1 < first || v0 > last {
                continue;
            }
            if !self.held.iter().any(|(j, _)| *j == k) {
                let grid = self.reader.read(tile)?;
                self.held.push((k, grid));
            }
            let Some((_, grid)) = self.held.iter().find(|(j, _)| *j == k) else {
                continue;
            };
            let sampler = Sampler::new(tile, grid, true);
            let (r0, r1) = (v0.max(first), v1.min(last));
            let angles = &self.angles;
            out[(r0 - first) * w..(r1 + 1 - first) * w]
                .par_chunks_mut(w)
                .enumerate()
                .for_each_init(
                    || vec![(0.0, 0.0); u1 + 1 - u0],
                    |span, (i, row)| {
                        angles.row_span(face, r0 + i, u0, span);
                        for u in u0..=u1 {
                            let (lat, lon) = span[u - u0];
                            if row[u].is_nan()
                                && let Some(s) = sampler.sample(lat, lon)
                            {
                                row[u] = s;
                            }
                        }
                    },
                );
        }
        if self.first_pass {
            self.nodata += out.iter().filter(|v| v.is_nan()).count();
        }
        self.next = (face, first + rows);
        Ok(())
    }
}

impl CubeSource for MosaicCube<'_> {
    fn face_side(&self) -> usize {
        self.face_side
    }

    fn read_face_rows(
        &mut self,
        face: usize,
        first: usize,
        count: usize,
        out: &mut [f64],
    ) -> Result<(), IoError> {
        let w = self.face_side + 1;
        planet::check_band(self.face_side, face, (first, count), out.len())?;
        self.fill(face, first, &mut out[..count * w])
            .map_err(Into::into)
    }

    fn quantum_m(&self) -> Option<f64> {
        self.reader.quantum.flatten()
    }
}

/// Refuses an output of `samples` larger than this machine's memory can build in core.
pub fn check_memory(samples: u64, advice: &str) -> Result<()> {
    let need = samples.saturating_mul(BUILD_BYTES_PER_SAMPLE);
    if let Some(total) = crate::layout::memory_total_bytes()
        && need > total
    {
        bail!(
            "the mosaic resamples to {samples} samples, about {} GB to build in memory; this \
             machine has {} GB: {advice}",
            need.div_ceil(1 << 30),
            total >> 30
        );
    }
    Ok(())
}

/// Reads tiles one at a time and keeps what must agree across them.
#[derive(Default)]
struct TileReader {
    units: Option<(String, PathBuf)>,
    /// `Some(q)` while every tile so far has quantum `q`; `None` once one differs.
    quantum: Option<Option<f64>>,
}

impl TileReader {
    fn read(&mut self, tile: &Tile) -> Result<Grid> {
        let raster = input::read_heights(&tile.path)
            .with_context(|| format!("reading the mosaic tile {}", tile.path.display()))?;
        let g = raster.grid;
        if (g.width, g.height) != (tile.width, tile.height) || raster.georef.is_none() {
            bail!(
                "{}: changed while the mosaic was built (its header said {} x {})",
                tile.path.display(),
                tile.width,
                tile.height
            );
        }
        match &self.units {
            Some((units, first)) if *units != raster.units => bail!(
                "{}: heights in {:?}, but {} has {units:?}: a mosaic needs one vertical unit",
                tile.path.display(),
                raster.units,
                first.display()
            ),
            Some(_) => {}
            None => self.units = Some((raster.units, tile.path.clone())),
        }
        self.quantum = Some(match self.quantum {
            None => g.quantum_m,
            Some(q) if q == g.quantum_m => q,
            Some(_) => None,
        });
        Ok(g)
    }

    fn finish(self, values: &[f64]) -> Assembled {
        self.assembled(values.par_iter().filter(|v| v.is_nan()).count())
    }

    /// What the metadata records of the tiles read, with `nodata_count` samples no tile
    /// gave a value.
    fn assembled(&self, nodata_count: usize) -> Assembled {
        Assembled {
            units: self
                .units
                .as_ref()
                .map_or_else(|| "m".to_owned(), |(u, _)| u.clone()),
            nodata_count,
            quantum_m: self.quantum.flatten(),
        }
    }
}

/// Bilinear samples of one tile, nodata-aware.
struct Sampler<'a> {
    tile: &'a Tile,
    grid: &'a Grid,
    geographic: bool,
}

/// Snaps a fractional index within 1e-6 of an integer onto it, so that a point of the same
/// lattice reads its sample exactly.
fn snap(t: f64) -> f64 {
    let r = t.round();
    if (t - r).abs() < 1e-6 { r } else { t }
}

impl<'a> Sampler<'a> {
    fn new(tile: &'a Tile, grid: &'a Grid, geographic: bool) -> Self {
        Sampler {
            tile,
            grid,
            geographic,
        }
    }

    /// The tile's value at northing/latitude `y`, easting/longitude `x` (rounded to the
    /// tile's quantum); `None` off the tile or where its neighbours are all nodata.
    fn sample(&self, y: f64, x: f64) -> Option<f64> {
        let x = self.tile.covers(y, x, self.geographic)?;
        let (w, h) = (self.tile.width, self.tile.height);
        let l = &self.tile.lattice;
        let row = snap((l.y0 - y) / l.dy).clamp(0.0, (h - 1) as f64);
        let col = snap((x - l.x0) / l.dx);
        let col = if self.tile.wraps {
            col.rem_euclid(w as f64)
        } else {
            col.clamp(0.0, (w - 1) as f64)
        };
        let (r0, c0) = (row as usize, (col as usize).min(w - 1));
        let (fr, fc) = (row - r0 as f64, col - c0 as f64);
        let r1 = (r0 + 1).min(h - 1);
        let c1 = if c0 + 1 < w {
            c0 + 1
        } else if self.tile.wraps {
            0
        } else {
            c0
        };
        let v = &self.grid.values_m;
        let at = [r0 * w + c0, r0 * w + c1, r1 * w + c0, r1 * w + c1].map(|k| v[k]);
        let weights = [
            (1.0 - fr) * (1.0 - fc),
            (1.0 - fr) * fc,
            fr * (1.0 - fc),
            fr * fc,
        ];
        let s = if at.iter().all(|x| x.is_finite()) {
            // The common case, in the same arithmetic as a single-grid planet build's.
            planet::bilinear(at, fr, fc)
        } else {
            let (mut sum, mut weight) = (0.0, 0.0);
            for (value, wt) in at.into_iter().zip(weights) {
                if value.is_finite() && wt > 0.0 {
                    sum += value * wt;
                    weight += wt;
                }
            }
            if weight <= 0.0 {
                return None;
            }
            sum / weight
        };
        Some(match self.grid.quantum_m {
            Some(q) => round(s / q) * q,
            None => s,
        })
    }
}

/// The border samples of the cube faces with their latitudes and longitudes, bucketed by
/// whole degrees: where a face's edge crosses a tile, the tile's footprint on the face
/// reaches that edge.
struct FaceBorders {
    /// The points by cell `(floor(lat) + 90) * 360 + floor(lon) + 180`.
    cells: Vec<Vec<BorderPoint>>,
}

/// A sample on the border of a cube face, where it is on the sphere.
#[derive(Clone, Copy)]
struct BorderPoint {
    face: u8,
    u: usize,
    v: usize,
    lat: f64,
    lon: f64,
}

/// The one-degree cell of a latitude/longitude.
fn degree_cell(lat: i64, lon: i64) -> usize {
    let lat = (lat.clamp(-90, 89) + 90) as usize;
    let lon = (lon + 180).rem_euclid(360) as usize;
    lat * 360 + lon
}

impl FaceBorders {
    fn new(geom: &SphereFrame) -> Self {
        let s = geom.face_side();
        let mut cells = vec![Vec::new(); 180 * 360];
        for face in 0..6u8 {
            for k in 0..=s {
                for (u, v) in [(k, 0), (k, s), (0, k), (s, k)] {
                    let (lat, lon) = planet::lat_lon(geom.sample_position(face, u, v));
                    cells[degree_cell(lat.floor() as i64, lon.floor() as i64)].push(BorderPoint {
                        face,
                        u,
                        v,
                        lat,
                        lon,
                    });
                }
            }
        }
        FaceBorders { cells }
    }

    /// The border points in the cells a tile's extent touches.
    fn near<'a>(&'a self, tile: &Tile) -> impl Iterator<Item = &'a BorderPoint> {
        let g = &tile.georef;
        let (lat0, lat1) = ((g.south.floor() as i64) - 1, (g.north.ceil() as i64) + 1);
        let (lon0, lon1) = if tile.wraps || g.east - g.west >= 358.0 {
            (-180, 179)
        } else {
            ((g.west.floor() as i64) - 1, (g.east.ceil() as i64) + 1)
        };
        let mut cells: Vec<usize> = (lat0.max(-90)..=lat1.min(89))
            .flat_map(|lat| (lon0..=lon1).map(move |lon| degree_cell(lat, lon)))
            .collect();
        cells.sort_unstable();
        cells.dedup();
        cells.into_iter().flat_map(|c| self.cells[c].iter())
    }

    /// The box of face samples `[u0, u1, v0, v1]` that holds a tile's footprint on each
    /// face (`None` where the tile does not reach the face). The footprint's extremes lie
    /// on its boundary, which is made of the tile's edges and of the face's edges inside
    /// the tile: the first are walked at a quarter of the cube's sample spacing, the second
    /// sample by sample (those in the degree cells around the tile), and the box grows by
    /// one sample each way.
    fn boxes(&self, tile: &Tile, geom: &SphereFrame) -> [Option<[usize; 4]>; 6] {
        let s = geom.face_side();
        let mut bounds = [[
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::INFINITY,
            f64::NEG_INFINITY,
        ]; 6];
        let mut add = |face: usize, u: f64, v: f64| {
            let b = &mut bounds[face];
            b[0] = b[0].min(u);
            b[1] = b[1].max(u);
            b[2] = b[2].min(v);
            b[3] = b[3].max(v);
        };
        let g = &tile.georef;
        let step = 0.25 * 90.0 / s as f64;
        let lat = |t: f64| (g.south + t * (g.north - g.south)).clamp(-90.0, 90.0);
        let lon = |t: f64| g.west + t * (g.east - g.west);
        let walk = |len: f64| (len.abs() / step).ceil().max(1.0) as usize;
        let (n_lat, n_lon) = (walk(g.north - g.south), walk(g.east - g.west));
        let mut edge_points = Vec::with_capacity(2 * (n_lat + n_lon + 2));
        for k in 0..=n_lat {
            let t = k as f64 / n_lat as f64;
            edge_points.push((lat(t), g.west));
            edge_points.push((lat(t), g.east));
        }
        for k in 0..=n_lon {
            let t = k as f64 / n_lon as f64;
            edge_points.push((g.south.clamp(-90.0, 90.0), lon(t)));
            edge_points.push((g.north.clamp(-90.0, 90.0), lon(t)));
        }
        for (la, lo) in edge_points {
            let (face, u, v) = planet::face_chart(la, lo, s);
            add(usize::from(face), u, v);
        }
        for p in self.near(tile) {
            if tile.covers(p.lat, p.lon, true).is_some() {
                add(usize::from(p.face), p.u as f64, p.v as f64);
            }
        }
        bounds.map(|[u0, u1, v0, v1]| {
            (u0 <= u1).then(|| {
                let lo = |x: f64| (x.floor() - 1.0).max(0.0) as usize;
                let hi = |x: f64| ((x.ceil() + 1.0) as usize).min(s);
                [lo(u0), hi(u1), lo(v0), hi(v1)]
            })
        })
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use super::*;

    #[test]
    fn patterns_match_like_a_shell() {
        let m = |p: &str, n: &str| {
            matches(
                &p.chars().collect::<Vec<_>>(),
                &n.chars().collect::<Vec<_>>(),
            )
        };
        assert!(m("N3?E12*.hgt", "N37E127.hgt"));
        assert!(m("*", "anything"));
        assert!(!m("N3?E12*.hgt", "N37E127.tif"));
        assert!(!m("?", ""));
        assert!(m("a*b*c", "aXXbYc"));
        assert!(!m("a*b*c", "aXXbY"));
    }
}
