//! Single-band GeoTIFF heights (stripped or tiled; uncompressed, LZW, deflate or PackBits)
//! in `uint8`, `int16`, `uint16`, `int32`, `uint32`, `float32` or `float64`.
//!
//! - Nodata: the GDAL_NODATA tag (42113, ASCII) when present; non-finite floats always.
//! - Georeference: ModelPixelScale (33550) + ModelTiepoint (33922); GTRasterTypeGeoKey in
//!   the GeoKeyDirectory (34735) says PixelIsArea (cell, the default) or PixelIsPoint
//!   (node); the CRS is the projected or geographic EPSG code of the geokeys, and what
//!   it is ([`Projection::from_geotiff`]) comes from GTModelTypeGeoKey, those codes, and
//!   for a user-defined projection ProjCoordTransGeoKey and ProjStdParallel1GeoKey.
//! - Memory: the decoded size is checked against what the file can hold (its length for
//!   uncompressed data, 4096 times it for compressed data) before anything is allocated.

use std::io::BufReader;
use std::path::Path;

use quincunx_codec::encode::Grid;
use tiff::decoder::{Decoder, DecodingResult, Limits};
use tiff::tags::Tag;

use super::{
    Georef, HeightRaster, InputError, InputFormat, Projection, Registration, check_decoded_size,
    check_dimensions, file_len, height_raster, io_error,
};

/// LZW (the worst case) expands a 12-bit code to at most about 4 KiB.
const COMPRESSED_MAX_RATIO: u64 = 4096;

/// GeoKey ids (GeoTIFF 1.0, section 6.2).
const GT_MODEL_TYPE: u16 = 1024;
const GT_RASTER_TYPE: u16 = 1025;
const PROJ_COORD_TRANS: u16 = 3075;
const PROJ_STD_PARALLEL1: u16 = 3078;
/// GeoDoubleParamsTag: where double-valued geokeys are.
const GEO_DOUBLE_PARAMS: u16 = 34736;
const GEOGRAPHIC_TYPE: u16 = 2048;
const PROJECTED_CS_TYPE: u16 = 3072;

/// The sample types read as heights.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum SampleType {
    U8,
    U16,
    I16,
    U32,
    I32,
    F32,
    F64,
}

impl SampleType {
    fn bytes(self) -> u64 {
        match self {
            SampleType::U8 => 1,
            SampleType::U16 | SampleType::I16 => 2,
            SampleType::U32 | SampleType::I32 | SampleType::F32 => 4,
            SampleType::F64 => 8,
        }
    }

    fn is_float(self) -> bool {
        matches!(self, SampleType::F32 | SampleType::F64)
    }
}

/// A GeoTIFF's header, checked, with the decoder positioned to read the image.
struct Header {
    decoder: Decoder<BufReader<std::fs::File>>,
    width: usize,
    height: usize,
    ty: SampleType,
    decoded_bytes: usize,
    nodata: Option<f64>,
    georef: Option<Georef>,
}

/// Size and georeference of a single-band GeoTIFF, without decoding its samples.
pub(super) fn probe(path: &Path) -> Result<(usize, usize, Option<Georef>), InputError> {
    let h = header(path)?;
    Ok((h.width, h.height, h.georef))
}

