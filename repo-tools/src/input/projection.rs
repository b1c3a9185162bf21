//! What a georeference's coordinate reference system is, recognised from the many ways
//! sources name it: EPSG and IAU codes, PROJ strings, WKT, free-text names in sidecars,
//! and GeoTIFF geokeys. One parser for every reader, so that a planet build accepts the
//! latitude/longitude grid under any of its names and refuses a genuinely different
//! projection by name.
//!
//! Planet builds take a regular grid of latitude and longitude. That is a geographic CRS
//! (coordinates in degrees), or the equirectangular projection (Plate Carrée, Simple
//! Cylindrical, `+proj=eqc`) with its standard parallel at the equator, whose columns and
//! rows are equal steps of longitude and latitude. See `docs/building.md`, "Planets".

use std::fmt;

/// A coordinate reference system, as far as the builds care.
#[derive(Clone, Debug, PartialEq)]
pub enum Projection {
    /// Latitude/longitude in degrees: a geographic CRS (`EPSG:4326`, `+proj=longlat`,
    /// `IAU2000:49900`, GeoTIFF model type geographic, "geographic lat/lon", ...).
    Geographic {
        /// How the source named it.
        name: String,
    },
    /// The equirectangular projection (Plate Carrée, Simple Cylindrical, Equidistant
    /// Cylindrical, `+proj=eqc`), true to scale at `standard_parallel_deg`.
    Equirectangular {
        /// Latitude of true scale (`lat_ts`, standard parallel 1), degrees.
        standard_parallel_deg: f64,
        /// How the source named it.
        name: String,
    },
    /// Another projection (UTM, Mercator, Lambert, a projected EPSG code, ...).
    Other {
        /// Its name, as precise as the source allows.
        name: String,
    },
    /// Text that names no CRS these readers recognise.
    Unrecognised {
        /// The text.
        text: String,
    },
}

/// What planet builds accept, for messages.
pub const ACCEPTED: &str = "a geographic CRS (EPSG:4326 and other geographic EPSG codes, \
    OGC CRS84, IAU2000/IAU_2015 <body>00, +proj=longlat, a GeoTIFF with a geographic model \
    type, or a name such as \"geographic lat/lon\" or \"WGS 84\"), or an equirectangular \
    projection with its standard parallel at 0 (Equirectangular, Plate Carree, Simple \
    Cylindrical, Equidistant Cylindrical, +proj=eqc, EPSG:4087, EPSG:32662)";

/// Geographic 2D (and 3D) CRSs by EPSG code: the world and continental datums sources
/// use. A GeoTIFF's GeographicTypeGeoKey is geographic whatever its code.
const GEOGRAPHIC_EPSG: &[(u32, &str)] = &[
    (4326, "WGS 84"),
    (4979, "WGS 84 (3D)"),
    (4269, "NAD83"),
    (4267, "NAD27"),
    (4152, "NAD83(HARN)"),
    (4617, "NAD83(CSRS)"),
    (6318, "NAD83(2011)"),
    (4258, "ETRS89"),
    (4937, "ETRS89 (3D)"),
    (4230, "ED50"),
    (4283, "GDA94"),
    (7844, "GDA2020"),
    (4202, "AGD66"),
    (4203, "AGD84"),
    (4612, "JGD2000"),
    (6668, "JGD2011"),
    (4301, "Tokyo"),
    (4167, "NZGD2000"),
    (4674, "SIRGAS 2000"),
    (4490, "CGCS2000"),
    (4322, "WGS 72"),
    (4277, "OSGB36"),
    (4171, "RGF93"),
    (4148, "Hartebeesthoek94"),
    (4737, "Korea 2000"),
    (4019, "Unknown datum based upon the GRS 1980 ellipsoid"),
    (4030, "Unknown datum based upon the WGS 84 ellipsoid"),
    (4035, "Unknown datum based upon the Authalic Sphere"),
    (
        4047,
        "Unspecified datum based upon the GRS 1980 Authalic Sphere",
    ),
];

/// Projected EPSG codes of the equirectangular projection with standard parallel 0.
const EQUIRECTANGULAR_EPSG: &[(u32, &str)] = &[
    (4087, "WGS 84 / World Equidistant Cylindrical"),
    (4088, "World Equidistant Cylindrical (Sphere)"),
    (32662, "WGS 84 / Plate Carree"),
];

