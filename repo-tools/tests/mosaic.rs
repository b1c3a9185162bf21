//! `quincunx build <dir | list | pattern>`: tile mosaics. Tiles are cut from the bundled
//! SRTM crop (and, where `../shared/data` is present, the 4097² korea grid cut into the
//! nine real 1201² `.hgt` tiles it was mosaicked from), with the bundled ETOPO20 grid as
//! a coarse global base.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use std::path::{Path, PathBuf};

use common::{bin, crop, write_raw, write_raw_crs};
use quincunx_codec::encode::round;
use quincunx_codec::sphere_raster::{SphereFrame, SphereGeometry};
use quincunx_codec::stream::CubeSource;
use quincunx_repo_tools::input::{self, HeightRaster};
use quincunx_repo_tools::mosaic::Mosaic;
use quincunx_repo_tools::planet::{self, Equirect};

/// 3 arc seconds, the SRTM3 spacing.
const SRTM3: f64 = 1.0 / 1200.0;

fn bundled(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../data")
        .join(name)
}

fn korea() -> HeightRaster {
    input::read_heights(&bundled("korea_srtm3_1025.json")).unwrap()
}

/// The bundled crop as four 513² tiles that share the middle row and column.
fn four_tiles(dir: &Path, k: &HeightRaster, skip_south_east: bool) {
    let g = &k.grid;
    for (name, r, c) in [
        ("nw", 0, 0),
        ("ne", 0, 512),
        ("sw", 512, 0),
        ("se", 512, 512),
    ] {
        if skip_south_east && name == "se" {
            continue;
        }
        let tile = crop(&g.values_m, g.width, r..=r + 512, c..=c + 512, 1);
        write_raw(
            dir,
            name,
            &tile,
            126.0 + c as f64 * SRTM3,
            38.0 - r as f64 * SRTM3,
            SRTM3,
        );
    }
}

fn same_values(a: &[f64], b: &[f64]) -> bool {
    a.len() == b.len()
        && a.iter()
            .zip(b)
            .all(|(x, y)| x == y || (x.is_nan() && y.is_nan()))
}

#[test]
fn planar_tiles_reassemble_the_source_exactly() {
    let k = korea();
    let dir = tempfile::tempdir().unwrap();
    four_tiles(dir.path(), &k, false);
    let (grid, georef, assembled) = Mosaic::open(dir.path()).unwrap().to_grid().unwrap();
    assert_eq!((grid.width, grid.height), (1025, 1025));
    assert!(same_values(&grid.values_m, &k.grid.values_m));
    assert_eq!(assembled.nodata_count, k.nodata_count);
    assert_eq!(grid.quantum_m, Some(1.0));
    let want = k.georef.as_ref().unwrap();
    for (got, want) in [
        (georef.west, want.west),
        (georef.east, want.east),
        (georef.north, want.north),
        (georef.south, want.south),
    ] {
        assert!((got - want).abs() < 1e-9, "extent {got} against {want}");
    }

    // The same tiles through a list file, in the reverse order, and through a pattern.
    let list = dir.path().join("tiles.txt");
    std::fs::write(&list, "# reversed\nse.json\nsw.json\n\nne.json\nnw.json\n").unwrap();
    let (from_list, _, _) = Mosaic::open(&list).unwrap().to_grid().unwrap();
    assert!(same_values(&from_list.values_m, &k.grid.values_m));
    let (from_pattern, _, _) = Mosaic::open(&dir.path().join("*.json"))
        .unwrap()
        .to_grid()
        .unwrap();
    assert!(same_values(&from_pattern.values_m, &k.grid.values_m));

    // Built, the mosaic codes the same blobs as the source it was cut from.
    let summary = |input: &Path, extra: &[&str]| -> serde_json::Value {
        let out = tempfile::tempdir().unwrap();
        let o = bin()
            .args(["build", "--max-error-m", "2", "--json", "-o"])
            .arg(out.path().join("r"))
            .args(extra)
            .arg(input)
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        serde_json::from_slice(&o.stdout).unwrap()
    };
    let mosaic = summary(dir.path(), &[]);
    let single = summary(&bundled("korea_srtm3_1025.json"), &["--sparse"]);
    assert_eq!(mosaic["samples"], 1025 * 1025);
    assert_eq!(mosaic["source_samples"], 4 * 513 * 513);
    for key in ["blob_count", "blob_bytes", "rms", "max_abs"] {
        assert_eq!(mosaic[key], single[key], "{key}");
    }
}

