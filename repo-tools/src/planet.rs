//! Planets: global latitude/longitude grids resampled onto the cube-mapped sphere, and
//! point queries back.
//!
//! Axes: `+Z` is the north pole, `+X` is (0°N, 0°E), `+Y` is (0°N, 90°E). A cube-raster
//! sample is the exact integer cube point of the codec's sphere domain, mapped to the
//! sphere with the codec's equal-angle map (`cube_to_unit_sphere`, area ratio 1.414 over
//! a face). Every copy of a cube edge or corner point is the same integer point, so it
//! gets the same latitude/longitude and the same resampled value: the resampled grid has
//! no seams to begin with. The poles are the centres of the `+Z`/`-Z` faces (no
//! singularity), and the antimeridian is an ordinary line: longitudes wrap when the
//! source spans 360°.

use anyhow::{Context, Result, bail};
use quincunx_codec::colour::rgb_to_ycocg_r;
use quincunx_codec::diamond::sphere::{cube_to_unit_sphere, unit_sphere_to_cube};
use quincunx_codec::encode::{CubeGrid, round};
use quincunx_codec::sphere_raster::{SphereFrame, SphereGeometry};
use quincunx_codec::stream::{CubeSource, IoError};
use rayon::prelude::*;

use crate::input::{Georef, HeightRaster, Projection, Registration, RgbImage};

/// Radius of a named body, metres.
pub fn body_radius_m(body: &str) -> Option<f64> {
    match body.to_ascii_lowercase().as_str() {
        "earth" => Some(6_371_000.0),
        "mars" => Some(3_396_000.0),
        "moon" => Some(1_737_400.0),
        "venus" => Some(6_051_800.0),
        "mercury" => Some(2_439_700.0),
        _ => None,
    }
}

/// Latitude and longitude (degrees) of a point on (or off) the cube.
pub fn lat_lon(p: [i64; 3]) -> (f64, f64) {
    degrees(cube_to_unit_sphere([p[0] as f64, p[1] as f64, p[2] as f64]))
}

/// Latitude and longitude (degrees) of a unit vector.
fn degrees(q: [f64; 3]) -> (f64, f64) {
    (lat_of_sine(q[2]), lon_of(q))
}

/// Latitude (degrees) whose sine is `z`.
#[inline(always)]
fn lat_of_sine(z: f64) -> f64 {
    z.clamp(-1.0, 1.0).asin().to_degrees()
}

/// The face and fractional chart coordinates `(u, v)` in `[0, face_side]` of a
/// latitude/longitude (degrees).
pub fn face_chart(lat: f64, lon: f64, face_side: usize) -> (u8, f64, f64) {
    let (lat, lon) = (lat.to_radians(), lon.to_radians());
    let q = [lat.cos() * lon.cos(), lat.cos() * lon.sin(), lat.sin()];
    let c = unit_sphere_to_cube(q);
    let axis = (0..3)
        .max_by(|&a, &b| c[a].abs().total_cmp(&c[b].abs()))
        .unwrap_or(2);
    let face = (2 * axis + usize::from(c[axis] < 0.0)) as u8;
    let (x, y, z) = (c[0], c[1], c[2]);
    let (u, v) = match face {
        0 => (y, z),
        1 => (z, y),
        2 => (z, x),
        3 => (x, z),
        4 => (x, y),
        _ => (y, x),
    };
    let half = face_side as f64 / 2.0;
    (face, (u + 1.0) * half, (v + 1.0) * half)
}

/// A global latitude/longitude grid ready to be sampled anywhere.
pub struct Equirect<'a> {
    width: usize,
    height: usize,
    lon0: f64,
    dlon: f64,
    lat0: f64,
    dlat: f64,
    wraps: bool,
    values: &'a [f64],
}