impl Projection {
    /// Whether a planet build can take a grid in this CRS as it is: a geographic CRS, or
    /// equirectangular with standard parallel 0.
    pub fn is_lat_lon_grid(&self) -> bool {
        match self {
            Projection::Geographic { .. } => true,
            Projection::Equirectangular {
                standard_parallel_deg,
                ..
            } => *standard_parallel_deg == 0.0,
            Projection::Other { .. } | Projection::Unrecognised { .. } => false,
        }
    }

    /// The CRS an EPSG code names.
    pub fn from_epsg(code: u32) -> Projection {
        if let Some((_, name)) = GEOGRAPHIC_EPSG.iter().find(|(c, _)| *c == code) {
            return Projection::Geographic {
                name: format!("EPSG:{code} ({name})"),
            };
        }
        if let Some((_, name)) = EQUIRECTANGULAR_EPSG.iter().find(|(c, _)| *c == code) {
            return Projection::Equirectangular {
                standard_parallel_deg: 0.0,
                name: format!("EPSG:{code} ({name})"),
            };
        }
        let name = match code {
            32601..=32660 => format!("EPSG:{code} (WGS 84 / UTM zone {}N)", code - 32600),
            32701..=32760 => format!("EPSG:{code} (WGS 84 / UTM zone {}S)", code - 32700),
            26901..=26923 => format!("EPSG:{code} (NAD83 / UTM zone {}N)", code - 26900),
            25828..=25838 => format!("EPSG:{code} (ETRS89 / UTM zone {}N)", code - 25800),
            3857 | 900913 => format!("EPSG:{code} (WGS 84 / Pseudo-Mercator, web Mercator)"),
            3395 => format!("EPSG:{code} (WGS 84 / World Mercator)"),
            4978 => format!("EPSG:{code} (WGS 84 geocentric, Cartesian)"),
            _ => format!("EPSG:{code} (not a geographic CRS known here)"),
        };
        Projection::Other { name }
    }

    /// The CRS an IAU planetary code (`IAU2000:49900`, `IAU_2015:30100`) names: the body
    /// is the code divided by 100; the last two digits 00-02 are the body's geographic
    /// CRSs (sphere, ellipsoid ocentric and ographic), others its projections.
    pub fn from_iau(authority: &str, code: u32) -> Projection {
        let (body, kind) = (code / 100, code % 100);
        let name = format!("{authority}:{code} (body {body})");
        if code >= 100 && kind <= 2 {
            Projection::Geographic { name }
        } else {
            Projection::Other {
                name: format!(
                    "{name}, a projected CRS: only <body>00 to <body>02 are latitude/longitude"
                ),
            }
        }
    }

    /// Recognises a CRS from text: an EPSG or IAU code, a PROJ string, WKT, or a name.
    pub fn parse(text: &str) -> Projection {
        let raw = text.trim();
        let t = normalise(raw);
        if let Some(p) = parse_code(&t) {
            return p;
        }
        if t.contains("+proj=") || t.starts_with("proj=") {
            return parse_proj(raw);
        }
        if let Some(p) = parse_wkt(raw, &t) {
            return p;
        }
        parse_name(raw, &t)
    }

    /// The CRS GeoTIFF geokeys give: `model_type` (GTModelTypeGeoKey, 1 projected, 2
    /// geographic, 3 geocentric), the geographic and projected EPSG codes, and for a
    /// user-defined projection its coordinate transformation (ProjCoordTransGeoKey, 17 =
    /// equirectangular) and first standard parallel. `None` when the keys say nothing.
    pub fn from_geotiff(
        model_type: Option<u16>,
        geographic_code: Option<u16>,
        projected_code: Option<u16>,
        coord_transform: Option<u16>,
        standard_parallel_deg: Option<f64>,
    ) -> Option<Projection> {
        const USER_DEFINED: u16 = 32767;
        const CT_EQUIRECTANGULAR: u16 = 17;
        if let Some(code) = projected_code.filter(|c| (1..USER_DEFINED).contains(c)) {
            return Some(Projection::from_epsg(u32::from(code)));
        }
        if model_type == Some(1) || projected_code == Some(USER_DEFINED) {
            return Some(match coord_transform {
                Some(CT_EQUIRECTANGULAR) => Projection::Equirectangular {
                    standard_parallel_deg: standard_parallel_deg.unwrap_or(0.0),
                    name: "GeoTIFF user-defined equirectangular projection".into(),
                },
                Some(ct) => Projection::Other {
                    name: format!("GeoTIFF projected CRS (coordinate transformation {ct})"),
                },
                None => Projection::Other {
                    name: "GeoTIFF projected CRS without a code".into(),
                },
            });
        }
        if model_type == Some(3) {
            return Some(Projection::Other {
                name: "GeoTIFF geocentric (Cartesian) CRS".into(),
            });
        }
        match geographic_code {
            Some(code) if (1..USER_DEFINED).contains(&code) => {
                let name = match Projection::from_epsg(u32::from(code)) {
                    Projection::Geographic { name } => name,
                    _ => format!("EPSG:{code} (GeoTIFF geographic type)"),
                };
                Some(Projection::Geographic { name })
            }
            Some(_) => Some(Projection::Geographic {
                name: "GeoTIFF user-defined geographic CRS".into(),
            }),
            None if model_type == Some(2) => Some(Projection::Geographic {
                name: "GeoTIFF geographic model".into(),
            }),
            None => None,
        }
    }
}