#[test]
fn finer_tiles_win_and_uncovered_areas_are_holes() {
    let k = korea();
    let g = &k.grid;
    let dir = tempfile::tempdir().unwrap();
    four_tiles(dir.path(), &k, true);
    // Without the south-east tile its quarter is a hole (its shared edges excepted).
    let (holed, _, assembled) = Mosaic::open(dir.path()).unwrap().to_grid().unwrap();
    let mut expected_nodata = 0;
    for r in 0..1025 {
        for c in 0..1025 {
            let k = r * 1025 + c;
            if r > 512 && c > 512 {
                assert!(holed.values_m[k].is_nan(), "({r}, {c}) is in the hole");
                expected_nodata += 1;
            } else {
                assert!(same_values(&holed.values_m[k..=k], &g.values_m[k..=k]));
                expected_nodata += usize::from(g.values_m[k].is_nan());
            }
        }
    }
    assert_eq!(assembled.nodata_count, expected_nodata);
    // Built, the hole is left out of the repository: a coverage bitmap and fewer blobs.
    let out = tempfile::tempdir().unwrap();
    let repo = out.path().join("holed");
    common::build(&["--max-error-m", "2"], dir.path(), &repo);
    let info = bin().arg("info").arg(&repo).arg("--json").output().unwrap();
    let info: serde_json::Value = serde_json::from_slice(&info.stdout).unwrap();
    assert!(
        info["metadata"]["coverage"].is_array(),
        "a sparse repository"
    );

    // A coarse tile (every other sample) over the whole crop, first in name order: the
    // finer tiles still win where they are, and the coarse one fills the hole.
    let coarse = crop(&g.values_m, g.width, 0..=1024, 0..=1024, 2);
    write_raw(dir.path(), "a_coarse", &coarse, 126.0, 38.0, 2.0 * SRTM3);
    let (filled, _, _) = Mosaic::open(dir.path()).unwrap().to_grid().unwrap();
    let mut between = 0;
    for r in 0..1025 {
        for c in 0..1025 {
            let k = r * 1025 + c;
            let v = filled.values_m[k];
            if r <= 512 || c <= 512 || (r % 2 == 0 && c % 2 == 0) {
                // A fine tile's sample, or a coarse sample on the fine lattice.
                assert!(same_values(&[v], &g.values_m[k..=k]), "({r}, {c})");
            } else if !v.is_nan() {
                // Between coarse samples: an interpolation of its coarse neighbours.
                let near: Vec<f64> = [
                    (r - 1, c - 1),
                    (r - 1, c + 1),
                    (r + 1, c - 1),
                    (r + 1, c + 1),
                ]
                .iter()
                .flat_map(|&(rr, cc)| [(rr, cc), (rr, c), (r, cc)])
                .filter(|&(rr, cc)| rr % 2 == 0 && cc % 2 == 0 && rr < 1025 && cc < 1025)
                .map(|(rr, cc)| g.values_m[rr * 1025 + cc])
                .filter(|x| x.is_finite())
                .collect();
                let lo = near.iter().copied().fold(f64::INFINITY, f64::min);
                let hi = near.iter().copied().fold(f64::NEG_INFINITY, f64::max);
                assert!(
                    lo - 0.5 <= v && v <= hi + 0.5,
                    "({r}, {c}): {v} not in {lo}..{hi}"
                );
                between += 1;
            }
        }
    }
    assert!(between > 100_000, "{between} interpolated samples");
}