fn header(path: &Path) -> Result<Header, InputError> {
    let corrupt = |e: tiff::TiffError| tiff_error(path, e);
    let unsupported = |message: String| InputError::Unsupported {
        path: path.to_path_buf(),
        format: "TIFF",
        message,
    };
    let file_bytes = file_len(path)?;
    let file = std::fs::File::open(path).map_err(io_error(path))?;
    let mut decoder = Decoder::new(BufReader::new(file)).map_err(corrupt)?;
    let (w, h) = decoder.dimensions().map_err(corrupt)?;
    let (width, height) = check_dimensions(path, w.into(), h.into())?;

    let samples: u16 = decoder
        .find_tag_unsigned(Tag::SamplesPerPixel)
        .map_err(corrupt)?
        .unwrap_or(1);
    if samples != 1 {
        let planar: u16 = decoder
            .find_tag_unsigned(Tag::PlanarConfiguration)
            .map_err(corrupt)?
            .unwrap_or(1);
        let layout = if planar == 2 {
            "planar-separate"
        } else {
            "interleaved"
        };
        return Err(unsupported(format!(
            "{samples} bands ({layout}); heights need a single-band TIFF"
        )));
    }
    let photometric: Option<u16> = decoder
        .find_tag_unsigned(Tag::PhotometricInterpretation)
        .map_err(corrupt)?;
    if photometric == Some(3) {
        return Err(unsupported(
            "palette (8-bit colour) image; heights need a single greyscale band".to_owned(),
        ));
    }
    let bits: Vec<u16> = decoder
        .find_tag_unsigned_vec(Tag::BitsPerSample)
        .map_err(corrupt)?
        .unwrap_or_else(|| vec![1]);
    let format: Vec<u16> = decoder
        .find_tag_unsigned_vec(Tag::SampleFormat)
        .map_err(corrupt)?
        .unwrap_or_else(|| vec![1]);
    let (bits, format) = (
        bits.first().copied().unwrap_or(1),
        format.first().copied().unwrap_or(1),
    );
    let ty = match (format, bits) {
        (1, 8) => SampleType::U8,
        (1, 16) => SampleType::U16,
        (2, 16) => SampleType::I16,
        (1, 32) => SampleType::U32,
        (2, 32) => SampleType::I32,
        (3, 32) => SampleType::F32,
        (3, 64) => SampleType::F64,
        (_, 1) => return Err(unsupported("bilevel (1-bit) image".to_owned())),
        (5 | 6, _) => return Err(unsupported("complex samples".to_owned())),
        (f, b) => {
            let kind = match f {
                1 => "unsigned integer",
                2 => "signed integer",
                3 => "floating point",
                _ => "unknown-format",
            };
            return Err(unsupported(format!("{b}-bit {kind} samples")));
        }
    };
    let compression: u16 = decoder
        .find_tag_unsigned(Tag::Compression)
        .map_err(corrupt)?
        .unwrap_or(1);
    let ratio = if compression == 1 {
        1
    } else {
        COMPRESSED_MAX_RATIO
    };
    let decoded_bytes = (w as u64)
        .checked_mul(h.into())
        .and_then(|n| n.checked_mul(ty.bytes()))
        .unwrap_or(u64::MAX);
    let decoded_bytes = check_decoded_size(path, decoded_bytes, file_bytes, ratio)?;

    let nodata = gdal_nodata(&mut decoder, path)?;
    let georef = georef(&mut decoder, path, width, height)?;
    Ok(Header {
        decoder,
        width,
        height,
        ty,
        decoded_bytes,
        nodata,
        georef,
    })
}

/// Reads a single-band GeoTIFF.
pub(super) fn read(path: &Path) -> Result<HeightRaster, InputError> {
    let corrupt = |e: tiff::TiffError| tiff_error(path, e);
    let Header {
        decoder,
        width,
        height,
        ty,
        decoded_bytes,
        nodata,
        georef,
    } = header(path)?;
    let mut limits = Limits::default();
    limits.decoding_buffer_size = decoded_bytes;
    let mut decoder = decoder.with_limits(limits);
    let data = decoder.read_image().map_err(corrupt)?;
    let values_m = to_metres(data, ty, nodata).ok_or_else(|| InputError::Corrupt {
        path: path.to_path_buf(),
        format: "TIFF",
        message: "decoded samples do not match the header's sample type".to_owned(),
    })?;
    if values_m.len() != width * height {
        return Err(InputError::Corrupt {
            path: path.to_path_buf(),
            format: "TIFF",
            message: format!(
                "decoded {} samples for a {width} x {height} image",
                values_m.len()
            ),
        });
    }
    let grid = Grid {
        width,
        height,
        values_m,
        quantum_m: (!ty.is_float()).then_some(1.0),
    };
    Ok(height_raster(
        grid,
        "m".to_owned(),
        georef,
        InputFormat::GeoTiff,
    ))
}

