//! Colour imagery: JPEG (RGB or greyscale) and 8-bit PNG (RGB, RGBA, grey, palette; alpha
//! dropped). The georeference comes from a sidecar `NAME.json` beside the image, read with
//! the same key mapping as the height sidecars; its `width`/`height`, when given, must
//! match the image.

use std::io::BufReader;
use std::path::Path;

use jpeg_decoder::PixelFormat;
use png::{ColorType, Transformations};

use super::raw::Sidecar;
use super::{InputError, RgbImage, check_decoded_size, check_dimensions, file_len, io_error};

/// Baseline JPEG spends at least two bits per 8x8 block and component (about 500x for
/// 4:2:0); progressive EOB runs can do better, so allow 1024x.
const JPEG_MAX_RATIO: u64 = 1024;

/// Reads a JPEG.
pub(super) fn read_jpeg(path: &Path) -> Result<RgbImage, InputError> {
    let corrupt = |e: jpeg_decoder::Error| InputError::Corrupt {
        path: path.to_path_buf(),
        format: "JPEG",
        message: e.to_string(),
    };
    let file_bytes = file_len(path)?;
    let file = std::fs::File::open(path).map_err(io_error(path))?;
    let mut decoder = jpeg_decoder::Decoder::new(BufReader::new(file));
    decoder.read_info().map_err(corrupt)?;
    let info = decoder.info().ok_or_else(|| InputError::Corrupt {
        path: path.to_path_buf(),
        format: "JPEG",
        message: "no frame header".to_owned(),
    })?;
    let (width, height) = check_dimensions(path, info.width.into(), info.height.into())?;
    let channels = match info.pixel_format {
        PixelFormat::RGB24 => 3,
        PixelFormat::L8 => 1,
        PixelFormat::L16 => {
            return Err(unsupported(
                path,
                "JPEG",
                "16-bit greyscale (lossless) JPEG",
            ));
        }
        PixelFormat::CMYK32 => {
            return Err(unsupported(path, "JPEG", "CMYK JPEG; convert it to RGB"));
        }
    };
    let decoded = check_decoded_size(
        path,
        u64::from(info.width) * u64::from(info.height) * channels as u64,
        file_bytes,
        JPEG_MAX_RATIO,
    )?;
    decoder.set_max_decoding_buffer_size(decoded);
    let data = decoder.decode().map_err(corrupt)?;
    if data.len() != width * height * channels {
        return Err(InputError::Corrupt {
            path: path.to_path_buf(),
            format: "JPEG",
            message: format!(
                "decoded {} bytes for {width} x {height} x {channels}",
                data.len()
            ),
        });
    }
    let pixels = if channels == 3 {
        data.chunks_exact(3).map(|p| [p[0], p[1], p[2]]).collect()
    } else {
        data.iter().map(|&g| [g, g, g]).collect()
    };
    finish(path, width, height, pixels)
}

/// Reads an 8-bit (or 16-bit, stripped to 8) colour or grey PNG.
pub(super) fn read_png(path: &Path) -> Result<RgbImage, InputError> {
    let (mut reader, file_bytes) =
        super::png16::open(path, Transformations::EXPAND | Transformations::STRIP_16)?;
    let info = reader.info();
    let (width, height) = check_dimensions(path, info.width.into(), info.height.into())?;
    let (colour, _) = reader.output_color_type();
    let channels = match colour {
        ColorType::Grayscale => 1,
        ColorType::GrayscaleAlpha => 2,
        ColorType::Rgb => 3,
        ColorType::Rgba => 4,
        ColorType::Indexed => {
            return Err(unsupported(path, "PNG", "palette not expanded"));
        }
    };
    let row_bytes = width * channels;
    let (buf, line_size) =
        super::png16::read_frame(path, &mut reader, file_bytes, row_bytes, height)?;
    let mut pixels = Vec::with_capacity(width * height);
    for line in buf.chunks_exact(line_size).take(height) {
        pixels.extend(line[..row_bytes].chunks_exact(channels).map(|p| {
            if channels < 3 {
                [p[0], p[0], p[0]]
            } else {
                [p[0], p[1], p[2]]
            }
        }));
    }
    finish(path, width, height, pixels)
}

fn finish(
    path: &Path,
    width: usize,
    height: usize,
    pixels: Vec<[u8; 3]>,
) -> Result<RgbImage, InputError> {
    let sidecar = Sidecar::beside(path)?;
    if let Some(s) = &sidecar {
        s.check_size(width, height)?;
    }
    Ok(RgbImage {
        width,
        height,
        pixels,
        georef: sidecar.and_then(|s| s.georef),
    })
}