#[test]
fn a_planar_mosaic_streams_out_of_core_with_the_in_memory_values() {
    use quincunx_codec::stream::RowSource;
    let k = korea();
    let g = &k.grid;
    let dir = tempfile::tempdir().unwrap();
    four_tiles(dir.path(), &k, true);
    let coarse = crop(&g.values_m, g.width, 0..=1024, 0..=1024, 2);
    write_raw(dir.path(), "a_coarse", &coarse, 126.0, 38.0, 2.0 * SRTM3);
    let mosaic = Mosaic::open(dir.path()).unwrap();
    let (grid, georef, assembled) = mosaic.to_grid().unwrap();
    // Bands of rows (three passes, the third in other bands) give the same values.
    let (mut rows, streamed_georef) = mosaic.rows().unwrap();
    assert_eq!((rows.width(), rows.height()), (grid.width, grid.height));
    assert_eq!(
        (streamed_georef.west, streamed_georef.north),
        (georef.west, georef.north)
    );
    assert!(rows.held_bytes() > 0);
    for band in [100, 333, 1025] {
        let mut all = Vec::new();
        let mut first = 0;
        while first < rows.height() {
            let count = band.min(rows.height() - first);
            let mut out = vec![0.0; count * rows.width()];
            rows.read_rows(first, count, &mut out).unwrap();
            all.extend(out);
            first += count;
        }
        assert!(same_values(&all, &grid.values_m), "bands of {band} rows");
    }
    let streamed = rows.assembled();
    assert_eq!(streamed.nodata_count, assembled.nodata_count);
    assert_eq!(streamed.quantum_m, assembled.quantum_m);
    assert_eq!(streamed.units, assembled.units);

    // Built out of core within a budget below the in-memory estimate: sparse, bounded, and
    // the same data as the in-memory mosaic build (within the bound, the same blobs but
    // where the hole's border fills differ).
    four_tiles(dir.path(), &k, true);
    std::fs::remove_file(dir.path().join("a_coarse.json")).unwrap();
    let out = tempfile::tempdir().unwrap();
    let build = |name: &str, extra: &[&str]| -> serde_json::Value {
        let o = bin()
            .args(["build", "--max-error-m", "2", "--json", "-o"])
            .arg(out.path().join(name))
            .args(extra)
            .arg(dir.path())
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        serde_json::from_slice(&o.stdout).unwrap()
    };
    let ooc = build("ooc", &["--memory-budget-mb", "24"]);
    let mem = build("mem", &[]);
    println!("mosaic out of core {ooc}\nin memory {mem}");
    assert_eq!(ooc["out_of_core"], true);
    assert!(ooc["peak_rss_mb"].as_f64().unwrap() <= 24.0, "{ooc}");
    assert_eq!(ooc["source_samples"], mem["source_samples"]);
    assert!(ooc["max_abs"].as_f64().unwrap() <= 2.0);
    let (a, b) = (
        ooc["bits_per_sample"].as_f64().unwrap(),
        mem["bits_per_sample"].as_f64().unwrap(),
    );
    assert!(
        (a - b).abs() / b < 0.01,
        "out of core {a} vs in memory {b} bits/sample"
    );
    let info = bin()
        .arg("info")
        .arg(out.path().join("ooc"))
        .arg("--json")
        .output()
        .unwrap();
    let info: serde_json::Value = serde_json::from_slice(&info.stdout).unwrap();
    assert!(
        info["metadata"]["coverage"].is_array(),
        "a sparse repository"
    );
    let v = bin()
        .args(["verify", "--json"])
        .arg(out.path().join("ooc"))
        .output()
        .unwrap();
    assert!(v.status.success(), "{}", String::from_utf8_lossy(&v.stderr));
}

#[test]
fn among_tiles_of_one_spacing_the_first_in_order_wins() {
    let k = korea();
    let g = &k.grid;
    let dir = tempfile::tempdir().unwrap();
    let a = crop(&g.values_m, g.width, 0..=512, 0..=512, 1);
    let b = (a.0, a.1, a.2.iter().map(|v| v + 100.0).collect::<Vec<_>>());
    write_raw(dir.path(), "a", &a, 126.0, 38.0, SRTM3);
    write_raw(dir.path(), "b", &b, 126.0, 38.0, SRTM3);
    let (by_name, _, _) = Mosaic::open(dir.path()).unwrap().to_grid().unwrap();
    assert!(same_values(&by_name.values_m, &a.2), "a.json comes first");
    let list = dir.path().join("order.list");
    std::fs::write(&list, "b.json\na.json\n").unwrap();
    let (listed, _, _) = Mosaic::open(&list).unwrap().to_grid().unwrap();
    // Where `b` has nodata, `a`'s nodata is there too: the same samples.
    assert!(
        same_values(&listed.values_m, &b.2),
        "b.json is listed first"
    );
}