impl<'a> Equirect<'a> {
    /// Describes `values` (`width x height`, row 0 north) placed by `georef` (degrees).
    pub fn new(width: usize, height: usize, values: &'a [f64], georef: &Georef) -> Result<Self> {
        let projection = georef.projection();
        if let Some(p) = &projection
            && !p.is_lat_lon_grid()
        {
            bail!(
                "planet builds need a latitude/longitude grid; the source's CRS is {p}. \
                 Accepted: {}",
                crate::input::projection::ACCEPTED
            );
        }
        if georef.west < -180.5
            || georef.east > 360.5
            || georef.north > 90.0
            || georef.south < -90.0
        {
            bail!(
                "the georeference ({}..{} E, {}..{} N) is not in degrees of latitude/longitude{}",
                georef.west,
                georef.east,
                georef.south,
                georef.north,
                match projection {
                    Some(Projection::Equirectangular { .. }) =>
                        " (an equirectangular grid's extent must be given in degrees, not metres)",
                    _ => "",
                }
            );
        }
        if width < 2 || height < 2 {
            bail!("a planet source needs at least 2 x 2 samples");
        }
        let (lon0, dlon, lat0, dlat) = match georef.registration {
            Registration::Node => (
                georef.west,
                (georef.east - georef.west) / (width - 1) as f64,
                georef.north,
                (georef.north - georef.south) / (height - 1) as f64,
            ),
            Registration::Cell => {
                let dlon = (georef.east - georef.west) / width as f64;
                let dlat = (georef.north - georef.south) / height as f64;
                (
                    georef.west + dlon / 2.0,
                    dlon,
                    georef.north - dlat / 2.0,
                    dlat,
                )
            }
        };
        let wraps = (width as f64 * dlon - 360.0).abs() < dlon * 0.01;
        Ok(Equirect {
            width,
            height,
            lon0,
            dlon,
            lat0,
            dlat,
            wraps,
            values,
        })
    }

    /// Source spacing in degrees (east-west).
    pub fn spacing_deg(&self) -> f64 {
        self.dlon
    }

    /// The four source samples around a latitude/longitude and the weights between them;
    /// `None` outside a source that does not wrap around the globe.
    fn locate(&self, lat: f64, lon: f64) -> Option<Bilinear> {
        let row = ((self.lat0 - lat) / self.dlat).clamp(0.0, (self.height - 1) as f64);
        let mut east = lon - self.lon0;
        if !(0.0..360.0).contains(&east) {
            east = east.rem_euclid(360.0); // (an fmod call: only when needed)
        }
        let mut col = east / self.dlon;
        if !self.wraps {
            let raw = (lon - self.lon0) / self.dlon;
            let alt = (lon + 360.0 - self.lon0) / self.dlon;
            col = if (0.0..=(self.width - 1) as f64).contains(&raw) {
                raw
            } else if (0.0..=(self.width - 1) as f64).contains(&alt) {
                alt
            } else {
                return None;
            };
        }
        // Both are finite and non-negative: truncation is `floor`, without a libm call.
        let (r0, c0) = (row as usize, col as usize);
        let (fr, fc) = (row - r0 as f64, col - c0 as f64);
        let r1 = (r0 + 1).min(self.height - 1);
        // `col` is below `width` but for rounding at 360 degrees: no division per sample.
        let c0 = if c0 < self.width { c0 } else { c0 % self.width };
        let c1 = if c0 + 1 < self.width {
            c0 + 1
        } else if self.wraps {
            0
        } else {
            c0
        };
        let (w0, w1) = (r0 * self.width, r1 * self.width);
        Some(Bilinear {
            at: [w0 + c0, w0 + c1, w1 + c0, w1 + c1],
            fr,
            fc,
            row,
            col,
        })
    }

    /// Bilinear sample at a latitude/longitude; nodata (`NaN`) neighbours are left out,
    /// `NaN` outside the grid or when all four are nodata.
    pub fn sample(&self, lat: f64, lon: f64) -> f64 {
        let Some(b) = self.locate(lat, lon) else {
            return f64::NAN;
        };
        let v = b.at.map(|k| self.values[k]);
        if v.iter().all(|x| x.is_finite()) {
            // The common case: no nodata neighbour.
            return b.mix(v);
        }
        let (fr, fc) = (b.fr, b.fc);
        let weights = [
            (1.0 - fr) * (1.0 - fc),
            (1.0 - fr) * fc,
            fr * (1.0 - fc),
            fr * fc,
        ];
        let mut sum = 0.0;
        let mut weight = 0.0;
        for (x, w) in v.into_iter().zip(weights) {
            if x.is_finite() && w > 0.0 {
                sum += x * w;
                weight += w;
            }
        }
        if weight > 0.0 {
            sum / weight
        } else {
            // Exactly on a nodata sample with zero-weight neighbours: nearest.
            let v = self.values[b.nearest(self.width)];
            if v.is_finite() { v } else { f64::NAN }
        }
    }