fn unsupported(path: &Path, format: &'static str, message: &str) -> InputError {
    InputError::Unsupported {
        path: path.to_path_buf(),
        format,
        message: message.to_owned(),
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use png::BitDepth;

    use super::super::test_support::fixture;
    use super::super::{Registration, read_rgb};
    use super::*;

    fn write_png(path: &Path, w: u32, h: u32, colour: ColorType, data: &[u8]) {
        let file = std::fs::File::create(path).unwrap();
        let mut enc = png::Encoder::new(std::io::BufWriter::new(file), w, h);
        enc.set_color(colour);
        enc.set_depth(BitDepth::Eight);
        enc.write_header().unwrap().write_image_data(data).unwrap();
    }

    #[test]
    fn gsi_jpeg_reads_without_georef() {
        let img = read_rgb(&fixture("gsi_color_256.jpg")).unwrap();
        assert_eq!((img.width, img.height), (256, 256));
        assert_eq!(img.pixels.len(), 256 * 256);
        // Its sidecar's georef is a note ("same tile as ..."), not an extent.
        assert_eq!(img.georef, None);
        // An orthophoto is not one flat colour.
        assert!(img.pixels.iter().any(|p| p != &img.pixels[0]));
    }

    #[test]
    fn jpeg_sidecar_georef_like_bmng_is_parsed() {
        let dir = tempfile::tempdir().unwrap();
        let jpg = dir.path().join("world.JPEG");
        std::fs::copy(fixture("gsi_color_256.jpg"), &jpg).unwrap();
        let meta = r#"{"width": 256, "height": 256, "format": "JPEG", "mode": "RGB",
            "georef": {"projection": "equirectangular (plate carree)", "west": -180,
            "east": 180, "north": 90, "south": -90,
            "registration": "pixel-is-area: pixel (r, c) centre at ...", "planet": "Earth"}}"#;
        std::fs::write(dir.path().join("world.json"), meta).unwrap();
        let g = read_rgb(&jpg).unwrap().georef.unwrap();
        assert_eq!(
            (g.west, g.east, g.north, g.south),
            (-180.0, 180.0, 90.0, -90.0)
        );
        assert_eq!(g.registration, Registration::Cell);
        assert_eq!(g.crs.as_deref(), Some("equirectangular (plate carree)"));

        std::fs::write(
            dir.path().join("world.json"),
            r#"{"width": 512, "height": 256}"#,
        )
        .unwrap();
        assert!(matches!(read_rgb(&jpg), Err(InputError::Sidecar { .. })));
    }

    #[test]
    fn truncated_jpeg_is_an_error() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("t.jpg");
        let bytes = std::fs::read(fixture("gsi_color_256.jpg")).unwrap();
        for cut in [0, 2, 100, 600, bytes.len() / 2] {
            std::fs::write(&path, &bytes[..cut]).unwrap();
            let err = read_rgb(&path).unwrap_err();
            assert!(
                matches!(err, InputError::Corrupt { format: "JPEG", .. }),
                "{cut}: {err}"
            );
        }
        // Every other cut must fail or succeed without panicking.
        for cut in (0..bytes.len()).step_by(101) {
            std::fs::write(&path, &bytes[..cut]).unwrap();
            let _ = read_rgb(&path);
        }
    }

    #[test]
    fn png_rgba_grey_and_palette_read_as_rgb() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("i.png");
        write_png(&path, 2, 1, ColorType::Rgba, &[1, 2, 3, 255, 4, 5, 6, 0]);
        let img = read_rgb(&path).unwrap();
        assert_eq!(img.pixels, vec![[1, 2, 3], [4, 5, 6]]);
        write_png(&path, 2, 1, ColorType::Grayscale, &[9, 200]);
        assert_eq!(
            read_rgb(&path).unwrap().pixels,
            vec![[9, 9, 9], [200, 200, 200]]
        );

        let file = std::fs::File::create(&path).unwrap();
        let mut enc = png::Encoder::new(std::io::BufWriter::new(file), 2, 1);
        enc.set_color(ColorType::Indexed);
        enc.set_depth(BitDepth::Eight);
        enc.set_palette(vec![10, 20, 30, 40, 50, 60]);
        enc.write_header()
            .unwrap()
            .write_image_data(&[1, 0])
            .unwrap();
        assert_eq!(
            read_rgb(&path).unwrap().pixels,
            vec![[40, 50, 60], [10, 20, 30]]
        );
    }

    #[test]
    fn unknown_imagery_extension_is_refused() {
        let err = read_rgb(Path::new("photo.gif")).unwrap_err();
        assert!(matches!(err, InputError::UnknownExtension { .. }));
    }
}
