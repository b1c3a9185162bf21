//! Raw little-endian grids (`NAME.i16` / `NAME.f32`) described by a JSON sidecar
//! (`NAME.json`), the layout of the shared data folder; and the sidecar parser the PNG
//! and imagery readers share.
//!
//! The real sidecars spell the georeference several ways: `registration` is free text
//! ("node (grid-registered): ...", "pixel (area): ...", "pixel-is-area: ..."), `georef` is
//! an object of `west`/`east`/`north`/`south` (or `west_x`/`north_y`/...), `null` or a
//! note, and `crs` is free text that may name an EPSG code. This module maps them all.

use std::io::Read;
use std::path::{Path, PathBuf};

use quincunx_codec::encode::{Grid, RawType};
use quincunx_codec::stream::IoError;
use serde_json::{Map, Value};

use super::{
    Georef, HeightRaster, InputError, InputFormat, Projection, Registration, check_dimensions,
    extension, file_len, height_raster, io_error, read_exact_len,
};

/// Sidecars are small; a larger file is not one.
const MAX_SIDECAR_BYTES: u64 = 1 << 20;

/// What a sidecar says (every key optional here; each reader requires what it needs).
#[derive(Clone, Debug)]
pub(super) struct Sidecar {
    /// The sidecar file.
    pub path: PathBuf,
    /// `width` key.
    pub width: Option<u64>,
    /// `height` key.
    pub height: Option<u64>,
    /// `dtype` key.
    pub dtype: Option<String>,
    /// `file` key: the data file's name.
    pub file: Option<String>,
    /// The raw value that marks nodata; `None` for `null`, `"NaN"` or no key (non-finite
    /// floats are always nodata).
    pub nodata: Option<f64>,
    /// `vertical_scale` (default 1).
    pub scale: f64,
    /// `vertical_offset` (default 0).
    pub offset: f64,
    /// `units`, normalised (`"m"` by default).
    pub units: String,
    /// `georef` + `registration` + `crs`, when the extent is given.
    pub georef: Option<Georef>,
}

impl Sidecar {
    /// Reads and parses a sidecar.
    pub fn read(path: &Path) -> Result<Sidecar, InputError> {
        let len = file_len(path)?;
        if len > MAX_SIDECAR_BYTES {
            return Err(sidecar_error(
                path,
                format!("{len} bytes is too large for a sidecar (at most {MAX_SIDECAR_BYTES})"),
            ));
        }
        let mut text = String::new();
        std::fs::File::open(path)
            .map_err(io_error(path))?
            .take(MAX_SIDECAR_BYTES)
            .read_to_string(&mut text)
            .map_err(io_error(path))?;
        let value: Value = serde_json::from_str(&text)
            .map_err(|e| sidecar_error(path, format!("not valid JSON: {e}")))?;
        Sidecar::from_json(path, &value).map_err(|message| sidecar_error(path, message))
    }

    /// The sidecar beside `data` (`NAME.json` for `NAME.ext`), if it exists.
    pub fn beside(data: &Path) -> Result<Option<Sidecar>, InputError> {
        let path = data.with_extension("json");
        match std::fs::metadata(&path) {
            Ok(_) => Sidecar::read(&path).map(Some),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
            Err(source) => Err(InputError::Io { path, source }),
        }
    }

    fn from_json(path: &Path, value: &Value) -> Result<Sidecar, String> {
        let obj = value
            .as_object()
            .ok_or("the top level is not a JSON object")?;
        let width = dimension(obj, "width")?;
        let height = dimension(obj, "height")?;
        let dtype = optional_str(obj, "dtype")?.map(str::to_owned);
        let file = optional_str(obj, "file")?.map(str::to_owned);
        let nodata = match obj.get("nodata") {
            None | Some(Value::Null) => None,
            Some(Value::Number(n)) => n.as_f64(),
            Some(Value::String(s)) if s.trim().eq_ignore_ascii_case("nan") => None,
            Some(Value::String(s)) => Some(
                s.trim()
                    .parse::<f64>()
                    .map_err(|_| format!("\"nodata\" is {s:?}, neither a number nor \"NaN\""))?,
            ),
            Some(other) => return Err(format!("\"nodata\" is {other}, not a number or \"NaN\"")),
        };
        let scale = optional_f64(obj, "vertical_scale")?.unwrap_or(1.0);
        let offset = optional_f64(obj, "vertical_offset")?.unwrap_or(0.0);
        if scale == 0.0 {
            return Err("\"vertical_scale\" is 0".into());
        }
        let units = optional_str(obj, "units")?.map_or_else(|| "m".to_owned(), normalise_units);
        let georef = parse_georef(obj, width)?;
        Ok(Sidecar {
            path: path.to_path_buf(),
            width,
            height,
            dtype,
            file,
            nodata,
            scale,
            offset,
            units,
            georef,
        })
    }

