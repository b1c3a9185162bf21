//! Readers that turn height and imagery files into the grids `quincunx build` encodes.
//!
//! Heights ([`read_heights`]), chosen by extension (case-insensitive):
//! - `.json`, `.i16`, `.f32`: the raw grid + JSON sidecar of the shared data folder (`raw`);
//! - `.hgt`: an SRTM tile, 1201² or 3601² big-endian `int16` (`hgt`);
//! - `.png`: 8- or 16-bit greyscale, scaled by an optional sidecar (`png16`);
//! - `.tif`/`.tiff`: single-band GeoTIFF (`geotiff`).
//!
//! Imagery ([`read_rgb`]): `.jpg`/`.jpeg` and `.png` (`rgb`).
//!
//! Every reader treats the file as untrusted: a bad file is an [`InputError`] naming the
//! file, never a panic, and no buffer is sized from a header before that size has been
//! checked against the file's length (or, for compressed formats, against the largest
//! expansion the compression allows).

use std::io::Read;
use std::path::{Path, PathBuf};

pub use quincunx_codec::encode::Grid;

mod geotiff;
mod hgt;
mod png16;
pub mod projection;
pub use projection::Projection;
mod raw;
pub use raw::{RawFile, RawRows};
mod rgb;

/// Largest width or height accepted from any file (2^24 samples).
pub const MAX_SIDE: u64 = 1 << 24;

/// Largest decoded buffer any reader allocates (4 GiB).
pub const MAX_DECODED_BYTES: u64 = 4 << 30;

/// How the samples sit on the extent given by a [`Georef`]: node (grid-registered: sample
/// (0, 0) sits on the north-west corner of the extent, the last sample on the south-east
/// corner) or cell (pixel-registered: the extent is the outer edge of the cells).
pub use quincunx_store::Registration;

/// Where a raster lies on the ground.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Georef {
    /// Coordinate reference system: `"EPSG:<code>"` when the source names an EPSG code,
    /// otherwise the source's own description (sidecar text); `None` when unknown.
    pub crs: Option<String>,
    /// Western edge (longitude or easting).
    pub west: f64,
    /// Eastern edge.
    pub east: f64,
    /// Northern edge (latitude or northing).
    pub north: f64,
    /// Southern edge.
    pub south: f64,
    /// Whether the edges pass through the outer samples or the outer cell edges.
    pub registration: Registration,
    /// What the reader recognised the CRS as (sidecar text or GeoTIFF geokeys), when it
    /// said anything. Not stored in repositories (`crs` is); [`Georef::projection`]
    /// parses `crs` when this is absent.
    #[serde(skip)]
    pub projection: Option<Projection>,
}

impl Georef {
    /// What a repository's metadata records of it.
    pub fn stored(&self) -> quincunx_store::Georef {
        quincunx_store::Georef {
            crs: self.crs.clone(),
            east: self.east,
            north: self.north,
            registration: self.registration,
            south: self.south,
            west: self.west,
        }
    }

    /// The CRS as recognised by the reader, else parsed from `crs`; `None` when the
    /// source names none.
    pub fn projection(&self) -> Option<Projection> {
        self.projection
            .clone()
            .or_else(|| self.crs.as_deref().map(Projection::parse))
    }
}

/// The file format a [`HeightRaster`] was read from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum InputFormat {
    /// Raw little-endian grid with a JSON sidecar.
    RawSidecar,
    /// SRTM `.hgt` tile.
    Hgt,
    /// 8- or 16-bit greyscale PNG.
    Png16,
    /// Single-band GeoTIFF.
    GeoTiff,
}

/// A height grid read from a file, with what the file says about it.
#[derive(Clone, Debug)]
pub struct HeightRaster {
    /// The heights (row 0 north, column 0 west; `NaN` = nodata).
    pub grid: Grid,
    /// Vertical units: `"m"` unless a sidecar says otherwise (`"ft"` for feet, else its text).
    pub units: String,
    /// Where the grid lies, when the file says.
    pub georef: Option<Georef>,
    /// The format it was read from.
    pub format: InputFormat,
    /// How many samples are nodata (`NaN` in `grid.values_m`).
    pub nodata_count: usize,
}

/// A colour image (row 0 north).
#[derive(Clone, Debug)]
pub struct RgbImage {
    /// Pixels per row.
    pub width: usize,
    /// Rows.
    pub height: usize,
    /// Row-major RGB pixels (alpha dropped, grey replicated).
    pub pixels: Vec<[u8; 3]>,
    /// Where the image lies, from a sidecar `NAME.json` beside it.
    pub georef: Option<Georef>,
}