    /// Resamples onto the cube raster of `geom` (values rounded to `quantum` when given).
    pub fn to_cube(&self, geom: &SphereGeometry, quantum: Option<f64>) -> Vec<f64> {
        let mut out = vec![f64::NAN; geom.cube_len()];
        for_each_cube_sample(geom, &mut out, |lat, lon| {
            self.cube_sample(lat, lon, quantum)
        });
        out
    }

    /// One cube sample: bilinear, rounded to `quantum` when given.
    fn cube_sample(&self, lat: f64, lon: f64, quantum: Option<f64>) -> f64 {
        let s = self.sample(lat, lon);
        match quantum {
            Some(q) if s.is_finite() => round(s / q) * q,
            _ => s,
        }
    }
}

/// A global grid resampled onto a cube a band of face rows at a time (the out-of-core
/// planet build's source): the values [`Equirect::to_cube`] gives, bit for bit.
pub struct EquirectRows<'a> {
    grid: Equirect<'a>,
    angles: CubeAngles,
    face_side: usize,
    quantum: Option<f64>,
}

impl<'a> EquirectRows<'a> {
    /// The rows of `raster` on the cube of `frame`.
    pub fn new(raster: &'a HeightRaster, frame: &SphereFrame) -> Result<Self> {
        let g = &raster.grid;
        let georef = raster
            .georef
            .as_ref()
            .context("planet builds need a georeferenced latitude/longitude grid")?;
        Ok(EquirectRows {
            grid: Equirect::new(g.width, g.height, &g.values_m, georef)?,
            angles: CubeAngles::new(frame),
            face_side: frame.face_side(),
            quantum: g.quantum_m,
        })
    }
}

/// Checks a [`CubeSource`] read: `count > 0` rows from `first` of face `face` of a planet of
/// `face_side`, into `out_len` values (exactly those rows').
pub(crate) fn check_band(
    face_side: usize,
    face: usize,
    (first, count): (usize, usize),
    out_len: usize,
) -> Result<(), String> {
    let w = face_side + 1;
    if face >= 6 || count == 0 || first + count > w || out_len != count * w {
        return Err(format!(
            "rows {first}..{} of face {face} into {out_len} values: outside a cube of face side {face_side}",
            first + count
        ));
    }
    Ok(())
}

impl CubeSource for EquirectRows<'_> {
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
        check_band(self.face_side, face, (first, count), out.len())?;
        self.angles.map_rows(face, first, out, |lat, lon| {
            self.grid.cube_sample(lat, lon, self.quantum)
        });
        Ok(())
    }

    fn quantum_m(&self) -> Option<f64> {
        self.quantum
    }
}

/// Where a latitude/longitude falls in a source grid: the indices of the four samples
/// around it (NW, NE, SW, SE), the fractions south and east, and the fractional row and
/// column (for the nearest sample, needed only where nodata leaves no weight).
struct Bilinear {
    at: [usize; 4],
    fr: f64,
    fc: f64,
    row: f64,
    col: f64,
}

impl Bilinear {
    /// Index of the source sample nearest to the point (in a grid `width` wide). Two
    /// libm `round` calls and a division: off the common path.
    fn nearest(&self, width: usize) -> usize {
        self.row.round() as usize * width + (self.col.round() as usize % width)
    }

    /// The bilinear mix of the four samples' values.
    #[inline]
    fn mix(&self, v: [f64; 4]) -> f64 {
        bilinear(v, self.fr, self.fc)
    }
}

/// The bilinear mix of four values (NW, NE, SW, SE) at fractions `fr` south and `fc` east:
/// the arithmetic every resampling onto the cube uses, so that a mosaic tile and a single
/// grid give a point the same value bit for bit.
#[inline]
pub(crate) fn bilinear([a, b, c, d]: [f64; 4], fr: f64, fc: f64) -> f64 {
    let top = a * (1.0 - fc) + b * fc;
    let bottom = c * (1.0 - fc) + d * fc;
    top * (1.0 - fr) + bottom * fr
}

/// Latitude and longitude of the sample points of one cube raster, with the equal-angle
/// map's tangents tabulated per coordinate: every sample point has one coordinate at
/// `+-S` and two integers in `-S..=S`, so `2S + 1` tangents serve all `6 (2S+1)^2`
/// samples (the tangent was 9 % of a planet build). The longitude needs no normalised
/// vector (`atan2` of the cube point), and on the four equatorial faces it is one value
/// per column or per row. Every copy of an edge or corner point is the same vector, so
/// it gets the same angles; they equal [`lat_lon`] to 1e-12 degrees (tested).
pub(crate) struct CubeAngles {
    tans: Vec<f64>,
    frames: Vec<FaceFrame>,
    /// Per face whose `v` is the z axis: the longitude of each column.
    column_lons: Vec<Option<Vec<f64>>>,
}