fn tiff_error(path: &Path, e: tiff::TiffError) -> InputError {
    match e {
        tiff::TiffError::UnsupportedError(u) => InputError::Unsupported {
            path: path.to_path_buf(),
            format: "TIFF",
            message: u.to_string(),
        },
        other => InputError::Corrupt {
            path: path.to_path_buf(),
            format: "TIFF",
            message: other.to_string(),
        },
    }
}

/// The GDAL_NODATA tag's value (`None` when absent or `nan`, since NaN is nodata anyway).
fn gdal_nodata<R: std::io::Read + std::io::Seek>(
    decoder: &mut Decoder<R>,
    path: &Path,
) -> Result<Option<f64>, InputError> {
    let Some(value) = decoder
        .find_tag(Tag::GdalNodata)
        .map_err(|e| tiff_error(path, e))?
    else {
        return Ok(None);
    };
    let text = value.into_string().map_err(|e| tiff_error(path, e))?;
    let text = text.trim_matches(|c: char| c == '\0' || c.is_whitespace());
    let nodata = text.parse::<f64>().map_err(|_| InputError::Corrupt {
        path: path.to_path_buf(),
        format: "TIFF",
        message: format!("GDAL_NODATA is {text:?}, not a number"),
    })?;
    Ok((!nodata.is_nan()).then_some(nodata))
}

/// Heights in metres: nodata and non-finite values become `NaN`. `None` when the decoded
/// buffer is not of the sample type the header promised.
fn to_metres(data: DecodingResult, ty: SampleType, nodata: Option<f64>) -> Option<Vec<f64>> {
    fn convert<T: Copy>(v: &[T], f: impl Fn(T) -> f64, nodata: Option<f64>) -> Vec<f64> {
        v.iter()
            .map(|&x| {
                let m = f(x);
                if !m.is_finite() || Some(m) == nodata {
                    f64::NAN
                } else {
                    m
                }
            })
            .collect()
    }
    Some(match (data, ty) {
        (DecodingResult::U8(v), SampleType::U8) => convert(&v, f64::from, nodata),
        (DecodingResult::U16(v), SampleType::U16) => convert(&v, f64::from, nodata),
        (DecodingResult::I16(v), SampleType::I16) => convert(&v, f64::from, nodata),
        (DecodingResult::U32(v), SampleType::U32) => convert(&v, f64::from, nodata),
        (DecodingResult::I32(v), SampleType::I32) => convert(&v, f64::from, nodata),
        (DecodingResult::F32(v), SampleType::F32) => {
            // GDAL writes float32 nodata at double precision: compare in float32.
            let nodata = nodata.map(|n| f64::from(n as f32));
            convert(&v, f64::from, nodata)
        }
        (DecodingResult::F64(v), SampleType::F64) => convert(&v, |x| x, nodata),
        _ => return None,
    })
}