impl fmt::Display for Projection {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Projection::Geographic { name } => write!(f, "{name} (geographic)"),
            Projection::Equirectangular {
                standard_parallel_deg,
                name,
            } => write!(
                f,
                "{name} (equirectangular, standard parallel {standard_parallel_deg} degrees)"
            ),
            Projection::Other { name } => write!(f, "{name}"),
            Projection::Unrecognised { text } => write!(f, "{text:?} (not recognised)"),
        }
    }
}

/// Lower case, `_`, `-` and runs of blanks as one space, `é` as `e`.
fn normalise(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    for c in text.trim().chars() {
        let c = match c {
            'é' | 'É' | 'è' => 'e',
            '_' | '-' | '\t' | '\n' => ' ',
            c => c.to_ascii_lowercase(),
        };
        if c == ' ' && out.ends_with(' ') {
            continue;
        }
        out.push(c);
    }
    out
}

/// The digits at the start of `s`, as a number.
fn leading_number(s: &str) -> Option<u32> {
    let digits: String = s
        .trim_start()
        .chars()
        .take_while(char::is_ascii_digit)
        .collect();
    digits.parse().ok()
}

/// `EPSG:4326`, `epsg 4326`, `urn:ogc:def:crs:EPSG::4326`, `CRS:84`, `IAU2000:49900`,
/// `IAU_2015:30100` (normalised text). WKT is left to [`parse_wkt`].
fn parse_code(t: &str) -> Option<Projection> {
    if t.contains('[') {
        return None;
    }
    if t.contains("crs84") || t.contains("crs:84") || t.contains("crs 84") {
        return Some(Projection::Geographic {
            name: "OGC CRS84 (WGS 84, longitude first)".into(),
        });
    }
    for authority in ["iau2000", "iau 2015", "iau2015", "iau 2000", "iau"] {
        if let Some(at) = t.find(&format!("{authority}:")) {
            let rest = t[at + authority.len() + 1..].trim_start_matches(':');
            if let Some(code) = leading_number(rest) {
                let label = authority.to_ascii_uppercase().replace(' ', "_");
                return Some(Projection::from_iau(&label, code));
            }
        }
    }
    let at = t.find("epsg")?;
    let rest = t[at + 4..].trim_start_matches([':', ' ']);
    let code = leading_number(rest)?;
    Some(Projection::from_epsg(code))
}

/// A PROJ string: `+proj=longlat`, `+proj=eqc +lat_ts=0`, `+proj=utm +zone=33`, ...
fn parse_proj(raw: &str) -> Projection {
    // Not `normalise`d: keys such as `lat_ts` keep their underscores.
    let t = raw.to_ascii_lowercase();
    let value = |key: &str| {
        t.split_whitespace()
            .filter_map(|w| w.trim_start_matches('+').split_once('='))
            .find(|(k, _)| *k == key)
            .map(|(_, v)| v.to_string())
    };
    let name = value("proj").unwrap_or_default();
    match name.as_str() {
        "longlat" | "latlong" | "lonlat" | "latlon" => Projection::Geographic {
            name: raw.to_string(),
        },
        "eqc" => match value("lat_ts").map(|v| v.parse::<f64>()) {
            None => Projection::Equirectangular {
                standard_parallel_deg: 0.0,
                name: raw.to_string(),
            },
            Some(Ok(lat_ts)) if lat_ts.is_finite() => Projection::Equirectangular {
                standard_parallel_deg: lat_ts,
                name: raw.to_string(),
            },
            Some(_) => Projection::Unrecognised {
                text: raw.to_string(),
            },
        },
        "" => Projection::Unrecognised {
            text: raw.to_string(),
        },
        other => Projection::Other {
            name: format!("{} ({raw})", proj_name(other)),
        },
    }
}