#[test]
fn a_planet_mosaic_takes_each_point_from_its_finest_tile_without_seams() {
    let k = korea();
    let dir = tempfile::tempdir().unwrap();
    four_tiles(dir.path(), &k, false);
    // A copy of a tile over a cube corner (35.26N 45E): the footprint on each of the
    // three faces there must reach the corner.
    let corner = crop(&k.grid.values_m, 1025, 0..=512, 0..=512, 1);
    write_raw(dir.path(), "corner", &corner, 44.8, 35.5, SRTM3);
    let etopo = bundled("etopo20_global.json");
    let list = dir.path().join("planet.txt");
    std::fs::write(
        &list,
        format!(
            "{}\nnw.json\nne.json\nsw.json\nse.json\ncorner.json\n",
            etopo.display()
        ),
    )
    .unwrap();
    let geom = SphereGeometry::new(2048, 32).unwrap();
    let (cube, assembled) = Mosaic::open(&list).unwrap().to_cube(&geom).unwrap();
    assert_eq!(planet::seam_mismatches(&geom, &cube.values_m), 0);

    // The out-of-core build's source: the same cube, band by band of every face, in two
    // passes of different bands, bit for bit (NaN where no tile reaches).
    let mosaic = Mosaic::open(&list).unwrap();
    let mut rows = mosaic
        .cube_rows(&SphereFrame::new(2048, 32, None).unwrap())
        .unwrap();
    let w = 2049;
    for band in [100, 333] {
        let mut buf = vec![0.0; band * w];
        for face in 0..6 {
            for first in (0..w).step_by(band) {
                let count = band.min(w - first);
                rows.read_face_rows(face, first, count, &mut buf[..count * w])
                    .unwrap();
                let want = &cube.values_m[(face * w + first) * w..(face * w + first + count) * w];
                assert!(
                    buf[..count * w]
                        .iter()
                        .zip(want)
                        .all(|(a, b)| a.to_bits() == b.to_bits()),
                    "face {face} rows {first}.. in bands of {band}"
                );
            }
        }
        assert_eq!(rows.assembled().nodata_count, assembled.nodata_count);
    }

    let base = input::read_heights(&etopo).unwrap();
    let (korea_grid, base_grid) = (equirect(&k), equirect(&base));
    let (mut in_korea, mut checked) = (0, 0);
    for face in 0..6u8 {
        for v in 0..=2048 {
            for u in 0..=2048 {
                let (lat, lon) = planet::lat_lon(geom.sample_position(face, u, v));
                let got = cube.values_m[geom.cube_index(face, u, v)];
                let inside = (37.14666..=38.0).contains(&lat) && (126.0..=126.85333).contains(&lon);
                let on_corner = (35.07..=35.5).contains(&lat) && (44.8..=45.23).contains(&lon);
                if on_corner || !inside && (u % 3 != 0 || v % 7 != 0) {
                    continue; // a sample of the rest
                }
                let want = if inside {
                    in_korea += 1;
                    korea_grid.sample(lat, lon)
                } else {
                    base_grid.sample(lat, lon)
                };
                if want.is_finite() {
                    assert_eq!(got, round(want), "face {face} ({u}, {v}) at {lat}, {lon}");
                    checked += 1;
                }
            }
        }
    }
    assert!(
        in_korea > 300 && checked > 1_000_000,
        "{in_korea} / {checked}"
    );
    println!("planet_mosaic: {checked} cube samples checked, {in_korea} in the korea tiles");

    // Korea alone: a sparse planet that is holes but for the tiles.
    let out = tempfile::tempdir().unwrap();
    let repo = out.path().join("korea-planet");
    common::build(
        &["--planet", "--face-side", "4096", "--max-error-m", "2"],
        &dir.path().join("??.json"),
        &repo,
    );
    let o = bin()
        .arg("query")
        .arg(&repo)
        .args(["--at", "37.5,126.5", "--at", "0,0", "--json"])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let answers: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let height = |k: usize| answers[k]["values"][0].as_f64();
    let want = korea_grid.sample(37.5, 126.5);
    let got = height(0).unwrap();
    assert!(
        (got - want).abs() < 30.0,
        "37.5N 126.5E: {got} against {want}"
    );
    assert_eq!(height(1), None, "0N 0E is a hole (null)");
}

fn equirect(r: &HeightRaster) -> Equirect<'_> {
    let g = &r.grid;
    Equirect::new(g.width, g.height, &g.values_m, r.georef.as_ref().unwrap()).unwrap()
}

