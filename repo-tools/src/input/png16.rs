//! Heights in a greyscale PNG (16- or 8-bit). Samples are metres as they stand unless a
//! sidecar `NAME.json` beside the PNG gives `vertical_scale` / `vertical_offset`
//! (metres = raw * scale + offset), `nodata` (a raw value), `units` and `georef`.

use std::io::BufReader;
use std::path::Path;

use png::{BitDepth, ColorType, Transformations};
use quincunx_codec::encode::Grid;

use super::raw::Sidecar;
use super::{
    HeightRaster, InputError, InputFormat, check_decoded_size, check_dimensions, file_len,
    height_raster, io_error,
};

/// Deflate expands at most about 1032 times; PNG adds one filter byte per row.
pub(super) const PNG_MAX_RATIO: u64 = 1100;

/// A PNG decoding error as an [`InputError`].
pub(super) fn corrupt(path: &Path) -> impl Fn(png::DecodingError) -> InputError + '_ {
    move |e| InputError::Corrupt {
        path: path.to_path_buf(),
        format: "PNG",
        message: e.to_string(),
    }
}

/// An open PNG reader (header read) and the file's size.
pub(super) type PngReader = png::Reader<BufReader<std::fs::File>>;

/// Opens a PNG with the given transformations and reads its header.
pub(super) fn open(
    path: &Path,
    transformations: Transformations,
) -> Result<(PngReader, u64), InputError> {
    let file_bytes = file_len(path)?;
    let file = std::fs::File::open(path).map_err(io_error(path))?;
    let mut decoder = png::Decoder::new(BufReader::new(file));
    decoder.set_transformations(transformations);
    Ok((decoder.read_info().map_err(corrupt(path))?, file_bytes))
}

/// Decodes the first frame into a buffer whose size was checked against the file; returns
/// it and its line size, after checking `height` lines of at least `row_bytes`.
pub(super) fn read_frame(
    path: &Path,
    reader: &mut PngReader,
    file_bytes: u64,
    row_bytes: usize,
    height: usize,
) -> Result<(Vec<u8>, usize), InputError> {
    let buffer_bytes = check_decoded_size(
        path,
        reader.output_buffer_size() as u64,
        file_bytes,
        PNG_MAX_RATIO,
    )?;
    let mut buf = vec![0u8; buffer_bytes];
    let frame = reader.next_frame(&mut buf).map_err(corrupt(path))?;
    if frame.line_size < row_bytes || buf.len() < frame.line_size * height {
        return Err(InputError::Corrupt {
            path: path.to_path_buf(),
            format: "PNG",
            message: "decoded rows are shorter than the header says".to_owned(),
        });
    }
    Ok((buf, frame.line_size))
}