/// A readable name of a PROJ projection.
fn proj_name(proj: &str) -> String {
    match proj {
        "utm" => "UTM".into(),
        "merc" | "webmerc" => "Mercator".into(),
        "tmerc" | "etmerc" => "transverse Mercator".into(),
        "lcc" => "Lambert conformal conic".into(),
        "laea" => "Lambert azimuthal equal-area".into(),
        "aea" => "Albers equal-area".into(),
        "stere" | "sterea" | "ups" => "stereographic".into(),
        "sinu" => "sinusoidal".into(),
        "moll" => "Mollweide".into(),
        "robin" => "Robinson".into(),
        "ortho" => "orthographic".into(),
        "cea" => "cylindrical equal-area".into(),
        "geocent" | "cart" => "geocentric Cartesian".into(),
        other => format!("+proj={other}"),
    }
}

/// WKT 1 or 2: `GEOGCS[`/`GEOGCRS[` are geographic; `PROJCS[`/`PROJCRS[` are named by
/// their projection (method), equirectangular with its first standard parallel.
fn parse_wkt(raw: &str, t: &str) -> Option<Projection> {
    let head = t.split('[').next()?.trim();
    if !t.contains('[') {
        return None;
    }
    match head {
        "geogcs" | "geogcrs" | "geodcrs" | "geographiccrs" => Some(Projection::Geographic {
            name: wkt_name(raw).unwrap_or_else(|| "WKT geographic CRS".into()),
        }),
        "projcs" | "projcrs" | "projectedcrs" => {
            let method = ["projection[", "method["]
                .iter()
                .find_map(|k| t.find(k).map(|at| &t[at + k.len()..]))
                .map(|rest| rest.trim_start_matches('"'))
                .and_then(|rest| rest.split('"').next())
                .unwrap_or("")
                .to_string();
            let name = wkt_name(raw).unwrap_or_else(|| "WKT projected CRS".into());
            if is_equirectangular_name(&method) {
                let lat_ts = [
                    "standard parallel 1\",",
                    "latitude of 1st standard parallel\",",
                ]
                .iter()
                .find_map(|k| t.find(k).map(|at| &t[at + k.len()..]))
                .and_then(|rest| {
                    rest.trim_start()
                        .split([',', ']'])
                        .next()
                        .and_then(|v| v.trim().parse::<f64>().ok())
                })
                .unwrap_or(0.0);
                Some(Projection::Equirectangular {
                    standard_parallel_deg: lat_ts,
                    name,
                })
            } else {
                Some(Projection::Other {
                    name: format!("{name} ({method})"),
                })
            }
        }
        _ => None,
    }
}

/// The quoted name right after the first `[` of WKT.
fn wkt_name(raw: &str) -> Option<String> {
    let rest = raw.split_once('[')?.1.trim_start().strip_prefix('"')?;
    Some(rest.split('"').next()?.to_string())
}

fn is_equirectangular_name(t: &str) -> bool {
    [
        "equirectangular",
        "equi rectangular",
        "plate carree",
        "platecarree",
        "simple cylindrical",
        "equidistant cylindrical",
        "cylindrical equidistant",
        "eqc",
    ]
    .iter()
    .any(|k| t.contains(k))
}

/// Projection names that are not a latitude/longitude grid, in the order they are
/// looked for (the more specific first).
const OTHER_NAMES: &[(&str, &str)] = &[
    ("universal transverse mercator", "UTM"),
    ("utm", "UTM"),
    ("pseudo mercator", "web Mercator"),
    ("web mercator", "web Mercator"),
    ("transverse mercator", "transverse Mercator"),
    ("mercator", "Mercator"),
    ("lambert", "Lambert"),
    ("albers", "Albers equal-area"),
    ("stereographic", "stereographic"),
    ("sinusoidal", "sinusoidal"),
    ("mollweide", "Mollweide"),
    ("robinson", "Robinson"),
    ("orthographic", "orthographic"),
    ("gauss kruger", "Gauss-Kruger"),
    ("state plane", "State Plane"),
    ("conic", "conic"),
    ("azimuthal", "azimuthal"),
    ("polyconic", "polyconic"),
];