/// Runs `quincunx build` on `input`, which must fail with a message containing each of
/// `needles` (and no panic).
fn fails(input: &Path, extra: &[&str], needles: &[&str]) {
    let out = tempfile::tempdir().unwrap();
    let o = bin()
        .arg("build")
        .args(extra)
        .arg("-o")
        .arg(out.path().join("r"))
        .arg(input)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(!err.contains("panicked"), "{err}");
    for n in needles {
        assert!(err.contains(n), "{n:?} not in: {err}");
    }
    assert!(!out.path().join("r").exists());
}

#[test]
fn bad_tiles_are_errors_naming_the_file() {
    let k = korea();
    let g = &k.grid;
    let tile = crop(&g.values_m, g.width, 0..=512, 0..=512, 1);
    let fresh = || {
        let dir = tempfile::tempdir().unwrap();
        write_raw(dir.path(), "good", &tile, 126.0, 38.0, SRTM3);
        dir
    };

    let dir = tempfile::tempdir().unwrap();
    fails(dir.path(), &[], &["no tiles"]);

    // Truncated samples.
    let dir = fresh();
    write_raw(dir.path(), "short", &tile, 126.2, 38.0, SRTM3);
    let data = dir.path().join("short.i16");
    let bytes = std::fs::read(&data).unwrap();
    std::fs::write(&data, &bytes[..bytes.len() - 2]).unwrap();
    fails(dir.path(), &[], &["short.i16", "expected 526338 bytes"]);

    // An .hgt of the wrong size, and one whose name gives no georeference.
    let dir = fresh();
    std::fs::write(dir.path().join("N37E126.hgt"), vec![0u8; 1000]).unwrap();
    fails(dir.path(), &[], &["N37E126.hgt", "2884802 bytes"]);
    let dir = fresh();
    std::fs::write(dir.path().join("tile.hgt"), vec![0u8; 2_884_802]).unwrap();
    fails(dir.path(), &[], &["tile.hgt", "no georeference"]);

    // A raw tile without a georeference.
    let dir = fresh();
    write_raw(dir.path(), "nowhere", &tile, 126.0, 38.0, SRTM3);
    let sidecar = dir.path().join("nowhere.json");
    let mut json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(&sidecar).unwrap()).unwrap();
    json.as_object_mut().unwrap().remove("georef");
    std::fs::write(&sidecar, json.to_string()).unwrap();
    fails(dir.path(), &[], &["nowhere.json", "no georeference"]);

    // A planar mosaic of two CRSs; a planet tile that is not latitude/longitude.
    let dir = fresh();
    write_raw_crs(
        dir.path(),
        "utm",
        &tile,
        300_000.0,
        4_200_000.0,
        90.0,
        "EPSG:32652",
    );
    fails(dir.path(), &[], &["utm.json", "differs", "good.json"]);
    fails(
        dir.path(),
        &["--planet"],
        &["utm.json", "not a planet tile"],
    );

    // A list naming a file that is not there; a GeoTIFF cut short after its header.
    let dir = fresh();
    let list = dir.path().join("tiles.txt");
    std::fs::write(&list, "good.json\nmissing.hgt\n").unwrap();
    fails(&list, &[], &["missing.hgt"]);
    let dir = fresh();
    let tif = std::fs::read(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/jacksboro_stripped_i16.tif"),
    )
    .unwrap();
    std::fs::write(dir.path().join("cut.tif"), &tif[..tif.len() / 2]).unwrap();
    fails(dir.path(), &[], &["cut.tif"]);

    // A planet far finer than memory allows is refused before anything is allocated.
    let dir = fresh();
    fails(dir.path(), &["--planet"], &["--face-side", "GB"]);
}

#[test]
fn a_geotiff_tile_reads_like_the_file_itself() {
    let dir = tempfile::tempdir().unwrap();
    let fixture =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/jacksboro_tiled_f32.tif");
    std::fs::copy(&fixture, dir.path().join("jacksboro.tif")).unwrap();
    let want = input::read_heights(&fixture).unwrap();
    let (grid, _, _) = Mosaic::open(dir.path()).unwrap().to_grid().unwrap();
    assert_eq!(
        (grid.width, grid.height),
        (want.grid.width, want.grid.height)
    );
    let worst = grid
        .values_m
        .iter()
        .zip(&want.grid.values_m)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f64::max);
    assert!(worst < 1e-9, "largest difference {worst}");
}