/// How a face's chart coordinates map to cube axes: `q[a] = s`, `q[b]` from `u`, `q[c]`
/// from `v` (read off [`SphereFrame::sample_position`]).
///
/// [`SphereFrame::sample_position`]: quincunx_codec::sphere_raster::SphereFrame::sample_position
#[derive(Clone, Copy)]
struct FaceFrame {
    a: usize,
    s: f64,
    b: usize,
    c: usize,
}

impl FaceFrame {
    fn of(geom: &SphereFrame, face: u8) -> Self {
        let o = geom.sample_position(face, 0, 0);
        let du = geom.sample_position(face, 1, 0);
        let dv = geom.sample_position(face, 0, 1);
        let b = (0..3).find(|&k| du[k] != o[k]).unwrap_or(0);
        let c = (0..3).find(|&k| dv[k] != o[k]).unwrap_or(1);
        let a = 3 - b - c;
        FaceFrame {
            a,
            s: o[a].signum() as f64,
            b,
            c,
        }
    }
}

impl CubeAngles {
    pub(crate) fn new(geom: &SphereFrame) -> Self {
        let half = (geom.face_side() / 2) as i64;
        let big = half as f64;
        // The expression of `cube_to_unit_sphere`, made odd by construction (the mirrored
        // half of each row reuses the other half's latitudes, see `row`).
        let positive: Vec<f64> = (0..=half)
            .map(|k| {
                if k == half {
                    1.0
                } else {
                    (std::f64::consts::FRAC_PI_4 * (k as f64 / big)).tan()
                }
            })
            .collect();
        let tans = (-half..=half)
            .map(|k| {
                let t = positive[k.unsigned_abs() as usize];
                if k < 0 { -t } else { t }
            })
            .collect();
        let mut angles = CubeAngles {
            tans,
            frames: (0..6).map(|face| FaceFrame::of(geom, face)).collect(),
            column_lons: Vec::new(),
        };
        angles.column_lons = angles
            .frames
            .iter()
            .map(|&f| {
                (f.c == 2).then(|| {
                    (0..=geom.face_side())
                        .map(|u| lon_of(angles.vector(f, u, 0)))
                        .collect()
                })
            })
            .collect();
        angles
    }

    /// The unnormalised direction of face sample `(u, v)`.
    #[inline(always)]
    fn vector(&self, f: FaceFrame, u: usize, v: usize) -> [f64; 3] {
        let mut q = [0.0; 3];
        q[f.a] = f.s;
        q[f.b] = self.tans[u];
        q[f.c] = self.tans[v];
        q
    }

    /// `out[k] = f(lat, lon)` over face `face`'s whole rows from `first` (`out`'s length
    /// a multiple of the row length), rows in parallel.
    pub(crate) fn map_rows<T: Send>(
        &self,
        face: usize,
        first: usize,
        out: &mut [T],
        f: impl Fn(f64, f64) -> T + Sync,
    ) {
        let w = self.tans.len();
        out.par_chunks_mut(w).enumerate().for_each_init(
            || vec![(0.0, 0.0); w],
            |angles, (r, dst)| {
                self.row(face, first + r, angles);
                for (x, &(lat, lon)) in dst.iter_mut().zip(angles.iter()) {
                    *x = f(lat, lon);
                }
            },
        );
    }