/// Why an input file could not be read.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum InputError {
    /// The operating system refused to open or read a file.
    #[error("cannot read {}: {source}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// What went wrong.
        #[source]
        source: std::io::Error,
    },
    /// The extension names no supported format.
    #[error("{}: unsupported file extension; expected {expected}", path.display())]
    UnknownExtension {
        /// The file.
        path: PathBuf,
        /// The extensions this reader accepts.
        expected: &'static str,
    },
    /// A raw grid without its JSON sidecar.
    #[error("{}: raw grid without a sidecar: {} does not exist", path.display(), sidecar.display())]
    MissingSidecar {
        /// The raw grid.
        path: PathBuf,
        /// Where the sidecar was looked for.
        sidecar: PathBuf,
    },
    /// The sidecar is not valid JSON or has missing or wrong keys.
    #[error("sidecar {}: {message}", path.display())]
    Sidecar {
        /// The sidecar.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// The sidecar's `dtype` is not one the raw format has.
    #[error("sidecar {}: unknown dtype {dtype:?}; expected \"int16\" or \"float32\"", path.display())]
    UnknownDtype {
        /// The sidecar.
        path: PathBuf,
        /// The dtype it gives.
        dtype: String,
    },
    /// Width or height is zero or larger than [`MAX_SIDE`].
    #[error("{}: invalid size {width} x {height}: {reason}", path.display())]
    BadDimensions {
        /// The file that states the size.
        path: PathBuf,
        /// Stated width.
        width: u64,
        /// Stated height.
        height: u64,
        /// Why it is refused.
        reason: &'static str,
    },
    /// A raw grid's length does not match its stated size and sample type.
    #[error(
        "{}: expected {expected} bytes for {width} x {height} {dtype}, file has {actual}",
        path.display()
    )]
    Length {
        /// The raw grid.
        path: PathBuf,
        /// width x height x sample size.
        expected: u64,
        /// The file's length.
        actual: u64,
        /// Stated width.
        width: u64,
        /// Stated height.
        height: u64,
        /// Sample type.
        dtype: String,
    },
    /// An `.hgt` file whose length is no SRTM tile size.
    #[error(
        "{}: an SRTM .hgt tile has 2884802 bytes (SRTM3, 1201 x 1201) or 25934402 bytes (SRTM1, 3601 x 3601); file has {actual}",
        path.display()
    )]
    HgtLength {
        /// The file.
        path: PathBuf,
        /// Its length.
        actual: u64,
    },
    /// The file is truncated or corrupt.
    #[error("{}: invalid {format} file: {message}", path.display())]
    Corrupt {
        /// The file.
        path: PathBuf,
        /// The format it claims to be.
        format: &'static str,
        /// The decoder's complaint.
        message: String,
    },
    /// A valid file in a layout these readers do not handle.
    #[error("{}: unsupported {format}: {message}", path.display())]
    Unsupported {
        /// The file.
        path: PathBuf,
        /// The format.
        format: &'static str,
        /// What is not supported.
        message: String,
    },
    /// A colour PNG given as heights.
    #[error("{}: colour PNG: use it as imagery (read_rgb)", path.display())]
    ColourPng {
        /// The file.
        path: PathBuf,
    },
    /// The header promises more decoded data than the file could hold.
    #[error(
        "{}: the header asks for {bytes} decoded bytes, more than the {limit} a {file_bytes}-byte file allows",
        path.display()
    )]
    TooLarge {
        /// The file.
        path: PathBuf,
        /// Decoded size the header implies.
        bytes: u64,
        /// The largest size accepted for this file.
        limit: u64,
        /// The file's length.
        file_bytes: u64,
    },
}

/// Reads a height grid, choosing the reader by extension (see the module docs).
pub fn read_heights(path: &Path) -> Result<HeightRaster, InputError> {
    let raster = match extension(path).as_deref() {
        Some("json" | "i16" | "f32") => raw::read(path)?,
        Some("hgt") => hgt::read(path)?,
        Some("png") => png16::read(path)?,
        Some("tif" | "tiff") => geotiff::read(path)?,
        _ => {
            return Err(InputError::UnknownExtension {
                path: path.to_path_buf(),
                expected: ".json, .i16, .f32, .hgt, .png, .tif or .tiff",
            });
        }
    };
    tracing::debug!(
        path = %path.display(),
        format = ?raster.format,
        width = raster.grid.width,
        height = raster.grid.height,
        nodata = raster.nodata_count,
        "read heights"
    );
    Ok(raster)
}

/// What a height file says about itself before its samples are read.
#[derive(Clone, Debug)]
pub struct HeightHeader {
    /// Samples per row.
    pub width: usize,
    /// Rows.
    pub height: usize,
    /// Where the grid lies, when the file says.
    pub georef: Option<Georef>,
}

/// Reads a height file's size and georeference: from the header or sidecar alone for
/// `.hgt`, raw grids and GeoTIFF; a PNG is decoded (its sidecar has no size).
pub fn probe_heights(path: &Path) -> Result<HeightHeader, InputError> {
    let (width, height, georef) = match extension(path).as_deref() {
        Some("json" | "i16" | "f32") => {
            let f = raw::open(path)?;
            (f.width, f.height, f.georef)
        }
        Some("hgt") => {
            let (side, georef) = hgt::probe(path)?;
            (side, side, georef)
        }
        Some("tif" | "tiff") => geotiff::probe(path)?,
        _ => {
            let r = read_heights(path)?;
            (r.grid.width, r.grid.height, r.georef)
        }
    };
    Ok(HeightHeader {
        width,
        height,
        georef,
    })
}