/// The nine whole SRTM3 tiles inside the shared 4097² korea grid (N35-N37, E126-E128),
/// written as real `.hgt` files: the mosaic gives back the grid they came from.
#[test]
fn srtm_hgt_tiles_mosaic_back_into_the_korea_grid() {
    let path =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/korea_srtm3_4097.json");
    if !path.exists() {
        quincunx_testkit::skip::skip(
            "srtm_hgt_tiles",
            "REQUIRE_SHARED_DATA",
            &format!("{} is absent", path.display()),
        );
        return;
    }
    let k = input::read_heights(&path).unwrap();
    let g = &k.grid;
    let dir = tempfile::tempdir().unwrap();
    for lat in 35..=37 {
        for lon in 126..=128 {
            let (r0, c0) = ((37 - lat) * 1200, (lon - 126) * 1200);
            let (_, _, tile) = crop(&g.values_m, g.width, r0..=r0 + 1200, c0..=c0 + 1200, 1);
            let bytes: Vec<u8> = tile
                .iter()
                .flat_map(|&v| (if v.is_nan() { -32768 } else { v as i16 }).to_be_bytes())
                .collect();
            std::fs::write(dir.path().join(format!("N{lat}E{lon}.hgt")), bytes).unwrap();
        }
    }
    let (grid, georef, _) = Mosaic::open(dir.path()).unwrap().to_grid().unwrap();
    let (_, _, want) = crop(&g.values_m, g.width, 0..=3600, 0..=3600, 1);
    assert_eq!((grid.width, grid.height), (3601, 3601));
    assert!(same_values(&grid.values_m, &want));
    assert_eq!(
        [georef.west, georef.east, georef.south, georef.north],
        [126.0, 129.0, 35.0, 38.0]
    );

    // On a planet, over ETOPO5: builds, and the tiles' area reads the SRTM heights.
    assert_eq!(
        Mosaic::open(&dir.path().join("N3*.hgt"))
            .unwrap()
            .tiles
            .len(),
        9
    );
    let etopo5 = path.with_file_name("etopo5_global.json");
    let list = dir.path().join("all.txt");
    let mut names: Vec<String> = (35..=37)
        .flat_map(|lat| (126..=128).map(move |lon| format!("N{lat}E{lon}.hgt")))
        .collect();
    names.push(etopo5.display().to_string());
    std::fs::write(&list, names.join("\n")).unwrap();
    let out = tempfile::tempdir().unwrap();
    let repo = out.path().join("planet");
    common::build(
        &["--planet", "--face-side", "2048", "--max-error-m", "2"],
        &list,
        &repo,
    );
    // Out of core (about 600 MB in memory, 384 MB allowed, 180 MB of it the decoded tiles
    // a band of rows meets): ETOPO5 leaves no nodata
    // inside the coverage, so the repository is the in-memory one.
    let built = |repo: &Path, flags: &[&str]| -> serde_json::Value {
        let o = bin()
            .args([
                "build",
                "--planet",
                "--face-side",
                "2048",
                "--max-error-m",
                "2",
                "--json",
            ])
            .args(flags)
            .arg("-o")
            .arg(repo)
            .arg(&list)
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        serde_json::from_slice(&o.stdout).unwrap()
    };
    let mem = built(&out.path().join("mem"), &[]);
    let ooc = built(&out.path().join("ooc"), &["--memory-budget-mb", "384"]);
    println!("planet mosaic out of core {ooc}\nin memory {mem}");
    assert_eq!(
        (ooc["out_of_core"].as_bool(), mem["out_of_core"].as_bool()),
        (Some(true), Some(false))
    );
    assert!(ooc["peak_rss_mb"].as_f64().unwrap() <= 384.0, "{ooc}");
    let phases: Vec<&str> = ooc["phases"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| p["name"].as_str().unwrap())
        .collect();
    assert_eq!(phases, quincunx_codec::stream::CUBE_PHASES, "{ooc}");
    assert_eq!(ooc["content_hash"], mem["content_hash"]);
    let o = bin()
        .arg("query")
        .arg(&repo)
        .args(["--at", "36.5,127.5", "--json"])
        .output()
        .unwrap();
    let answers: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let got = answers[0]["values"][0].as_f64().unwrap();
    let srtm = Equirect::new(g.width, g.height, &g.values_m, k.georef.as_ref().unwrap())
        .unwrap()
        .sample(36.5, 127.5);
    assert!(
        (got - srtm).abs() < 100.0,
        "36.5N 127.5E: {got} against SRTM {srtm}"
    );
}