/// Reads a greyscale PNG as heights.
pub(super) fn read(path: &Path) -> Result<HeightRaster, InputError> {
    let (mut reader, file_bytes) = open(path, Transformations::IDENTITY)?;
    let info = reader.info();
    let (width, height) = check_dimensions(path, info.width.into(), info.height.into())?;
    let sample_bytes = match (info.color_type, info.bit_depth) {
        (ColorType::Grayscale, BitDepth::Sixteen) => 2,
        (ColorType::Grayscale, BitDepth::Eight) => 1,
        (ColorType::Grayscale, depth) => {
            return Err(InputError::Unsupported {
                path: path.to_path_buf(),
                format: "PNG",
                message: format!("{}-bit greyscale; heights need 8 or 16 bits", depth as u8),
            });
        }
        (ColorType::GrayscaleAlpha, _) => {
            return Err(InputError::Unsupported {
                path: path.to_path_buf(),
                format: "PNG",
                message: "greyscale with alpha; heights need plain greyscale".to_owned(),
            });
        }
        (ColorType::Rgb | ColorType::Rgba | ColorType::Indexed, _) => {
            return Err(InputError::ColourPng {
                path: path.to_path_buf(),
            });
        }
    };
    let row_bytes = width * sample_bytes;
    let (buf, line_size) = read_frame(path, &mut reader, file_bytes, row_bytes, height)?;

    let sidecar = Sidecar::beside(path)?;
    if let Some(s) = &sidecar {
        s.check_size(width, height)?;
    }
    let (scale, offset, nodata) = sidecar
        .as_ref()
        .map_or((1.0, 0.0, None), |s| (s.scale, s.offset, s.nodata));
    let mut values_m = Vec::with_capacity(width * height);
    for line in buf.chunks_exact(line_size).take(height) {
        let row = &line[..row_bytes];
        let raw = |c: &[u8]| -> f64 {
            if sample_bytes == 2 {
                f64::from(u16::from_be_bytes([c[0], c[1]]))
            } else {
                f64::from(c[0])
            }
        };
        values_m.extend(row.chunks_exact(sample_bytes).map(|c| {
            let v = raw(c);
            if nodata == Some(v) {
                f64::NAN
            } else {
                v * scale + offset
            }
        }));
    }
    let grid = Grid {
        width,
        height,
        values_m,
        quantum_m: Some(scale.abs()),
    };
    let (units, georef) = match sidecar {
        Some(s) => (s.units, s.georef),
        None => ("m".to_owned(), None),
    };
    Ok(height_raster(grid, units, georef, InputFormat::Png16))
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use std::path::PathBuf;

    use super::super::test_support::{H, W, assert_close, assert_heights, fixture, jacksboro_m};
    use super::super::{Registration, read_heights};
    use super::*;

    /// `tests/fixtures/make_fixtures.py` NODATA_PNG.
    const HOLES: [(usize, usize); 5] = [(1, 1), (2, 2), (3, 3), (100, 150), (149, 199)];

    fn write_png(
        path: &Path,
        width: u32,
        height: u32,
        colour: ColorType,
        depth: BitDepth,
        data: &[u8],
    ) {
        let file = std::fs::File::create(path).unwrap();
        let mut enc = png::Encoder::new(std::io::BufWriter::new(file), width, height);
        enc.set_color(colour);
        enc.set_depth(depth);
        enc.write_header().unwrap().write_image_data(data).unwrap();
    }

    #[test]
    fn png16_with_sidecar_matches_raw() {
        let r = read_heights(&fixture("jacksboro_u16.png")).unwrap();
        assert_eq!(r.format, InputFormat::Png16);
        assert_eq!((r.grid.width, r.grid.height), (W, H));
        assert_eq!(r.nodata_count, HOLES.len());
        assert_eq!(r.grid.quantum_m, Some(1.0));
        assert_heights(&r.grid.values_m, &jacksboro_m(), &HOLES);
        let g = r.georef.unwrap();
        assert_eq!(g.registration, Registration::Cell);
        assert_close(g.west, -84.41375);
    }

    #[test]
    fn png_without_sidecar_is_raw_metres() {
        let dir = tempfile::tempdir().unwrap();
        let copy = dir.path().join("alone.PNG");
        std::fs::copy(fixture("jacksboro_u16.png"), &copy).unwrap();
        let r = read_heights(&copy).unwrap();
        assert_eq!(r.nodata_count, 0);
        assert_eq!(r.georef, None);
        let want = jacksboro_m();
        assert_eq!(r.grid.values_m[5], want[5] + 1000.0);
        assert_eq!(r.grid.values_m[W + 1], 0.0);
    }

    #[test]
    fn png8_grey_reads() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("g.png");
        write_png(
            &path,
            3,
            2,
            ColorType::Grayscale,
            BitDepth::Eight,
            &[0, 1, 2, 253, 254, 255],
        );
        let r = read_heights(&path).unwrap();
        assert_eq!(r.grid.values_m, vec![0.0, 1.0, 2.0, 253.0, 254.0, 255.0]);
    }

    #[test]
    fn colour_png_is_not_heights() {
        let dir = tempfile::tempdir().unwrap();
        for (colour, channels) in [(ColorType::Rgb, 3), (ColorType::Rgba, 4)] {
            let path = dir.path().join("c.png");
            write_png(
                &path,
                4,
                4,
                colour,
                BitDepth::Eight,
                &vec![7u8; 16 * channels],
            );
            let err = read_heights(&path).unwrap_err();
            assert!(matches!(err, InputError::ColourPng { .. }));
            assert!(
                err.to_string()
                    .contains("colour PNG: use it as imagery (read_rgb)")
            );
        }
    }

    #[test]
    fn sidecar_with_other_size_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let copy: PathBuf = dir.path().join("p.png");
        std::fs::copy(fixture("jacksboro_u16.png"), &copy).unwrap();
        std::fs::write(
            dir.path().join("p.json"),
            r#"{"width": 201, "height": 150}"#,
        )
        .unwrap();
        let err = read_heights(&copy).unwrap_err();
        assert!(matches!(err, InputError::Sidecar { .. }));
        assert!(err.to_string().contains("201 x 150"), "{err}");
    }

    #[test]
    fn hostile_png_header_cannot_ask_for_gigabytes() {
        // A header promising 60000 x 60000 16-bit samples and no image data.
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("big.png");
        let file = std::fs::File::create(&path).unwrap();
        let mut enc = png::Encoder::new(file, 60000, 60000);
        enc.set_color(ColorType::Grayscale);
        enc.set_depth(BitDepth::Sixteen);
        let mut writer = enc.write_header().unwrap();
        // An empty zlib stream.
        let idat = [0x78, 0x9c, 0x03, 0x00, 0x00, 0x00, 0x00, 0x01];
        writer.write_chunk(png::chunk::IDAT, &idat).unwrap();
        drop(writer);
        let err = read_heights(&path).unwrap_err();
        assert!(matches!(err, InputError::TooLarge { .. }), "{err}");
        assert!(super::super::read_rgb(&path).is_err());
    }

    #[test]
    fn truncated_and_damaged_pngs_are_errors() {
        let dir = tempfile::tempdir().unwrap();
        let bytes = std::fs::read(fixture("jacksboro_u16.png")).unwrap();
        let path = dir.path().join("t.png");
        for cut in (0..bytes.len()).step_by(1013) {
            std::fs::write(&path, &bytes[..cut]).unwrap();
            assert!(read_heights(&path).is_err(), "cut at {cut}");
        }
        let mut damaged = bytes.clone();
        damaged[200] ^= 0x55;
        std::fs::write(&path, &damaged).unwrap();
        assert!(read_heights(&path).is_err());
    }
}