    /// Latitude and longitude (degrees) of row `v` of face `face`, into `out`.
    pub(crate) fn row(&self, face: usize, v: usize, out: &mut [(f64, f64)]) {
        let f = self.frames[face];
        // Equatorial faces: the longitude is constant along a column (`v` is the
        // z axis) or along this row (`u` is).
        let row_lon = (f.b == 2).then(|| lon_of(self.vector(f, 0, v)));
        let columns = self.column_lons[face].as_deref();
        // Mirroring `u` about the face centre negates the tangent along `u`: the norm
        // stays bit for bit, and the latitude too, or changes sign where `u` is the z
        // axis (`asin` is odd). So the second half of the row reuses the first's.
        let last = out.len() - 1;
        let mirror_sign = if f.b == 2 { -1.0 } else { 1.0 };
        for u in 0..out.len() {
            let q = self.vector(f, u, v);
            let lat = if 2 * u > last {
                mirror_sign * out[last - u].0
            } else {
                let norm = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2]).sqrt();
                lat_of_sine(q[2] / norm)
            };
            let lon = match (row_lon, columns) {
                (Some(l), _) => l,
                (None, Some(c)) => c[u],
                (None, None) => lon_of(q),
            };
            out[u] = (lat, lon);
        }
    }

    /// Latitude and longitude of samples `u0 .. u0 + out.len()` of row `v` of face `face`,
    /// into `out`: the angles [`CubeAngles::row`] gives them, bit for bit, without
    /// computing the rest of the row (a tile's footprint is a small part of it).
    pub(crate) fn row_span(&self, face: usize, v: usize, u0: usize, out: &mut [(f64, f64)]) {
        let f = self.frames[face];
        let row_lon = (f.b == 2).then(|| lon_of(self.vector(f, 0, v)));
        let columns = self.column_lons[face].as_deref();
        for (k, o) in out.iter_mut().enumerate() {
            let u = u0 + k;
            let q = self.vector(f, u, v);
            let norm = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2]).sqrt();
            let lon = match (row_lon, columns) {
                (Some(l), _) => l,
                (None, Some(c)) => c[u],
                (None, None) => lon_of(q),
            };
            *o = (lat_of_sine(q[2] / norm), lon);
        }
    }
}

/// Longitude (degrees) of a cube point (any length: `atan2` needs no normalised vector).
#[inline(always)]
fn lon_of(q: [f64; 3]) -> f64 {
    q[1].atan2(q[0]).to_degrees()
}

/// Fills every sample of the cube raster of `geom` with `f(lat, lon)`, rows in parallel.
fn for_each_cube_sample<T: Send>(
    geom: &SphereGeometry,
    out: &mut [T],
    f: impl Fn(f64, f64) -> T + Sync,
) {
    let side = geom.face_side() + 1;
    let angles = CubeAngles::new(geom);
    for (face, rows) in out.chunks_mut(side * side).enumerate() {
        angles.map_rows(face, 0, rows, &f);
    }
}

/// Resamples a global height grid onto the cube raster of `geom` (values rounded to the
/// source quantum, so integer sources stay integer and lossless coding stays meaningful).
pub fn resample_heights(raster: &HeightRaster, geom: &SphereGeometry) -> Result<CubeGrid> {
    let g = &raster.grid;
    let georef = raster
        .georef
        .as_ref()
        .context("planet builds need a georeferenced latitude/longitude grid")?;
    let e = Equirect::new(g.width, g.height, &g.values_m, georef)?;
    Ok(CubeGrid {
        face_side: geom.face_side(),
        values_m: e.to_cube(geom, g.quantum_m),
        quantum_m: g.quantum_m,
    })
}

/// Resamples global RGB imagery onto the cube raster of `geom` (bilinear per channel,
/// rounded to 8 bits), all three channels in one pass over the cube.
pub fn resample_rgb(image: &RgbImage, geom: &SphereGeometry) -> Result<Vec<[u8; 3]>> {
    // One lookup of the four neighbours for all three channels, straight from the
    // interleaved pixels (no per-channel copy of the image).
    let e = rgb_equirect(image)?;
    let mut cube = vec![[0u8; 3]; geom.cube_len()];
    for_each_cube_sample(geom, &mut cube, |lat, lon| rgb_at(&e, image, lat, lon));
    Ok(cube)
}

fn rgb_equirect(image: &RgbImage) -> Result<Equirect<'static>> {
    let georef = image
        .georef
        .as_ref()
        .context("planet builds need georeferenced imagery (a sidecar with `georef`)")?;
    Equirect::new(image.width, image.height, &[], georef)
}

/// The image's colour at a latitude/longitude (black outside its extent).
fn rgb_at(e: &Equirect<'_>, image: &RgbImage, lat: f64, lon: f64) -> [u8; 3] {
    let Some(b) = e.locate(lat, lon) else {
        return [0; 3];
    };
    let p = b.at.map(|k| image.pixels[k]);
    std::array::from_fn(|c| {
        let v = b.mix(p.map(|px| f64::from(px[c])));
        round(v).clamp(0.0, 255.0) as u8
    })
}