/// Free text: a projection's name, or words that say latitude/longitude.
fn parse_name(raw: &str, t: &str) -> Projection {
    if let Some((_, name)) = OTHER_NAMES.iter().find(|(k, _)| has_word(t, k)) {
        return Projection::Other {
            name: format!("{name} ({raw:?})"),
        };
    }
    if is_equirectangular_name(t) {
        let lat_ts = ["standard parallel", "lat ts", "latitude of true scale"]
            .iter()
            .find_map(|k| t.find(k).map(|at| &t[at + k.len()..]))
            .and_then(|rest| {
                let rest = rest.trim_start_matches([' ', '=', ':']);
                let end = rest
                    .find(|c: char| !(c.is_ascii_digit() || c == '.' || c == ' '))
                    .unwrap_or(rest.len());
                rest[..end].trim().parse::<f64>().ok()
            })
            .unwrap_or(0.0);
        return Projection::Equirectangular {
            standard_parallel_deg: lat_ts,
            name: raw.to_string(),
        };
    }
    let geographic = [
        "geographic",
        "geodetic",
        "lat/lon",
        "lat/long",
        "lon/lat",
        "latitude/longitude",
        "longitude/latitude",
        "latitude longitude",
        "longitude latitude",
        "lat lon",
        "lon lat",
        "latlon",
        "lonlat",
        "longlat",
        "latlong",
        "unprojected",
        "wgs 84",
        "wgs84",
        "nad83",
        "nad 83",
        "etrs89",
        "degrees",
    ];
    if geographic.iter().any(|k| t.contains(k)) {
        return Projection::Geographic {
            name: raw.to_string(),
        };
    }
    Projection::Unrecognised {
        text: raw.to_string(),
    }
}

