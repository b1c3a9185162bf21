//! SRTM `.hgt` tiles: a square of big-endian `int16` metres, 1201² (SRTM3) or 3601²
//! (SRTM1) told apart by the file's length, `-32768` for voids. The name (`N37E127.hgt`)
//! gives the south-west corner; the tile is node-registered and spans one degree.

use std::path::Path;

use quincunx_codec::encode::Grid;

use super::{
    Georef, HeightRaster, InputError, InputFormat, Registration, file_len, height_raster,
    read_exact_len,
};

/// The void value of SRTM.
const VOID: i16 = -32768;

/// The side of an `.hgt` tile (from its length) and its georeference (from its name),
/// without reading its samples.
pub(super) fn probe(path: &Path) -> Result<(usize, Option<Georef>), InputError> {
    let actual = file_len(path)?;
    let side: usize = match actual {
        2_884_802 => 1201,
        25_934_402 => 3601,
        _ => {
            return Err(InputError::HgtLength {
                path: path.to_path_buf(),
                actual,
            });
        }
    };
    let georef = path
        .file_stem()
        .and_then(|s| s.to_str())
        .and_then(tile_corner)
        .map(|(lat, lon)| Georef {
            crs: Some("EPSG:4326".to_owned()),
            west: f64::from(lon),
            east: f64::from(lon + 1),
            north: f64::from(lat + 1),
            south: f64::from(lat),
            registration: Registration::Node,
            projection: Some(super::Projection::Geographic {
                name: "SRTM .hgt tile (WGS 84 latitude/longitude)".into(),
            }),
        });
    Ok((side, georef))
}

/// Reads an `.hgt` tile.
pub(super) fn read(path: &Path) -> Result<HeightRaster, InputError> {
    let (side, georef) = probe(path)?;
    let bytes = read_exact_len(path, side * side * 2)?;
    let values_m = bytes
        .chunks_exact(2)
        .map(|c| match i16::from_be_bytes([c[0], c[1]]) {
            VOID => f64::NAN,
            h => f64::from(h),
        })
        .collect();
    let grid = Grid {
        width: side,
        height: side,
        values_m,
        quantum_m: Some(1.0),
    };
    if georef.is_none() {
        tracing::warn!(path = %path.display(), "no [NS]dd[EW]ddd tile name: reading without a georeference");
    }
    Ok(height_raster(
        grid,
        "m".to_owned(),
        georef,
        InputFormat::Hgt,
    ))
}

/// The south-west corner `(lat, lon)` in whole degrees from a name starting `N37E127`
/// (any case; anything may follow, as in `N37E127.SRTMGL1`).
fn tile_corner(stem: &str) -> Option<(i32, i32)> {
    let b = stem.as_bytes();
    let digits = |r: std::ops::Range<usize>| -> Option<i32> {
        let s = b.get(r)?;
        s.iter()
            .all(u8::is_ascii_digit)
            .then(|| s.iter().fold(0i32, |acc, d| acc * 10 + i32::from(d - b'0')))
    };
    let lat = match b.first()?.to_ascii_uppercase() {
        b'N' => digits(1..3)?,
        b'S' => -digits(1..3)?,
        _ => return None,
    };
    let lon = match b.get(3)?.to_ascii_uppercase() {
        b'E' => digits(4..7)?,
        b'W' => -digits(4..7)?,
        _ => return None,
    };
    ((-90..90).contains(&lat) && (-180..180).contains(&lon)).then_some((lat, lon))
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use super::super::read_heights;
    use super::super::test_support::{H, W, jacksboro_m};
    use super::*;

    /// The jacksboro crop in the north-west corner of an SRTM3 tile, zeros elsewhere,
    /// voids at two places.
    fn synthetic_tile(dir: &Path, name: &str) -> std::path::PathBuf {
        let heights = jacksboro_m();
        let mut tile = vec![0i16; 1201 * 1201];
        for r in 0..H {
            for c in 0..W {
                tile[r * 1201 + c] = heights[r * W + c] as i16;
            }
        }
        tile[0] = VOID;
        tile[1201 * 1201 - 1] = VOID;
        let bytes: Vec<u8> = tile.iter().flat_map(|v| v.to_be_bytes()).collect();
        let path = dir.join(name);
        std::fs::write(&path, bytes).unwrap();
        path
    }

    #[test]
    fn srtm3_tile_reads_big_endian_with_voids_and_georef() {
        let dir = tempfile::tempdir().unwrap();
        let path = synthetic_tile(dir.path(), "N36W085.hgt");
        let r = read_heights(&path).unwrap();
        assert_eq!(r.format, InputFormat::Hgt);
        assert_eq!((r.grid.width, r.grid.height), (1201, 1201));
        assert_eq!(r.grid.quantum_m, Some(1.0));
        assert_eq!(r.nodata_count, 2);
        let want = jacksboro_m();
        for row in 0..H {
            for col in 0..W {
                let got = r.grid.values_m[row * 1201 + col];
                if row == 0 && col == 0 {
                    assert!(got.is_nan());
                } else {
                    assert_eq!(got, want[row * W + col]);
                }
            }
        }
        assert_eq!(r.grid.values_m[1201 * 1000 + 1000], 0.0);
        let g = r.georef.unwrap();
        assert_eq!(
            (g.west, g.east, g.south, g.north),
            (-85.0, -84.0, 36.0, 37.0)
        );
        assert_eq!(g.registration, Registration::Node);
        assert_eq!(g.crs.as_deref(), Some("EPSG:4326"));
    }

    #[test]
    fn tile_names_give_corners() {
        assert_eq!(tile_corner("N37E127"), Some((37, 127)));
        assert_eq!(tile_corner("s12w077.SRTMGL1"), Some((-12, -77)));
        assert_eq!(tile_corner("N90E000"), None);
        assert_eq!(tile_corner("N3xE127"), None);
        assert_eq!(tile_corner("tile"), None);
        assert_eq!(tile_corner(""), None);
    }

    #[test]
    fn unnamed_tile_has_no_georef() {
        let dir = tempfile::tempdir().unwrap();
        let path = synthetic_tile(dir.path(), "tile.HGT");
        let r = read_heights(&path).unwrap();
        assert_eq!(r.georef, None);
    }

    #[test]
    fn wrong_length_hgt_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("N00E000.hgt");
        std::fs::write(&path, vec![0u8; 2 * 1201 * 1200]).unwrap();
        let err = read_heights(&path).unwrap_err();
        assert!(matches!(
            err,
            InputError::HgtLength {
                actual: 2_882_400,
                ..
            }
        ));
        assert!(err.to_string().contains("2884802"));
    }
}