/// An RGB image resampled onto a cube a band of face rows at a time (the out-of-core
/// colour planet build's source): the pixels [`resample_rgb`] gives, bit for bit. As a
/// [`CubeSource`] it reads one YCoCg-R channel (`channel`: 0 Y, 1 Co, 2 Cg).
pub struct EquirectRgbRows<'a> {
    image: &'a RgbImage,
    grid: Equirect<'static>,
    angles: CubeAngles,
    face_side: usize,
    /// The channel read as a [`CubeSource`].
    pub channel: usize,
}

impl<'a> EquirectRgbRows<'a> {
    /// The rows of `image` on the cube of `frame`.
    pub fn new(image: &'a RgbImage, frame: &SphereFrame) -> Result<Self> {
        Ok(EquirectRgbRows {
            image,
            grid: rgb_equirect(image)?,
            angles: CubeAngles::new(frame),
            face_side: frame.face_side(),
            channel: 0,
        })
    }

    /// Face `face`'s rows `first .. first + count` of pixels, every copy of every point.
    pub fn rgb_rows(
        &self,
        face: usize,
        (first, count): (usize, usize),
        out: &mut [[u8; 3]],
    ) -> Result<(), String> {
        check_band(self.face_side, face, (first, count), out.len())?;
        self.angles.map_rows(face, first, out, |lat, lon| {
            rgb_at(&self.grid, self.image, lat, lon)
        });
        Ok(())
    }
}

impl CubeSource for EquirectRgbRows<'_> {
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
        let mut rgb = vec![[0u8; 3]; out.len()];
        self.rgb_rows(face, (first, count), &mut rgb)?;
        let c = self.channel;
        out.par_iter_mut().zip(&rgb).for_each(|(x, &[r, g, b])| {
            let (y, co, cg) = rgb_to_ycocg_r(i32::from(r), i32::from(g), i32::from(b));
            *x = f64::from([y, co, cg][c]);
        });
        Ok(())
    }

    fn quantum_m(&self) -> Option<f64> {
        Some(1.0)
    }
}

/// The default face side for a source of `spacing_deg`: the power-of-two multiple of `n`
/// closest (in ratio) to the source's samples per 90°.
pub fn default_face_side(spacing_deg: f64, n: usize) -> usize {
    let want = (90.0 / spacing_deg).max(n as f64);
    let mut side = n;
    while (side * 2) as f64 / want < want / side as f64 {
        side *= 2;
    }
    side
}

/// Bilinear sample of a decoded cube raster at a latitude/longitude; corners that are
/// holes of a sparse repository are left out (`NaN` when all four are).
pub fn query(geom: &SphereGeometry, values: &[f64], lat: f64, lon: f64) -> f64 {
    let side = geom.face_side();
    let (face, u, v) = face_chart(lat, lon, side);
    let u = u.clamp(0.0, side as f64);
    let v = v.clamp(0.0, side as f64);
    let (u0, v0) = (
        (u.floor() as usize).min(side - 1),
        (v.floor() as usize).min(side - 1),
    );
    let (fu, fv) = (u - u0 as f64, v - v0 as f64);
    let (mut sum, mut weight) = (0.0, 0.0);
    for (du, dv, w) in [
        (0, 0, (1.0 - fu) * (1.0 - fv)),
        (1, 0, fu * (1.0 - fv)),
        (0, 1, (1.0 - fu) * fv),
        (1, 1, fu * fv),
    ] {
        let k = geom.cube_index(face, u0 + du, v0 + dv);
        if geom.is_valid(k) && values[k].is_finite() {
            sum += values[k] * w;
            weight += w;
        }
    }
    if weight > 0.0 { sum / weight } else { f64::NAN }
}