/// Whether `t` has `word` not inside a longer word (`utm` but not `autumn`).
fn has_word(t: &str, word: &str) -> bool {
    t.match_indices(word).any(|(at, _)| {
        let before = t[..at].chars().next_back();
        let after = t[at + word.len()..].chars().next();
        !before.is_some_and(|c| c.is_ascii_alphanumeric())
            && !after.is_some_and(|c| c.is_ascii_alphabetic())
    })
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use super::*;

    #[test]
    fn latitude_longitude_grids_are_recognised_under_their_names_and_codes() {
        for text in [
            "EPSG:4326",
            "epsg:4326",
            "EPSG 4269",
            "urn:ogc:def:crs:EPSG::4258",
            "EPSG:4283",
            "EPSG:4612",
            "EPSG:4230",
            "EPSG:4979",
            "EPSG:4087",
            "EPSG:32662",
            "OGC:CRS84",
            "CRS:84",
            "IAU2000:49900",
            "IAU2000:30100",
            "IAU_2015:49900",
            "IAU_2015:19900",
            "iau2000:29900",
            "+proj=longlat +datum=WGS84 +no_defs",
            "+proj=latlong +a=3396190 +b=3376200",
            "+proj=eqc +lat_ts=0 +lat_0=0 +lon_0=0 +a=3396190",
            "+proj=eqc +R=1737400",
            "GEOGCS[\"WGS 84\",DATUM[\"WGS_1984\",SPHEROID[\"WGS 84\",6378137,298.257223563]]]",
            "GEOGCRS[\"Mars (2015) - Sphere / Ocentric\",DATUM[\"Mars (2015) - Sphere\"]]",
            "PROJCS[\"Mars_Equirectangular\",GEOGCS[\"Mars\"],PROJECTION[\"Equirectangular\"],PARAMETER[\"standard_parallel_1\",0]]",
            "PROJCRS[\"Moon Simple Cylindrical\",METHOD[\"Equidistant Cylindrical\"],PARAMETER[\"Latitude of 1st standard parallel\",0]]",
            "equirectangular",
            "Equirectangular",
            "equirectangular (plate carree)",
            "Plate Carree",
            "Plate Carrée",
            "plate_carree",
            "PlateCarree",
            "Simple Cylindrical",
            "SIMPLE_CYLINDRICAL",
            "simple-cylindrical",
            "Equidistant Cylindrical",
            "equirectangular, standard parallel 0",
            "geographic lat/lon (NAD83/WGS84)",
            "geographic lat/lon (ETOPO5 / WGS84-equivalent), equirectangular (plate carree) grid",
            "geographic",
            "WGS 84",
            "WGS84",
            "latitude/longitude",
            "lat/lon",
            "Geographic Lat/Lon",
            "unprojected",
        ] {
            let p = Projection::parse(text);
            assert!(p.is_lat_lon_grid(), "{text:?} -> {p:?}");
        }
    }

    #[test]
    fn other_projections_are_refused_by_name() {
        for (text, named) in [
            ("EPSG:32633", "UTM zone 33N"),
            ("EPSG:32755", "UTM zone 55S"),
            ("EPSG:26915", "UTM zone 15N"),
            ("EPSG:3857", "Mercator"),
            ("EPSG:3395", "Mercator"),
            ("EPSG:2193", "EPSG:2193"),
            ("EPSG:4978", "geocentric"),
            ("IAU2000:49910", "projected"),
            ("IAU_2015:30116", "projected"),
            ("+proj=utm +zone=33 +datum=WGS84", "UTM"),
            ("+proj=merc +a=3396190", "Mercator"),
            ("+proj=eqc +lat_ts=30", "standard parallel 30"),
            (
                "+proj=eqc +lat_ts=-45.5 +R=3396190",
                "standard parallel -45.5",
            ),
            ("+proj=stere +lat_0=90", "stereographic"),
            ("+proj=sinu", "sinusoidal"),
            ("UTM zone 52N", "UTM"),
            ("WGS 84 / UTM zone 33N", "UTM"),
            ("Mercator", "Mercator"),
            ("Transverse Mercator", "transverse Mercator"),
            ("Web Mercator", "web Mercator"),
            ("Lambert Conformal Conic", "Lambert"),
            ("Polar Stereographic", "stereographic"),
            ("Sinusoidal", "sinusoidal"),
            ("Mollweide", "Mollweide"),
            (
                "equirectangular, standard parallel 30",
                "standard parallel 30",
            ),
            (
                "PROJCS[\"WGS 84 / UTM zone 33N\",GEOGCS[\"WGS 84\"],PROJECTION[\"Transverse_Mercator\"]]",
                "WGS 84 / UTM zone 33N",
            ),
            (
                "PROJCS[\"Mars Equirectangular 30N\",PROJECTION[\"Equirectangular\"],PARAMETER[\"standard_parallel_1\",30]]",
                "standard parallel 30",
            ),
            ("something else entirely", "not recognised"),
            ("autumn colours", "not recognised"),
        ] {
            let p = Projection::parse(text);
            assert!(!p.is_lat_lon_grid(), "{text:?} -> {p:?}");
            let shown = p.to_string();
            assert!(
                shown.contains(named),
                "{text:?}: {shown:?} should name {named:?}"
            );
        }
    }

    #[test]
    fn geotiff_keys_give_the_same_projections() {
        let g = |m, geo, proj, ct, sp| Projection::from_geotiff(m, geo, proj, ct, sp);
        assert_eq!(g(None, None, None, None, None), None);
        for p in [
            g(Some(2), Some(4326), None, None, None),
            g(Some(2), Some(4148), None, None, None),
            g(Some(2), Some(32767), None, None, None),
            g(Some(2), None, None, None, None),
            g(None, Some(4269), None, None, None),
            g(Some(1), None, Some(4087), None, None),
            g(Some(1), None, Some(32767), Some(17), Some(0.0)),
            g(Some(1), None, Some(32767), Some(17), None),
        ] {
            assert!(p.as_ref().is_some_and(Projection::is_lat_lon_grid), "{p:?}");
        }
        for (p, named) in [
            (
                g(Some(1), Some(4326), Some(32633), None, None),
                "UTM zone 33N",
            ),
            (
                g(Some(1), None, Some(32767), Some(17), Some(30.0)),
                "standard parallel 30",
            ),
            (
                g(Some(1), None, Some(32767), Some(11), None),
                "transformation 11",
            ),
            (g(Some(1), None, None, None, None), "projected"),
            (g(Some(3), None, None, None, None), "geocentric"),
        ] {
            let p = p.unwrap();
            assert!(!p.is_lat_lon_grid(), "{p:?}");
            assert!(p.to_string().contains(named), "{p}");
        }
    }
}