/// Reads a colour image (`.jpg`, `.jpeg` or `.png`) and the georeference of a sidecar
/// `NAME.json` beside it, if there is one.
pub fn read_rgb(path: &Path) -> Result<RgbImage, InputError> {
    let image = match extension(path).as_deref() {
        Some("jpg" | "jpeg") => rgb::read_jpeg(path)?,
        Some("png") => rgb::read_png(path)?,
        _ => {
            return Err(InputError::UnknownExtension {
                path: path.to_path_buf(),
                expected: ".jpg, .jpeg or .png",
            });
        }
    };
    tracing::debug!(path = %path.display(), width = image.width, height = image.height, "read imagery");
    Ok(image)
}

/// The lower-cased extension.
fn extension(path: &Path) -> Option<String> {
    path.extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase)
}

fn io_error(path: &Path) -> impl FnOnce(std::io::Error) -> InputError + '_ {
    move |source| InputError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// Checks a stated size and converts it to `usize`.
fn check_dimensions(path: &Path, width: u64, height: u64) -> Result<(usize, usize), InputError> {
    let bad = |reason| InputError::BadDimensions {
        path: path.to_path_buf(),
        width,
        height,
        reason,
    };
    if width == 0 || height == 0 {
        return Err(bad("the image is empty"));
    }
    if width > MAX_SIDE || height > MAX_SIDE {
        return Err(bad("a side is larger than 2^24"));
    }
    let w = usize::try_from(width).map_err(|_| bad("too large for this machine"))?;
    let h = usize::try_from(height).map_err(|_| bad("too large for this machine"))?;
    w.checked_mul(h)
        .ok_or_else(|| bad("too large for this machine"))?;
    Ok((w, h))
}

/// Checks that `bytes` of decoded data are plausible for a `file_bytes`-long file whose
/// compression expands at most `max_ratio` times, and below [`MAX_DECODED_BYTES`].
fn check_decoded_size(
    path: &Path,
    bytes: u64,
    file_bytes: u64,
    max_ratio: u64,
) -> Result<usize, InputError> {
    let limit = file_bytes.saturating_mul(max_ratio).min(MAX_DECODED_BYTES);
    let too_large = || InputError::TooLarge {
        path: path.to_path_buf(),
        bytes,
        limit,
        file_bytes,
    };
    if bytes > limit {
        return Err(too_large());
    }
    usize::try_from(bytes).map_err(|_| too_large())
}

fn file_len(path: &Path) -> Result<u64, InputError> {
    Ok(std::fs::metadata(path).map_err(io_error(path))?.len())
}

/// Reads exactly `len` bytes (the length already checked against the file's metadata).
fn read_exact_len(path: &Path, len: usize) -> Result<Vec<u8>, InputError> {
    let file = std::fs::File::open(path).map_err(io_error(path))?;
    let mut bytes = Vec::with_capacity(len);
    file.take(len as u64)
        .read_to_end(&mut bytes)
        .map_err(io_error(path))?;
    if bytes.len() != len {
        return Err(InputError::Corrupt {
            path: path.to_path_buf(),
            format: "input",
            message: format!(
                "file shrank while being read ({} of {len} bytes)",
                bytes.len()
            ),
        });
    }
    Ok(bytes)
}

fn height_raster(
    grid: Grid,
    units: String,
    georef: Option<Georef>,
    format: InputFormat,
) -> HeightRaster {
    let nodata_count = grid.values_m.iter().filter(|v| v.is_nan()).count();
    HeightRaster {
        grid,
        units,
        georef,
        format,
        nodata_count,
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod test_support {
    use std::path::PathBuf;

    /// Width and height of every jacksboro fixture.
    pub const W: usize = 200;
    pub const H: usize = 150;

    pub fn fixture(name: &str) -> PathBuf {
        PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/tests/fixtures")).join(name)
    }

    /// The reference heights: `jacksboro.i16` read directly.
    pub fn jacksboro_m() -> Vec<f64> {
        let bytes = std::fs::read(fixture("jacksboro.i16")).unwrap();
        assert_eq!(bytes.len(), W * H * 2);
        bytes
            .chunks_exact(2)
            .map(|c| f64::from(i16::from_le_bytes([c[0], c[1]])))
            .collect()
    }

    /// Asserts `got` equals `want` except at `holes` (row, col), which must be `NaN`.
    pub fn assert_heights(got: &[f64], want: &[f64], holes: &[(usize, usize)]) {
        assert_eq!(got.len(), want.len());
        for (i, (g, w)) in got.iter().zip(want).enumerate() {
            if holes.contains(&(i / W, i % W)) {
                assert!(g.is_nan(), "sample {i} should be nodata, is {g}");
            } else {
                assert_eq!(g, w, "sample {i} (row {}, col {})", i / W, i % W);
            }
        }
    }

    pub fn assert_close(a: f64, b: f64) {
        assert!((a - b).abs() < 1e-9, "{a} != {b}");
    }
}