/// The extent from ModelPixelScale + ModelTiepoint, when both are present and sane.
fn georef<R: std::io::Read + std::io::Seek>(
    decoder: &mut Decoder<R>,
    path: &Path,
    width: usize,
    height: usize,
) -> Result<Option<Georef>, InputError> {
    let mut f64_tag = |tag| -> Result<Option<Vec<f64>>, InputError> {
        decoder
            .find_tag(tag)
            .map_err(|e| tiff_error(path, e))?
            .map(|v| v.into_f64_vec().map_err(|e| tiff_error(path, e)))
            .transpose()
    };
    let scale = f64_tag(Tag::ModelPixelScaleTag)?;
    let tiepoint = f64_tag(Tag::ModelTiepointTag)?;
    let doubles = f64_tag(Tag::Unknown(GEO_DOUBLE_PARAMS))?.unwrap_or_default();
    let keys: Vec<u16> = decoder
        .find_tag(Tag::GeoKeyDirectoryTag)
        .map_err(|e| tiff_error(path, e))?
        .map(|v| v.into_u16_vec().map_err(|e| tiff_error(path, e)))
        .transpose()?
        .unwrap_or_default();
    let (Some(scale), Some(tie)) = (scale, tiepoint) else {
        return Ok(None);
    };
    let (&[sx, sy, ..], &[i, j, _, x, y, ..]) = (scale.as_slice(), tie.as_slice()) else {
        tracing::warn!(path = %path.display(), "short ModelPixelScale or ModelTiepoint: no georeference");
        return Ok(None);
    };
    let sane = [sx, sy, i, j, x, y].iter().all(|v| v.is_finite()) && sx > 0.0 && sy > 0.0;
    if !sane {
        tracing::warn!(path = %path.display(), sx, sy, "unusable pixel scale or tiepoint: no georeference");
        return Ok(None);
    }
    let registration = match geokey(&keys, GT_RASTER_TYPE) {
        Some(2) => Registration::Node,
        _ => Registration::Cell,
    };
    // Raster point (i, j) is model point (x, y). Under PixelIsArea raster (0, 0) is the
    // outer corner of the first pixel; under PixelIsPoint it is the first sample.
    let west = x - i * sx;
    let north = y + j * sy;
    let (across, down) = match registration {
        Registration::Cell => (width as f64, height as f64),
        Registration::Node => ((width - 1) as f64, (height - 1) as f64),
    };
    let crs = [PROJECTED_CS_TYPE, GEOGRAPHIC_TYPE]
        .iter()
        .filter_map(|&k| geokey(&keys, k))
        .find(|code| (1..32767).contains(code))
        .map(|code| format!("EPSG:{code}"));
    let projection = Projection::from_geotiff(
        geokey(&keys, GT_MODEL_TYPE),
        geokey(&keys, GEOGRAPHIC_TYPE),
        geokey(&keys, PROJECTED_CS_TYPE),
        geokey(&keys, PROJ_COORD_TRANS),
        double_geokey(&keys, &doubles, PROJ_STD_PARALLEL1),
    );
    Ok(Some(Georef {
        crs,
        west,
        east: west + across * sx,
        north,
        south: north - down * sy,
        registration,
        projection,
    }))
}

/// A double GeoKey's value, stored in GeoDoubleParamsTag at the entry's offset.
fn double_geokey(keys: &[u16], doubles: &[f64], id: u16) -> Option<f64> {
    let count = usize::from(*keys.get(3)?);
    let e = keys
        .get(4..)?
        .chunks_exact(4)
        .take(count)
        .find(|e| e[0] == id && e[1] == GEO_DOUBLE_PARAMS)?;
    doubles.get(usize::from(e[3])).copied()
}