    /// Errs when the sidecar states a size that differs from the data's.
    pub fn check_size(&self, width: usize, height: usize) -> Result<(), InputError> {
        let matches = |stated: Option<u64>, actual: usize| {
            stated.is_none_or(|s| u64::try_from(actual).is_ok_and(|a| a == s))
        };
        if matches(self.width, width) && matches(self.height, height) {
            return Ok(());
        }
        let show = |v: Option<u64>| v.map_or_else(|| "?".to_owned(), |v| v.to_string());
        Err(sidecar_error(
            &self.path,
            format!(
                "says {} x {} but the image is {width} x {height}",
                show(self.width),
                show(self.height)
            ),
        ))
    }
}

/// A raw grid whose sidecar and length have been checked, not yet read.
pub struct RawFile {
    /// The data file.
    pub data_path: PathBuf,
    /// Samples per row.
    pub width: usize,
    /// Rows.
    pub height: usize,
    /// Sample type.
    pub ty: RawType,
    /// Metres per raw unit.
    pub scale: f64,
    /// Metres at raw 0.
    pub offset: f64,
    /// Raw nodata value.
    pub nodata: Option<f64>,
    /// Units of the values.
    pub units: String,
    /// Where the grid lies.
    pub georef: Option<Georef>,
    len: usize,
}

/// Opens a raw grid: `path` is the sidecar (`.json`) or the data (`.i16` / `.f32`).
pub fn open(path: &Path) -> Result<RawFile, InputError> {
    let is_sidecar = extension(path).as_deref() == Some("json");
    let sidecar_path = if is_sidecar {
        path.to_path_buf()
    } else {
        path.with_extension("json")
    };
    if !is_sidecar && !sidecar_path.exists() {
        return Err(InputError::MissingSidecar {
            path: path.to_path_buf(),
            sidecar: sidecar_path,
        });
    }
    let sidecar = Sidecar::read(&sidecar_path)?;
    let dtype = sidecar
        .dtype
        .clone()
        .ok_or_else(|| sidecar_error(&sidecar_path, "no \"dtype\" key".into()))?;
    let (ty, data_ext) = match RawType::from_dtype(&dtype) {
        Some(RawType::I16) => (RawType::I16, "i16"),
        Some(RawType::F32) => (RawType::F32, "f32"),
        None => {
            return Err(InputError::UnknownDtype {
                path: sidecar_path,
                dtype,
            });
        }
    };
    let data_path = if is_sidecar {
        data_file(&sidecar, data_ext)?
    } else {
        if extension(path).as_deref() != Some(data_ext) {
            return Err(sidecar_error(
                &sidecar_path,
                format!("dtype is {dtype} but the data file is not .{data_ext}"),
            ));
        }
        path.to_path_buf()
    };
    let stated = |key: &str, v: Option<u64>| {
        v.ok_or_else(|| sidecar_error(&sidecar_path, format!("no \"{key}\" key")))
    };
    let (width_u64, height_u64) = (
        stated("width", sidecar.width)?,
        stated("height", sidecar.height)?,
    );
    let (width, height) = check_dimensions(&sidecar_path, width_u64, height_u64)?;
    let item = if ty == RawType::I16 { 2 } else { 4 };
    let expected = width_u64
        .checked_mul(height_u64)
        .and_then(|n| n.checked_mul(item));
    let actual = file_len(&data_path)?;
    let expected = match expected {
        Some(e) if e == actual => e,
        _ => {
            return Err(InputError::Length {
                path: data_path,
                expected: expected.unwrap_or(u64::MAX),
                actual,
                width: width_u64,
                height: height_u64,
                dtype,
            });
        }
    };
    let len = usize::try_from(expected).map_err(|_| InputError::BadDimensions {
        path: sidecar_path.clone(),
        width: width_u64,
        height: height_u64,
        reason: "too large for this machine",
    })?;
    Ok(RawFile {
        data_path,
        width,
        height,
        ty,
        scale: sidecar.scale,
        offset: sidecar.offset,
        nodata: sidecar.nodata,
        units: sidecar.units,
        georef: sidecar.georef,
        len,
    })
}