/// Cube edge and corner samples whose copies on different faces disagree.
pub fn seam_mismatches<T: PartialEq + Copy>(geom: &SphereGeometry, values: &[T]) -> u64 {
    let side = geom.face_side();
    let mut mismatches = 0;
    for face in 0..6u8 {
        for v in 0..=side {
            for u in 0..=side {
                if u != 0 && u != side && v != 0 && v != side {
                    continue;
                }
                let own = values[geom.cube_index(face, u, v)];
                let p = geom.sample_position(face, u, v);
                if geom.point_indices(p).any(|k| values[k] != own) {
                    mismatches += 1;
                }
            }
        }
    }
    mismatches
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use super::*;

    #[test]
    fn face_chart_inverts_sample_positions() {
        let geom = SphereGeometry::new(64, 8).unwrap();
        for face in 0..6u8 {
            for (u, v) in [(1, 1), (10, 50), (32, 32), (63, 2)] {
                let (lat, lon) = lat_lon(geom.sample_position(face, u, v));
                let (f, uu, vv) = face_chart(lat, lon, 64);
                assert_eq!(f, face);
                assert!((uu - u as f64).abs() < 1e-6 && (vv - v as f64).abs() < 1e-6);
            }
        }
        let (lat, _) = lat_lon(geom.sample_position(4, 32, 32));
        assert!(
            (lat - 90.0).abs() < 1e-9,
            "+Z face centre is the north pole"
        );
    }

    #[test]
    fn equirect_sampling_wraps_the_antimeridian_and_reproduces_nodes() {
        // 8 x 5 node grid with value = column (wraps), 45° spacing.
        let values: Vec<f64> = (0..40).map(|k| (k % 8) as f64).collect();
        let g = Georef {
            crs: None,
            west: -180.0,
            east: 135.0,
            north: 90.0,
            south: -90.0,
            registration: Registration::Node,
            projection: None,
        };
        let e = Equirect::new(8, 5, &values, &g).unwrap();
        assert_eq!(e.sample(0.0, -180.0), 0.0);
        assert_eq!(e.sample(45.0, -90.0), 2.0);
        assert!(
            (e.sample(0.0, 157.5) - 3.5).abs() < 1e-9,
            "between col 7 and col 0"
        );
        assert!((e.sample(0.0, 180.0) - 0.0).abs() < 1e-9);
    }

    #[test]
    fn tabulated_angles_equal_lat_lon_and_agree_across_faces() {
        for face_side in [64usize, 1024] {
            let geom = SphereGeometry::new(face_side, 32).unwrap();
            let angles = CubeAngles::new(&geom);
            let mut seen = std::collections::HashMap::new();
            let mut row = vec![(0.0, 0.0); face_side + 1];
            for face in 0..6u8 {
                for v in 0..=face_side {
                    angles.row(usize::from(face), v, &mut row);
                    for (u, &(lat, lon)) in row.iter().enumerate() {
                        let p = geom.sample_position(face, u, v);
                        let (want_lat, want_lon) = lat_lon(p);
                        assert!((lat - want_lat).abs() < 1e-12, "lat at {face} {u} {v}");
                        // Longitude is undefined at the poles themselves.
                        let pole = p[0] == 0 && p[1] == 0;
                        assert!(
                            pole || (lon - want_lon).abs() < 1e-12,
                            "lon at {face} {u} {v}"
                        );
                        // Every copy of an edge or corner point: the same angles, bit for bit.
                        let half = (face_side / 2) as i64;
                        if p.iter().filter(|x| x.abs() == half).count() < 2 {
                            continue;
                        }
                        let first = *seen.entry(p).or_insert((lat.to_bits(), lon.to_bits()));
                        assert_eq!(first, (lat.to_bits(), lon.to_bits()), "copy of {p:?}");
                    }
                }
            }
        }
    }

    #[test]
    fn row_spans_equal_whole_rows_bit_for_bit() {
        let geom = SphereGeometry::new(256, 32).unwrap();
        let angles = CubeAngles::new(&geom);
        let mut row = vec![(0.0, 0.0); 257];
        for face in 0..6 {
            for v in [0, 1, 77, 128, 200, 256] {
                angles.row(face, v, &mut row);
                for (u0, len) in [(0, 257), (0, 1), (100, 57), (200, 57), (256, 1)] {
                    let mut span = vec![(0.0, 0.0); len];
                    angles.row_span(face, v, u0, &mut span);
                    for (k, (a, b)) in span.iter().zip(&row[u0..u0 + len]).enumerate() {
                        assert_eq!(
                            (a.0.to_bits(), a.1.to_bits()),
                            (b.0.to_bits(), b.1.to_bits()),
                            "face {face} row {v} sample {}",
                            u0 + k
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn default_face_side_tracks_the_source_resolution() {
        assert_eq!(default_face_side(5.0 / 60.0, 32), 1024); // ETOPO5: 1080 per 90°
        assert_eq!(default_face_side(20.0 / 60.0, 32), 256); // ETOPO20: 270
        assert_eq!(default_face_side(4.0 / 60.0, 64), 1024); // Blue Marble: 1350
    }
}