/// A short GeoKey's value stored inline in the GeoKeyDirectory.
fn geokey(keys: &[u16], id: u16) -> Option<u16> {
    let count = usize::from(*keys.get(3)?);
    keys.get(4..)?
        .chunks_exact(4)
        .take(count)
        .find(|e| e[0] == id && e[1] == 0)
        .map(|e| e[3])
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use tiff::encoder::{TiffEncoder, colortype};

    use super::super::read_heights;
    use super::super::test_support::{H, W, assert_close, assert_heights, fixture, jacksboro_m};
    use super::*;

    /// `tests/fixtures/make_fixtures.py` NODATA_I16.
    const HOLES_I16: [(usize, usize); 10] = [
        (0, 0),
        (0, 199),
        (149, 0),
        (149, 199),
        (75, 100),
        (10, 20),
        (10, 21),
        (11, 20),
        (11, 21),
        (140, 3),
    ];
    /// NODATA_F32_SENTINEL + NODATA_F32_NAN.
    const HOLES_F32: [(usize, usize); 6] =
        [(64, 64), (64, 65), (65, 64), (65, 65), (0, 5), (149, 150)];

    #[test]
    fn stripped_int16_geotiff_matches_raw() {
        let r = read_heights(&fixture("jacksboro_stripped_i16.tif")).unwrap();
        assert_eq!(r.format, InputFormat::GeoTiff);
        assert_eq!((r.grid.width, r.grid.height), (W, H));
        assert_eq!(r.grid.quantum_m, Some(1.0));
        assert_eq!(r.nodata_count, HOLES_I16.len());
        assert_heights(&r.grid.values_m, &jacksboro_m(), &HOLES_I16);
        let g = r.georef.unwrap();
        assert_eq!(g.registration, Registration::Cell);
        assert_eq!(g.crs.as_deref(), Some("EPSG:4326"));
        assert_close(g.west, -84.41375);
        assert_close(g.north, 36.73291667);
        assert_close(g.east, -84.41375 + 200.0 / 1200.0);
        assert_close(g.south, 36.73291667 - 150.0 / 1200.0);
    }

    #[test]
    fn tiled_deflate_float32_geotiff_matches_raw() {
        let r = read_heights(&fixture("jacksboro_tiled_f32.tif")).unwrap();
        assert_eq!((r.grid.width, r.grid.height), (W, H));
        assert_eq!(r.grid.quantum_m, None);
        assert_eq!(r.nodata_count, HOLES_F32.len());
        assert_heights(&r.grid.values_m, &jacksboro_m(), &HOLES_F32);
        let g = r.georef.unwrap();
        assert_eq!(g.registration, Registration::Node);
        assert_close(g.west, -84.41375);
        assert_close(g.east, -84.41375 + 199.0 / 1200.0);
        assert_close(g.south, 36.73291667 - 149.0 / 1200.0);
    }

    fn write_tiff(path: &Path, f: impl FnOnce(&mut TiffEncoder<std::fs::File>)) {
        let mut enc = TiffEncoder::new(std::fs::File::create(path).unwrap()).unwrap();
        f(&mut enc);
    }

    #[test]
    fn other_sample_types_read_without_georef() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("t.TIFF");
        write_tiff(&path, |e| {
            e.write_image::<colortype::Gray16>(2, 2, &[0, 1, 65535, 7])
                .unwrap();
        });
        let r = read_heights(&path).unwrap();
        assert_eq!(r.grid.values_m, vec![0.0, 1.0, 65535.0, 7.0]);
        assert_eq!(r.georef, None);

        write_tiff(&path, |e| {
            e.write_image::<colortype::Gray64Float>(2, 1, &[1.25, f64::INFINITY])
                .unwrap();
        });
        let r = read_heights(&path).unwrap();
        assert_eq!(r.grid.values_m[0], 1.25);
        assert!(r.grid.values_m[1].is_nan());
        assert_eq!(r.nodata_count, 1);
        assert_eq!(r.grid.quantum_m, None);

        write_tiff(&path, |e| {
            e.write_image::<colortype::GrayI32>(1, 2, &[-100_000, 100_000])
                .unwrap();
        });
        let r = read_heights(&path).unwrap();
        assert_eq!(r.grid.values_m, vec![-100_000.0, 100_000.0]);
    }

    #[test]
    fn three_band_tiff_is_unsupported() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("rgb.tif");
        write_tiff(&path, |e| {
            e.write_image::<colortype::RGB8>(4, 4, &[9u8; 48]).unwrap();
        });
        let err = read_heights(&path).unwrap_err();
        assert!(matches!(err, InputError::Unsupported { .. }), "{err}");
        assert!(err.to_string().contains("3 bands"), "{err}");
    }

    #[test]
    fn bilevel_and_8bit_colour_tiffs_are_unsupported() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("x.tif");
        write_tiff(&path, |e| {
            e.write_image::<colortype::RGBA8>(2, 2, &[1u8; 16]).unwrap();
        });
        assert!(matches!(
            read_heights(&path),
            Err(InputError::Unsupported { .. })
        ));
        write_tiff(&path, |e| {
            e.write_image::<colortype::GrayI8>(2, 2, &[1, 2, 3, 4])
                .unwrap();
        });
        let err = read_heights(&path).unwrap_err();
        assert!(err.to_string().contains("8-bit signed"), "{err}");
    }

    #[test]
    fn truncated_tiffs_are_errors_never_panics() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("t.tif");
        for name in ["jacksboro_stripped_i16.tif", "jacksboro_tiled_f32.tif"] {
            let bytes = std::fs::read(fixture(name)).unwrap();
            let full = read_heights(&fixture(name)).unwrap().grid.values_m;
            for cut in [0, 1, 4, 8, 9, 100, bytes.len() / 2] {
                std::fs::write(&path, &bytes[..cut]).unwrap();
                let err = read_heights(&path).unwrap_err();
                assert!(
                    matches!(
                        err,
                        InputError::Corrupt { format: "TIFF", .. } | InputError::TooLarge { .. }
                    ),
                    "{name} cut at {cut}: {err}"
                );
            }
            // Anywhere else: an error, or (when only a deflate checksum is cut off)
            // exactly the full image.
            for cut in (0..bytes.len())
                .step_by(331)
                .chain(bytes.len() - 8..bytes.len())
            {
                std::fs::write(&path, &bytes[..cut]).unwrap();
                if let Ok(r) = read_heights(&path) {
                    let same = r
                        .grid
                        .values_m
                        .iter()
                        .zip(&full)
                        .all(|(a, b)| a == b || (a.is_nan() && b.is_nan()));
                    assert!(same, "{name} cut at {cut} read wrong heights");
                }
            }
        }
    }

    #[test]
    fn hostile_header_cannot_ask_for_gigabytes() {
        // A valid uncompressed 1 x 1 image whose header then claims 60000 x 60000.
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("big.tif");
        write_tiff(&path, |e| {
            e.write_image::<colortype::Gray32Float>(1, 1, &[1.0])
                .unwrap();
        });
        let mut bytes = std::fs::read(&path).unwrap();
        let ifd = u32::from_le_bytes(bytes[4..8].try_into().unwrap()) as usize;
        let n = u16::from_le_bytes([bytes[ifd], bytes[ifd + 1]]) as usize;
        for k in 0..n {
            let e = ifd + 2 + 12 * k;
            let tag = u16::from_le_bytes([bytes[e], bytes[e + 1]]);
            if tag == 256 || tag == 257 || tag == 278 {
                // Width, length and rows-per-strip as LONG 60000.
                bytes[e + 2..e + 4].copy_from_slice(&4u16.to_le_bytes());
                bytes[e + 8..e + 12].copy_from_slice(&60000u32.to_le_bytes());
            }
        }
        std::fs::write(&path, &bytes).unwrap();
        let err = read_heights(&path).unwrap_err();
        assert!(matches!(err, InputError::TooLarge { .. }), "{err}");
    }

    #[test]
    fn geokeys_are_read_inline_only() {
        let keys = [1, 1, 0, 2, 1025, 0, 1, 2, 3072, 0, 1, 32633];
        assert_eq!(geokey(&keys, GT_RASTER_TYPE), Some(2));
        assert_eq!(geokey(&keys, PROJECTED_CS_TYPE), Some(32633));
        assert_eq!(geokey(&keys, GEOGRAPHIC_TYPE), None);
        assert_eq!(geokey(&[1, 1, 0, 9, 1025, 0], GT_RASTER_TYPE), None);
        assert_eq!(geokey(&[], GT_RASTER_TYPE), None);
    }
}