/// Reads a raw grid: `path` is the sidecar (`.json`) or the data (`.i16` / `.f32`).
pub(super) fn read(path: &Path) -> Result<HeightRaster, InputError> {
    let RawFile {
        data_path,
        width,
        height,
        ty,
        scale,
        offset,
        nodata,
        units,
        georef,
        len,
    } = open(path)?;
    let bytes = read_exact_len(&data_path, len)?;
    let grid =
        Grid::from_raw_le(width, height, ty, &bytes, scale, offset, nodata).map_err(|e| {
            InputError::Corrupt {
                path: data_path.clone(),
                format: "raw grid",
                message: e.to_string(),
            }
        })?;
    Ok(height_raster(grid, units, georef, InputFormat::RawSidecar))
}

/// Rows of a raw grid read on demand from its file (for out-of-core builds): only the
/// rows asked for are ever in memory.
pub struct RawRows {
    file: RawFile,
    handle: std::fs::File,
    buf: Vec<u8>,
}

impl RawRows {
    /// Opens the grid for row reads.
    pub fn open(path: &Path) -> Result<RawRows, InputError> {
        let file = open(path)?;
        let handle = std::fs::File::open(&file.data_path).map_err(|source| InputError::Io {
            path: file.data_path.clone(),
            source,
        })?;
        Ok(RawRows {
            file,
            handle,
            buf: Vec::new(),
        })
    }

    /// What the sidecar says.
    pub fn raw(&self) -> &RawFile {
        &self.file
    }
}

impl quincunx_codec::stream::RowSource for RawRows {
    fn width(&self) -> usize {
        self.file.width
    }

    fn height(&self) -> usize {
        self.file.height
    }

    fn read_rows(&mut self, first: usize, count: usize, out: &mut [f64]) -> Result<(), IoError> {
        use std::io::{Seek, SeekFrom};
        let f = &self.file;
        let item = if f.ty == RawType::I16 { 2 } else { 4 };
        if first + count > f.height || out.len() != f.width * count {
            return Err(format!(
                "rows {first}..{} of a {}-row grid into {} values",
                first + count,
                f.height,
                out.len()
            )
            .into());
        }
        let start = (first * f.width * item) as u64;
        self.buf.resize(count * f.width * item, 0);
        self.handle
            .seek(SeekFrom::Start(start))
            .and_then(|_| self.handle.read_exact(&mut self.buf))
            .map_err(|e| {
                quincunx_codec::stream::io_context(f.data_path.display().to_string(), e.into())
            })?;
        for (dst, c) in out.iter_mut().zip(self.buf.chunks_exact(item)) {
            let raw = match f.ty {
                RawType::I16 => i16::from_le_bytes([c[0], c[1]]) as f64,
                RawType::F32 => f32::from_le_bytes([c[0], c[1], c[2], c[3]]) as f64,
            };
            *dst = if f.nodata == Some(raw) || !raw.is_finite() {
                f64::NAN
            } else {
                raw * f.scale + f.offset
            };
        }
        Ok(())
    }

    fn quantum_m(&self) -> Option<f64> {
        (self.file.ty == RawType::I16).then_some(self.file.scale)
    }
}

/// The data file a sidecar describes: its `file` key (a plain name beside it) or the
/// sidecar's name with the dtype's extension.
fn data_file(sidecar: &Sidecar, data_ext: &str) -> Result<PathBuf, InputError> {
    let Some(name) = &sidecar.file else {
        return Ok(sidecar.path.with_extension(data_ext));
    };
    let plain = Path::new(name)
        .file_name()
        .is_some_and(|f| f == name.as_str());
    if !plain {
        return Err(sidecar_error(
            &sidecar.path,
            format!("\"file\" is {name:?}; it must be a plain file name beside the sidecar"),
        ));
    }
    Ok(sidecar.path.with_file_name(name))
}

pub(super) fn sidecar_error(path: &Path, message: String) -> InputError {
    InputError::Sidecar {
        path: path.to_path_buf(),
        message,
    }
}

fn dimension(obj: &Map<String, Value>, key: &str) -> Result<Option<u64>, String> {
    match obj.get(key) {
        None | Some(Value::Null) => Ok(None),
        Some(v) => v
            .as_u64()
            .map(Some)
            .ok_or_else(|| format!("\"{key}\" is {v}, not a non-negative integer")),
    }
}

fn optional_str<'a>(obj: &'a Map<String, Value>, key: &str) -> Result<Option<&'a str>, String> {
    match obj.get(key) {
        None | Some(Value::Null) => Ok(None),
        Some(Value::String(s)) => Ok(Some(s)),
        Some(v) => Err(format!("\"{key}\" is {v}, not a string")),
    }
}

fn optional_f64(obj: &Map<String, Value>, key: &str) -> Result<Option<f64>, String> {
    match obj.get(key) {
        None | Some(Value::Null) => Ok(None),
        Some(v) => v
            .as_f64()
            .filter(|x| x.is_finite())
            .map(Some)
            .ok_or_else(|| format!("\"{key}\" is {v}, not a number")),
    }
}

/// `"m"` for metres in any spelling, `"ft"` for feet, else the text as given.
fn normalise_units(text: &str) -> String {
    let first = text
        .split(|c: char| !c.is_ascii_alphabetic())
        .find(|w| !w.is_empty())
        .unwrap_or("")
        .to_ascii_lowercase();
    match first.as_str() {
        "m" | "meter" | "meters" | "metre" | "metres" => "m".to_owned(),
        "ft" | "foot" | "feet" => "ft".to_owned(),
        _ => text.trim().to_owned(),
    }
}

/// `"EPSG:<code>"` when the text names one, else the text itself.
pub(super) fn normalise_crs(text: &str) -> Option<String> {
    let text = text.trim();
    if text.is_empty() {
        return None;
    }
    let upper = text.to_ascii_uppercase();
    if let Some(at) = upper.find("EPSG:") {
        let code: String = upper[at + 5..]
            .chars()
            .take_while(char::is_ascii_digit)
            .collect();
        if !code.is_empty() {
            return Some(format!("EPSG:{code}"));
        }
    }
    Some(text.to_owned())
}

/// The registration a free-text description names, if any.
fn classify_registration(text: &str) -> Option<Registration> {
    let t = text.to_ascii_lowercase();
    if t.starts_with("node")
        || t.contains("grid-registered")
        || t.contains("pixel-is-point")
        || t.contains("pixelispoint")
        || t.contains("sample centres")
        || t.contains("sample centers")
    {
        Some(Registration::Node)
    } else if t.starts_with("cell")
        || t.starts_with("pixel")
        || t.contains("pixel-is-area")
        || t.contains("pixelisarea")
        || t.contains("cell edges")
        || t.contains("outer edges")
    {
        Some(Registration::Cell)
    } else {
        None
    }
}

/// The extent from `georef` (`None` when absent, `null`, a note, or missing an edge),
/// with its registration and CRS.
fn parse_georef(obj: &Map<String, Value>, width: Option<u64>) -> Result<Option<Georef>, String> {
    let Some(Value::Object(g)) = obj.get("georef") else {
        return Ok(None);
    };
    let edge = |names: &[&str]| -> Result<Option<f64>, String> {
        match names.iter().find_map(|n| g.get(*n).map(|v| (n, v))) {
            None | Some((_, Value::Null)) => Ok(None),
            Some((name, v)) => v
                .as_f64()
                .map(Some)
                .ok_or_else(|| format!("\"georef.{name}\" is {v}, not a number")),
        }
    };
    let (Some(west), Some(east), Some(north), Some(south)) = (
        edge(&["west", "west_x", "west_lon", "xmin"])?,
        edge(&["east", "east_x", "east_lon", "xmax"])?,
        edge(&["north", "north_y", "north_lat", "ymax"])?,
        edge(&["south", "south_y", "south_lat", "ymin"])?,
    ) else {
        return Ok(None);
    };
    if east <= west || north <= south {
        return Err(format!(
            "georef extent west {west}, east {east}, north {north}, south {south} is empty or inverted"
        ));
    }
    let text = |v: Option<&Value>| v.and_then(Value::as_str).map(str::to_owned);
    let registration = [
        text(obj.get("registration")),
        text(g.get("registration")),
        text(g.get("extent_note")),
    ]
    .iter()
    .flatten()
    .find_map(|t| classify_registration(t))
    .or_else(|| registration_from_spacing(obj, west, east, width))
    .unwrap_or(Registration::Cell);
    let texts = [
        text(obj.get("crs")),
        text(g.get("crs")),
        text(g.get("projection")),
    ];
    let crs = texts.iter().flatten().find_map(|t| normalise_crs(t));
    // The first text that names a CRS these readers recognise, else the first given.
    let parsed: Vec<Projection> = texts
        .iter()
        .flatten()
        .filter(|t| !t.trim().is_empty())
        .map(|t| Projection::parse(t))
        .collect();
    let projection = parsed
        .iter()
        .find(|p| !matches!(p, Projection::Unrecognised { .. }))
        .or(parsed.first())
        .cloned();
    Ok(Some(Georef {
        crs,
        west,
        east,
        north,
        south,
        registration,
        projection,
    }))
}

/// When the text does not say: node if `(east - west) / (width - 1)` matches the stated
/// east-west spacing better than `(east - west) / width` does.
fn registration_from_spacing(
    obj: &Map<String, Value>,
    west: f64,
    east: f64,
    width: Option<u64>,
) -> Option<Registration> {
    let dx = obj
        .get("sample_spacing_deg")?
        .as_array()?
        .first()?
        .as_f64()?;
    let width = width.filter(|&w| w > 1)? as f64;
    let span = east - west;
    let cell_miss = (span / width - dx).abs();
    let node_miss = (span / (width - 1.0) - dx).abs();
    Some(if node_miss < cell_miss {
        Registration::Node
    } else {
        Registration::Cell
    })
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use super::super::read_heights;
    use super::super::test_support::{H, W, assert_close, assert_heights, fixture, jacksboro_m};
    use super::*;

    fn write(dir: &Path, name: &str, bytes: &[u8]) -> PathBuf {
        let p = dir.join(name);
        std::fs::write(&p, bytes).unwrap();
        p
    }

    fn jacksboro_sidecar() -> Value {
        serde_json::from_slice(&std::fs::read(fixture("jacksboro.json")).unwrap()).unwrap()
    }

    #[test]
    fn raw_grid_reads_by_data_or_sidecar_path() {
        for name in ["jacksboro.i16", "jacksboro.json", "JACKSBORO.I16"] {
            let path = fixture(name);
            if !path.exists() {
                // A case-sensitive file system: the upper-case name is only for dispatch.
                continue;
            }
            let r = read_heights(&path).unwrap();
            assert_eq!(r.format, InputFormat::RawSidecar);
            assert_eq!((r.grid.width, r.grid.height), (W, H));
            assert_eq!(r.grid.quantum_m, Some(1.0));
            assert_eq!(r.units, "m");
            assert_eq!(r.nodata_count, 0);
            assert_heights(&r.grid.values_m, &jacksboro_m(), &[]);
            let g = r.georef.unwrap();
            assert_close(g.west, -84.41375);
            assert_close(g.north, 36.73291667);
            assert_close(g.east, -84.41375 + 200.0 / 1200.0);
            assert_close(g.south, 36.73291667 - 150.0 / 1200.0);
            // The text does not say; the spacing matches (east - west) / width.
            assert_eq!(g.registration, Registration::Cell);
            assert_eq!(g.crs.as_deref(), Some("geographic lat/lon (NAD83/WGS84)"));
        }
    }

    #[test]
    fn real_shared_sidecars_parse() {
        let dir = Path::new("/work/shared/data");
        if !dir.exists() {
            return;
        }
        let expect = [
            (
                "korea_srtm3_4097.json",
                Some((Registration::Node, "EPSG:4326")),
            ),
            (
                "etopo5_global.json",
                Some((Registration::Node, "geographic")),
            ),
            (
                "etopo20_global.json",
                Some((Registration::Cell, "geographic")),
            ),
            (
                "fixture_colorado_ned_10m.json",
                Some((Registration::Cell, "EPSG:4269")),
            ),
            (
                "fixture_lidar_dem_1m.json",
                Some((Registration::Cell, "EPSG:26915")),
            ),
            (
                "fixture_topobathy_salish_sea.json",
                Some((Registration::Node, "geographic")),
            ),
            (
                "bmng_global_5400x2700.json",
                Some((Registration::Cell, "equirectangular")),
            ),
            ("fixture_fuji_terrainrgb.json", None),
            ("fixture_gsi_dem_256.json", None),
            ("fixture_gsi_color_256.json", None),
        ];
        for (name, want) in expect {
            let s = Sidecar::read(&dir.join(name)).unwrap();
            match (s.georef, want) {
                (None, None) => {}
                (Some(g), Some((reg, crs))) => {
                    assert_eq!(g.registration, reg, "{name}");
                    assert!(g.crs.as_deref().unwrap().starts_with(crs), "{name}: {g:?}");
                    assert!(g.east > g.west && g.north > g.south, "{name}");
                }
                (got, want) => panic!("{name}: got {got:?}, want {want:?}"),
            }
        }
        let korea = Sidecar::read(&dir.join("korea_srtm3_4097.json")).unwrap();
        assert_eq!(korea.nodata, Some(-32768.0));
        assert_eq!(korea.units, "m");
        let colorado = Sidecar::read(&dir.join("fixture_colorado_ned_10m.json")).unwrap();
        assert_eq!(colorado.nodata, None);
    }

    #[test]
    fn truncated_raw_is_a_length_error() {
        let dir = tempfile::tempdir().unwrap();
        let bytes = std::fs::read(fixture("jacksboro.i16")).unwrap();
        write(
            dir.path(),
            "j.json",
            &std::fs::read(fixture("jacksboro.json")).unwrap(),
        );
        let data = write(dir.path(), "j.i16", &bytes[..bytes.len() - 3]);
        let err = read_heights(&data).unwrap_err();
        assert!(matches!(
            err,
            InputError::Length {
                expected: 60000,
                actual: 59997,
                ..
            }
        ));
        let msg = err.to_string();
        assert!(
            msg.contains("expected 60000 bytes for 200 x 150 int16, file has 59997"),
            "{msg}"
        );
    }

    #[test]
    fn sidecar_with_wrong_width_is_a_length_error() {
        let dir = tempfile::tempdir().unwrap();
        let mut meta = jacksboro_sidecar();
        meta["width"] = 201.into();
        meta["file"] = "j.i16".into();
        write(
            dir.path(),
            "j.i16",
            &std::fs::read(fixture("jacksboro.i16")).unwrap(),
        );
        let side = write(dir.path(), "j.json", meta.to_string().as_bytes());
        let err = read_heights(&side).unwrap_err();
        assert!(
            matches!(err, InputError::Length { width: 201, .. }),
            "{err}"
        );
        assert!(err.to_string().contains("201 x 150"));
    }

    #[test]
    fn unknown_dtype_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let mut meta = jacksboro_sidecar();
        meta["dtype"] = "int24".into();
        write(
            dir.path(),
            "j.i16",
            &std::fs::read(fixture("jacksboro.i16")).unwrap(),
        );
        write(dir.path(), "j.json", meta.to_string().as_bytes());
        let err = read_heights(&dir.path().join("j.i16")).unwrap_err();
        assert!(matches!(&err, InputError::UnknownDtype { dtype, .. } if dtype == "int24"));
        assert!(err.to_string().contains("int24"));
    }

    #[test]
    fn zero_and_huge_sizes_are_refused_before_reading() {
        let dir = tempfile::tempdir().unwrap();
        write(dir.path(), "j.i16", &[]);
        for (w, h) in [(0u64, 150u64), (200, 0), (1 << 25, 1), (1 << 24, 1 << 24)] {
            let mut meta = jacksboro_sidecar();
            meta["width"] = w.into();
            meta["height"] = h.into();
            meta["file"] = "j.i16".into();
            let side = write(dir.path(), "j.json", meta.to_string().as_bytes());
            let err = read_heights(&side).unwrap_err();
            if w == 1 << 24 {
                // Each side is allowed; the empty file is the problem.
                assert!(matches!(err, InputError::Length { actual: 0, .. }), "{err}");
            } else {
                assert!(matches!(err, InputError::BadDimensions { .. }), "{err}");
            }
        }
    }

    #[test]
    fn bad_sidecars_are_sidecar_errors() {
        let dir = tempfile::tempdir().unwrap();
        write(
            dir.path(),
            "j.i16",
            &std::fs::read(fixture("jacksboro.i16")).unwrap(),
        );
        let cases: [(&str, &str); 7] = [
            ("{", "not valid JSON"),
            ("[1, 2]", "not a JSON object"),
            (r#"{"width": 200, "height": 150}"#, "dtype"),
            (r#"{"width": -1, "height": 150, "dtype": "int16"}"#, "width"),
            (r#"{"width": 200, "dtype": "int16"}"#, "height"),
            (
                r#"{"width": 200, "height": 150, "dtype": "int16", "nodata": "none"}"#,
                "nodata",
            ),
            (
                r#"{"width": 200, "height": 150, "dtype": "int16", "file": "../j.i16"}"#,
                "plain file name",
            ),
        ];
        for (json, needle) in cases {
            let side = write(dir.path(), "j.json", json.as_bytes());
            let err = read_heights(&side).unwrap_err();
            assert!(matches!(err, InputError::Sidecar { .. }), "{json}: {err}");
            assert!(err.to_string().contains(needle), "{json}: {err}");
        }
    }

    #[test]
    fn missing_sidecar_is_reported() {
        let dir = tempfile::tempdir().unwrap();
        let data = write(dir.path(), "lonely.f32", &[0; 16]);
        let err = read_heights(&data).unwrap_err();
        assert!(matches!(err, InputError::MissingSidecar { .. }));
        assert!(err.to_string().contains("lonely.json"));
    }

    #[test]
    fn all_nan_f32_reads_with_every_sample_nodata() {
        let dir = tempfile::tempdir().unwrap();
        let bytes: Vec<u8> = (0..120 * 91).flat_map(|_| f32::NAN.to_le_bytes()).collect();
        let data = write(dir.path(), "t.f32", &bytes);
        let meta = r#"{"width": 120, "height": 91, "dtype": "float32", "nodata": "NaN",
            "units": "meters relative to sea level (negative = below sea level)"}"#;
        write(dir.path(), "t.json", meta.as_bytes());
        let r = read_heights(&data).unwrap();
        assert_eq!(r.nodata_count, 120 * 91);
        assert_eq!(r.grid.quantum_m, None);
        assert_eq!(r.units, "m");
        assert_eq!(r.georef, None);
    }

    #[test]
    fn real_topobathy_f32_matches_its_stats() {
        let path = Path::new("/work/shared/data/fixture_topobathy_salish_sea.f32");
        if !path.exists() {
            return;
        }
        let r = read_heights(path).unwrap();
        assert_eq!((r.grid.width, r.grid.height), (120, 91));
        let min = r
            .grid
            .values_m
            .iter()
            .copied()
            .fold(f64::INFINITY, f64::min);
        let max = r
            .grid
            .values_m
            .iter()
            .copied()
            .fold(f64::NEG_INFINITY, f64::max);
        assert_eq!((min, max), (-1437.0, 2205.0));
        assert_eq!(r.georef.unwrap().registration, Registration::Node);
    }

    #[test]
    fn scale_offset_and_nodata_apply() {
        let dir = tempfile::tempdir().unwrap();
        let raw: Vec<u8> = [10i16, -32768, 20, 30]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        let data = write(dir.path(), "s.i16", &raw);
        let meta = r#"{"width": 2, "height": 2, "dtype": "int16", "nodata": -32768,
            "vertical_scale": 0.5, "vertical_offset": 100, "units": "feet"}"#;
        write(dir.path(), "s.json", meta.as_bytes());
        let r = read_heights(&data).unwrap();
        assert_eq!(r.grid.values_m[0], 105.0);
        assert!(r.grid.values_m[1].is_nan());
        assert_eq!(r.grid.values_m[3], 115.0);
        assert_eq!(r.grid.quantum_m, Some(0.5));
        assert_eq!(r.nodata_count, 1);
        assert_eq!(r.units, "ft");
    }

    #[test]
    fn unknown_extension_is_refused() {
        let err = read_heights(Path::new("heights.xyz")).unwrap_err();
        assert!(matches!(err, InputError::UnknownExtension { .. }));
        assert!(err.to_string().contains(".hgt"));
    }
}
