//! Golden vectors for the JavaScript blob decoder of the web demo (`web-demo/js/codec.mjs`,
//! tested by `web-demo/test/codec.test.mjs`): blobs with their decoding contexts and what
//! this crate decodes from them, written as JSON into `web-demo/test/golden/`.
//!
//! - `codec-committed-golden.json`: the golden blobs of `codec/tests/golden/` (the grid and
//!   contexts of `real_data.rs`'s `golden_blobs_are_unchanged`);
//! - `codec-encoder-paths.json`: blobs made by the encoder to cover every decoding path
//!   (lossless and quantised steps with sign hiding, masks, side information with no-data
//!   flags, magnitude escapes up to `i32::MIN` and `i32::MAX`, all-zero matrices, every
//!   diamond size class), and a small raster encoded in the RMS and max-error modes;
//! - `codec-hostile.json`: random and corrupted blobs, with the result or error `blob::decode`
//!   gives (so the JavaScript decoder must fail where and how this one fails);
//! - `codec-tables.json`: class bounds, model probabilities, dequantisation and colour samples.
//!
//! `QUINCUNX_BLESS=1` writes the files; otherwise the test checks that the committed files
//! are exactly what the encoder and decoder produce now, so a format change that is not
//! re-blessed (and ported to the JavaScript decoder) fails here as well as in
//! `real_data.rs`. The raster vectors also change with the encoder's choices (rate
//! control, quantisation): re-bless after such a change too.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use quincunx_codec::blob::{self, BlobContext, DecodeError};
use quincunx_codec::colour;
use quincunx_codec::encode::{self, EncodeOptions, Grid, RateMode, RdoMode};
use quincunx_codec::entropy::{
    self, CONTEXTS, CodecModel, ContextCounts, EntropyError, HIDDEN_SIGN_MIN, NO_DATA,
};
use quincunx_codec::lifting::DiamondMask;
use quincunx_codec::raster::RasterGeometry;

fn out_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../web-demo/test/golden")
}

fn golden_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/golden")
}

// ---------------------------------------------------------------------------------------
// JSON, written by hand so that the text does not depend on serde_json's features.

fn hex(bytes: &[u8]) -> String {
    bytes.iter().fold(String::new(), |mut s, b| {
        let _ = write!(s, "{b:02x}");
        s
    })
}

fn list<T: std::fmt::Display>(items: impl IntoIterator<Item = T>) -> String {
    let items: Vec<String> = items.into_iter().map(|x| x.to_string()).collect();
    format!("[{}]", items.join(","))
}

/// Valid cells as the hex of a bitmap: cell `k` is bit `k % 8` of byte `k / 8` (like a
/// model's bitmap).
fn cells_text(cells: &[bool]) -> String {
    let mut bytes = vec![0u8; cells.len().div_ceil(8)];
    for (k, _) in cells.iter().enumerate().filter(|(_, c)| **c) {
        bytes[k / 8] |= 1 << (k % 8);
    }
    hex(&bytes)
}

/// FNV-1a (32 bits) of the values as little-endian `i32`s: how hostile vectors state a
/// decoded matrix without listing it.
fn fnv1a(q: &[i32]) -> u32 {
    let mut h = 0x811C_9DC5u32;
    for x in q {
        for b in x.to_le_bytes() {
            h = (h ^ u32::from(b)).wrapping_mul(0x0100_0193);
        }
    }
    h
}

/// A JSON file: named models, then one vector per line.
fn file_text(title: &str, models: &[(String, CodecModel)], vectors: &[String]) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "{{\"about\":\"{title} (written by codec/tests/js_golden.rs; bless with QUINCUNX_BLESS=1)\","
    );
    let _ = writeln!(s, "\"blobVersion\":{},", blob::VERSION);
    s.push_str("\"models\":{\n");
    let models: Vec<String> = models
        .iter()
        .map(|(name, m)| format!("\"{name}\":\"{}\"", hex(&m.to_bytes())))
        .collect();
    s.push_str(&models.join(",\n"));
    s.push_str("\n},\n\"vectors\":[\n");
    s.push_str(&vectors.join(",\n"));
    s.push_str("\n]}\n");
    s
}

// ---------------------------------------------------------------------------------------
// Vectors.

/// One blob and its decoding context.
struct Case {
    name: String,
    blob: Vec<u8>,
    key: Vec<u8>,
    n: usize,
    group: usize,
    cells: Option<Vec<bool>>,
    owned: usize,
    step: u32,
    model: String,
    /// For hostile vectors: the name of the `codec-encoder-paths.json` vector whose context
    /// (model, key, size, group, cells, owned children, step) this one shares.
    context: Option<String>,
}

impl Case {
    fn mask(&self) -> Option<DiamondMask> {
        self.cells.as_ref().map(|c| {
            let n = self.n;
            DiamondMask::from_fn(n, |_, _| true, |i, j| c[i * n + j])
        })
    }

    fn decode(&self, model: &CodecModel) -> Result<blob::BlobContent, DecodeError> {
        let mask = self.mask();
        let ctx = BlobContext {
            key: &self.key,
            n: self.n,
            group: self.group,
            mask: mask.as_ref(),
            owned_children: self.owned,
            step: self.step,
        };
        blob::decode(&self.blob, &ctx, model)
    }

    /// The vector's JSON: context, then the decoded classes and matrix (`full`) or its
    /// hash, or the error's kind.
    fn json(&self, models: &[(String, CodecModel)], full: bool) -> String {
        let model = &models
            .iter()
            .find(|(name, _)| *name == self.model)
            .expect("model of a case")
            .1;
        let result = match self.decode(model) {
            Ok(c) if full => format!(
                "\"error\":null,\"childClasses\":{},{}",
                list(&c.child_classes),
                q_text(&c.q)
            ),
            Ok(c) => format!(
                "\"error\":null,\"childClasses\":{},\"qFnv1a\":{}",
                list(&c.child_classes),
                fnv1a(&c.q)
            ),
            Err(e) => format!("\"error\":\"{}\"", error_kind(&e)),
        };
        let context = match &self.context {
            Some(name) => format!("\"context\":\"{name}\""),
            None => {
                let cells = self
                    .cells
                    .as_ref()
                    .map_or("null".to_string(), |c| format!("\"{}\"", cells_text(c)));
                format!(
                    "\"model\":\"{}\",\"key\":\"{}\",\"n\":{},\"group\":{},\"ownedChildren\":{},\"step\":{},\"cells\":{}",
                    self.model,
                    hex(&self.key),
                    self.n,
                    self.group,
                    self.owned,
                    self.step,
                    cells
                )
            }
        };
        format!(
            "{{\"name\":\"{}\",{context},\"blob\":\"{}\",{result}}}",
            self.name,
            hex(&self.blob),
        )
    }
}

/// A decoded matrix as `"q": [...]`, or as `"qSparse": [index, value, ...]` of its
/// nonzeros when that is shorter.
fn q_text(q: &[i32]) -> String {
    let dense = format!("\"q\":{}", list(q));
    let pairs = q
        .iter()
        .enumerate()
        .filter(|&(_, &v)| v != 0)
        .flat_map(|(k, &v)| [k as i64, i64::from(v)]);
    let sparse = format!("\"qSparse\":{}", list(pairs));
    if sparse.len() < dense.len() {
        sparse
    } else {
        dense
    }
}

/// The JavaScript `DecodeError`'s `kind`, with the entropy error after a dot.
fn error_kind(e: &DecodeError) -> String {
    match e {
        DecodeError::TooShort(_) => "TooShort".into(),
        DecodeError::Version(_) => "Version".into(),
        DecodeError::Size { .. } => "Size".into(),
        DecodeError::Checksum { .. } => "Checksum".into(),
        DecodeError::Entropy(EntropyError::Truncated) => "Entropy.Truncated".into(),
        DecodeError::Entropy(EntropyError::EscapeTooLong) => "Entropy.EscapeTooLong".into(),
        DecodeError::Entropy(EntropyError::BadModel(_)) => "Entropy.BadModel".into(),
    }
}

/// A deterministic generator (64-bit LCG, high bits).
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self
            .0
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        self.0 >> 33
    }

    fn below(&mut self, n: u64) -> u64 {
        self.next() % n
    }
}

// ---------------------------------------------------------------------------------------
// The committed golden blobs.

fn committed_golden() -> (Vec<(String, CodecModel)>, Vec<Case>) {
    let geom = RasterGeometry::new(65, 65, 32).unwrap();
    let mut models = Vec::new();
    let mut cases = Vec::new();
    for mode in ["lossless", "rms_2m", "rms_2m_rdo"] {
        let dir = golden_dir().join(mode);
        let model = CodecModel::from_bytes(&std::fs::read(dir.join("model.bin")).unwrap()).unwrap();
        models.push((mode.to_string(), model));
        let steps: serde_json::Value =
            serde_json::from_slice(&std::fs::read(dir.join("steps.json")).unwrap()).unwrap();
        let steps: Vec<u32> = steps["steps"]
            .as_array()
            .unwrap()
            .iter()
            .map(|s| s.as_u64().unwrap() as u32)
            .collect();
        let mut names: Vec<(usize, usize)> = std::fs::read_dir(&dir)
            .unwrap()
            .filter_map(|e| {
                let name = e.unwrap().file_name().to_string_lossy().into_owned();
                let stem = name.strip_suffix(".bin")?;
                let (l, i) = stem.split_once('_')?;
                Some((l.parse().ok()?, i.parse().ok()?))
            })
            .collect();
        names.sort_unstable();
        assert!(names.len() >= 5, "{mode}: golden blobs missing");
        for (l, i) in names {
            let ctx = geom.blob_context(l, i);
            cases.push(Case {
                name: format!("{mode}/{l}_{i}"),
                blob: std::fs::read(dir.join(format!("{l}_{i}.bin"))).unwrap(),
                key: ctx.key.to_vec(),
                n: ctx.n,
                group: ctx.group,
                cells: ctx.mask.map(|m| m.cells().to_vec()),
                owned: ctx.owned_children,
                step: steps[l],
                model: mode.to_string(),
                context: None,
            });
        }
    }
    (models, cases)
}

// ---------------------------------------------------------------------------------------
// Synthetic matrices through `blob::encode`.

/// What one synthetic blob holds.
struct Content {
    name: &'static str,
    n: usize,
    group: usize,
    cells: Option<Vec<bool>>,
    classes: Vec<u8>,
    q: Vec<i32>,
    step: u32,
}

/// Makes every 4x4 block with at least [`HIDDEN_SIGN_MIN`] nonzeros obey the sign-hiding
/// parity rule (first sign negative exactly when the magnitudes sum to an odd number) by
/// moving the block's last nonzero by one, as the encoder's pruning does.
fn obey_parity(n: usize, q: &mut [i32]) {
    let b = n.min(4);
    for bi in (0..n).step_by(b) {
        for bj in (0..n).step_by(b) {
            let nz: Vec<usize> = (bi..bi + b)
                .flat_map(|i| (bj..bj + b).map(move |j| i * n + j))
                .filter(|&k| q[k] != 0)
                .collect();
            if nz.len() >= HIDDEN_SIGN_MIN {
                let odd = nz.iter().fold(0, |a, &k| a ^ (q[k].unsigned_abs() & 1)) == 1;
                if odd != (q[nz[0]] < 0) {
                    let last = nz[nz.len() - 1];
                    let v = q[last];
                    q[last] = if v.unsigned_abs() >= 1 << 30 {
                        v - v.signum()
                    } else {
                        v + v.signum()
                    };
                }
            }
        }
    }
}

/// A matrix with `density` in 16 cells nonzero, magnitudes below `amp`.
fn random_matrix(rng: &mut Rng, n: usize, density: u64, amp: u64) -> Vec<i32> {
    (0..n * n)
        .map(|_| {
            if rng.below(16) < density {
                let m = 1 + rng.below(amp) as i32;
                if rng.below(2) == 0 { m } else { -m }
            } else {
                0
            }
        })
        .collect()
}

fn synthetic_contents() -> Vec<Content> {
    let mut rng = Rng(23);
    let mut out = Vec::new();
    let triangle = |n: usize| (0..n * n).map(|k| k / n + k % n < n).collect::<Vec<bool>>();
    let stripes = |n: usize| (0..n * n).map(|k| k % 3 != 0).collect::<Vec<bool>>();
    // All zero, without and with side information (classes 0..=63, no-data flags).
    out.push(Content {
        name: "zero_no_children",
        n: 32,
        group: 0,
        cells: None,
        classes: vec![],
        q: vec![0; 1024],
        step: 256,
    });
    out.push(Content {
        name: "zero_with_classes",
        n: 32,
        group: 1,
        cells: None,
        classes: vec![0, 5 | NO_DATA, 63, 1 | NO_DATA],
        q: vec![0; 1024],
        step: 256,
    });
    // Sparse and dense, lossless (every sign coded) and quantised (sign hiding).
    for (name, density, amp, step, group) in [
        ("sparse_lossless", 1, 6, 256, 0),
        ("sparse_quantised", 1, 6, 700, 0),
        ("medium_lossless", 5, 30, 256, 2),
        ("dense_lossless", 12, 200, 256, 3),
        ("dense_quantised", 12, 200, 4000, 3),
        ("dense_small_quantised", 14, 3, 300, 4),
    ] {
        let mut q = random_matrix(&mut rng, 32, density, amp);
        if step > 256 {
            obey_parity(32, &mut q);
        }
        let classes = (0..rng.below(5))
            .map(|_| {
                let c = rng.below(64) as u8;
                if c > 0 && rng.below(2) == 0 {
                    c | NO_DATA
                } else {
                    c
                }
            })
            .collect();
        out.push(Content {
            name,
            n: 32,
            group,
            cells: None,
            classes,
            q,
            step,
        });
    }
    // Masks: invalid cells are 0; whole blocks invalid (the quadtree skips them).
    for (name, step, tri) in [
        ("masked_triangle_lossless", 256, true),
        ("masked_triangle_quantised", 1024, true),
        ("masked_stripes_quantised", 512, false),
    ] {
        let cells = if tri { triangle(32) } else { stripes(32) };
        let mut q = random_matrix(&mut rng, 32, 10, 40);
        for (x, &ok) in q.iter_mut().zip(&cells) {
            if !ok {
                *x = 0;
            }
        }
        if step > 256 {
            obey_parity(32, &mut q);
        }
        out.push(Content {
            name,
            n: 32,
            group: 1,
            cells: Some(cells),
            classes: vec![9, 2 | NO_DATA],
            q,
            step,
        });
    }
    // Escapes: extreme magnitudes, as a hidden first sign too, and saturated activities.
    for (name, step) in [("escapes_lossless", 256), ("escapes_quantised", 512)] {
        let mut q = random_matrix(&mut rng, 32, 3, 20);
        q[0] = i32::MIN;
        q[4] = i32::MAX;
        q[37] = 1 << 20;
        q[38] = -(1 << 24) - 3;
        q[100] = 70_000;
        q[200] = -5_000;
        // Blocks of extremes: activities saturate at u32::MAX, Rice parameter 15; the
        // first of a dense block is `i32::MIN`, whose hidden sign's magnitude `2^31` the
        // decoder holds as `2^31 - 1` until the block ends.
        for i in 8..12 {
            for j in 8..16 {
                q[i * 32 + j] = match ((i + j) % 2, j < 12) {
                    (0, true) => i32::MAX,
                    (_, true) => i32::MIN + 1,
                    (0, false) => i32::MIN,
                    _ => 1 << 29,
                };
            }
        }
        if step > 256 {
            obey_parity(32, &mut q);
        }
        out.push(Content {
            name,
            n: 32,
            group: 5,
            cells: None,
            classes: vec![63 | NO_DATA],
            q,
            step,
        });
    }
    // Every size class: n = 2 (one 2x2 block), 4, 8, 16 and 64 (colour), one masked.
    for (name, n, step, masked) in [
        ("n2", 2usize, 256, false),
        ("n4", 4, 512, false),
        ("n8", 8, 256, true),
        ("n16", 16, 2048, false),
        ("n64", 64, 600, false),
        ("n64_masked", 64, 256, true),
    ] {
        let density = if n <= 8 { 10 } else { 2 };
        let mut q = random_matrix(&mut rng, n, density, 50);
        let cells = masked.then(|| triangle(n));
        if let Some(c) = &cells {
            for (x, &ok) in q.iter_mut().zip(c) {
                if !ok {
                    *x = 0;
                }
            }
        }
        if step > 256 {
            obey_parity(n, &mut q);
        }
        out.push(Content {
            name,
            n,
            group: 2,
            cells,
            classes: vec![3, 0, 17 | NO_DATA],
            q,
            step,
        });
    }
    out
}

fn encoder_paths() -> (Vec<(String, CodecModel)>, Vec<Case>) {
    let contents = synthetic_contents();
    // A trained model, like a repository's: counts of every decision of every blob.
    let mut counts = ContextCounts::default();
    for c in &contents {
        entropy::write_gammas(&mut counts, c.group, &c.classes);
        entropy::write_matrix(
            &mut counts,
            c.group,
            c.n,
            &c.q,
            c.cells.as_deref(),
            c.step > 256,
        );
    }
    let mut models = vec![
        ("trained".to_string(), CodecModel::from_counts(&counts)),
        ("default".to_string(), CodecModel::default()),
    ];
    let mut cases = Vec::new();
    let mut rng = Rng(7);
    for (k, c) in contents.iter().enumerate() {
        for (name, model) in &models[..2] {
            // Every blob with the trained model; every fifth with the default one too.
            if name == "default" && k % 5 != 0 {
                continue;
            }
            let key: Vec<u8> = (0..1 + rng.below(6))
                .map(|_| rng.below(256) as u8)
                .collect();
            let mask = c
                .cells
                .as_ref()
                .map(|cells| DiamondMask::from_fn(c.n, |_, _| true, |i, j| cells[i * c.n + j]));
            let ctx = BlobContext {
                key: &key,
                n: c.n,
                group: c.group,
                mask: mask.as_ref(),
                owned_children: c.classes.len(),
                step: c.step,
            };
            let bytes = blob::encode(&ctx, model, &c.classes, &c.q);
            let case = Case {
                name: format!("{}/{name}", c.name),
                blob: bytes,
                key: key.clone(),
                n: c.n,
                group: c.group,
                cells: c.cells.clone(),
                owned: c.classes.len(),
                step: c.step,
                model: name.clone(),
                context: None,
            };
            // The decoder gives back what was encoded (the no-data flag only with a class).
            let got = case.decode(model).unwrap();
            let want: Vec<u8> = c
                .classes
                .iter()
                .map(|&e| if e & !NO_DATA == 0 { 0 } else { e })
                .collect();
            assert_eq!(got.child_classes, want, "{}", case.name);
            assert_eq!(got.q, c.q, "{}", case.name);
            cases.push(case);
        }
    }
    // A small raster through the whole encoder: border diamonds with masks, several
    // levels of owned children, side information from real subtrees.
    let raster = raster_grid();
    for (mode_name, mode) in [
        ("raster_rms", RateMode::RmsM(1.5)),
        ("raster_max_error", RateMode::MaxErrorM(4.0)),
    ] {
        let enc = encode::encode(
            &raster,
            EncodeOptions {
                n: 8,
                mode,
                sparse: false,
                rdo: RdoMode::Auto,
            },
        )
        .unwrap();
        let geom = RasterGeometry::new(enc.width, enc.height, enc.n).unwrap();
        for (l, level) in enc.blobs.iter().enumerate() {
            for (i, b) in level.iter().enumerate() {
                let Some(b) = b else { continue };
                let ctx = geom.blob_context(l, i);
                // The finest level's unmasked blobs of the second mode add little.
                if mode_name == "raster_max_error" && l + 1 == enc.blobs.len() && ctx.mask.is_none()
                {
                    continue;
                }
                cases.push(Case {
                    name: format!("{mode_name}/{l}_{i}"),
                    blob: b.clone(),
                    key: ctx.key.to_vec(),
                    n: ctx.n,
                    group: ctx.group,
                    cells: ctx.mask.map(|m| m.cells().to_vec()),
                    owned: ctx.owned_children,
                    step: enc.steps[l],
                    model: mode_name.to_string(),
                    context: None,
                });
            }
        }
        models.push((mode_name.to_string(), enc.model.clone()));
    }
    (models, cases)
}

/// A 45 x 29 terrain (integer arithmetic only): a hill, a steep ridge and a flat plateau
/// whose diamonds have no details (their owners flag them no-data).
fn raster_grid() -> Grid {
    let (w, h) = (45usize, 29usize);
    let values_m = (0..w * h)
        .map(|k| {
            let (x, y) = ((k % w) as i64, (k / w) as i64);
            if x < 16 && y < 16 {
                return 300.0;
            }
            let hill = 600 - ((x - 30) * (x - 30) + (y - 14) * (y - 14)) * 2;
            let ridge = if (x + y) % 11 < 2 { 40 } else { 0 };
            let noise = ((x * 73_856_093) ^ (y * 19_349_663)).rem_euclid(9);
            (hill.max(300) + ridge + noise) as f64
        })
        .collect();
    Grid {
        width: w,
        height: h,
        values_m,
        quantum_m: Some(1.0),
    }
}

// ---------------------------------------------------------------------------------------
// Hostile bytes.

fn hostile(paths: &[Case], models: &[(String, CodecModel)]) -> Vec<Case> {
    let mut rng = Rng(99);
    let mut out = Vec::new();
    // Random payloads behind a valid header and checksum, in a spread of contexts: they
    // reach the entropy decoder, which must fail or succeed exactly as here.
    let contexts: Vec<&Case> = paths
        .iter()
        .filter(|c| c.model == "trained")
        .step_by(3)
        .collect();
    for (k, base) in contexts.iter().enumerate() {
        for r in 0..12 {
            let len = match r % 4 {
                0 => rng.below(4),
                1 => rng.below(16),
                2 => rng.below(48),
                _ => rng.below(120),
            } as usize;
            let payload: Vec<u8> = (0..len)
                .map(|_| {
                    // Some streams of mostly ones or zeros (long unary runs and escapes).
                    match r % 3 {
                        0 => rng.below(256) as u8,
                        1 => 0xFF ^ (1 << rng.below(8)) as u8,
                        _ => (rng.below(4) as u8) << 6,
                    }
                })
                .collect();
            out.push(Case {
                name: format!("random/{k}_{r}"),
                blob: sealed(base, &payload),
                ..clone_context(base)
            });
        }
    }
    // Valid blobs with a few payload bytes changed and the checksum patched.
    let small = paths.iter().filter(|c| c.blob.len() <= 120);
    for (k, base) in small.step_by(2).enumerate() {
        for r in 0..3 {
            let mut payload = base.blob[blob::HEADER_BYTES..].to_vec();
            if payload.is_empty() {
                continue;
            }
            for _ in 0..1 + rng.below(3) {
                let at = rng.below(payload.len() as u64) as usize;
                payload[at] ^= 1 + rng.below(255) as u8;
            }
            if r == 2 {
                payload.truncate(payload.len() / 2);
            }
            out.push(Case {
                name: format!("patched/{k}_{r}"),
                blob: sealed(base, &payload),
                ..clone_context(base)
            });
        }
    }
    // Header errors and truncations of one blob, and a blob under another key.
    let base = paths
        .iter()
        .find(|c| c.name.starts_with("medium_lossless"))
        .unwrap();
    let b = &base.blob;
    let mut header = vec![
        ("too_short_0", b[..0].to_vec()),
        ("too_short_2", b[..2].to_vec()),
        ("header_only", b[..3].to_vec()),
        ("cut_half", b[..b.len() / 2].to_vec()),
        ("cut_last", b[..b.len() - 1].to_vec()),
    ];
    for (name, head) in [
        ("version_3", 0x35u8),
        ("version_5", 0x55),
        ("version_0", 0x05),
        ("size_16", 0x44),
        ("size_64", 0x46),
    ] {
        let mut x = b.clone();
        x[0] = head;
        header.push((name, x));
    }
    let mut x = b.clone();
    x[1] ^= 0x10;
    header.push(("checksum_flip", x));
    let mut x = b.clone();
    x[b.len() - 1] ^= 1;
    header.push(("payload_flip", x));
    for (name, bytes) in header {
        out.push(Case {
            name: format!("header/{name}"),
            blob: bytes,
            ..clone_context(base)
        });
    }
    let mut wrong_key = clone_context(base);
    wrong_key.name = "header/wrong_key".into();
    wrong_key.blob = b.clone();
    wrong_key.key.push(1);
    wrong_key.context = None;
    out.push(wrong_key);
    // Every outcome of the decoder occurs.
    let kinds: std::collections::BTreeSet<String> = out
        .iter()
        .map(|c| {
            let m = &models.iter().find(|(n, _)| *n == c.model).unwrap().1;
            c.decode(m).map_or_else(|e| error_kind(&e), |_| "ok".into())
        })
        .collect();
    for kind in [
        "ok",
        "TooShort",
        "Version",
        "Size",
        "Checksum",
        "Entropy.Truncated",
        "Entropy.EscapeTooLong",
    ] {
        assert!(
            kinds.contains(kind),
            "no hostile vector gives {kind}: {kinds:?}"
        );
    }
    out
}

/// `payload` behind a valid header and checksum for `base`'s context.
fn sealed(base: &Case, payload: &[u8]) -> Vec<u8> {
    let head = (blob::VERSION << 4) | base.n.trailing_zeros() as u8;
    let crc = blob::crc16(&[&base.key, &[head], payload]);
    let mut out = vec![head];
    out.extend_from_slice(&crc.to_le_bytes());
    out.extend_from_slice(payload);
    out
}

fn clone_context(c: &Case) -> Case {
    Case {
        name: c.name.clone(),
        blob: Vec::new(),
        key: c.key.clone(),
        n: c.n,
        group: c.group,
        cells: c.cells.clone(),
        owned: c.owned,
        step: c.step,
        model: c.model.clone(),
        context: Some(c.name.clone()),
    }
}

// ---------------------------------------------------------------------------------------
// Tables.

fn tables() -> String {
    // A model with every context explicit and byte k % 256 at context k (the JavaScript
    // test builds the same bytes): its probabilities (read from its Debug form: the field
    // is private) are MODEL_PROBS, repeated.
    let mut explicit = vec![0xFFu8; CONTEXTS.div_ceil(8)];
    let last = explicit.len() - 1;
    explicit[last] = (1u8 << (CONTEXTS % 8)) - 1;
    explicit.extend((0..CONTEXTS).map(|k| (k % 256) as u8));
    let model = CodecModel::from_bytes(&explicit).unwrap();
    let debug = format!("{model:?}");
    let inner = &debug[debug.find('[').unwrap() + 1..debug.rfind(']').unwrap()];
    let probs: Vec<u16> = inner.split(", ").map(|p| p.parse().unwrap()).collect();
    assert_eq!(probs.len(), CONTEXTS);
    let class_bounds: Vec<u64> = (0..=63).map(entropy::class_bound).collect();
    let gammas = [
        0u64,
        1,
        2,
        3,
        4,
        5,
        6,
        7,
        8,
        100,
        12_345,
        1 << 20,
        1 << 30,
        1 << 31,
    ];
    let gamma_classes: Vec<u8> = gammas.iter().map(|&g| entropy::gamma_class(g)).collect();
    let sides: Vec<String> = (0..=255u8)
        .map(|e| {
            let (c, f) = entropy::split_side(e);
            format!("[{c},{f}]")
        })
        .collect();
    let mut dq = Vec::new();
    for q in [
        0,
        1,
        -1,
        2,
        -7,
        1000,
        -1000,
        65_535,
        i32::MAX,
        i32::MIN,
        -i32::MAX,
    ] {
        for s in [256u32, 257, 300, 511, 4000, 16_371, 65_536, u32::MAX] {
            dq.push(format!("[{q},{s},{}]", encode::dequantize(q, s)));
        }
    }
    let mut rgb = Vec::new();
    for (r, g, b) in [
        (0, 0, 0),
        (255, 255, 255),
        (255, 0, 0),
        (0, 255, 0),
        (0, 0, 255),
        (12, 200, 99),
        (1, 2, 3),
    ] {
        let (y, co, cg) = colour::rgb_to_ycocg_r(r, g, b);
        assert_eq!(colour::ycocg_r_to_rgb(y, co, cg), (r, g, b));
        rgb.push(format!("[{r},{g},{b},{y},{co},{cg}]"));
    }
    let mut s = String::new();
    s.push_str("{\"about\":\"entropy, dequantisation and colour tables (written by codec/tests/js_golden.rs; bless with QUINCUNX_BLESS=1)\",\n");
    let _ = writeln!(s, "\"contexts\":{CONTEXTS},");
    let _ = writeln!(s, "\"crc16_123456789\":{},", blob::crc16(&[b"123456789"]));
    let _ = writeln!(s, "\"modelProbs\":{},", list(&probs[..256]));
    let _ = writeln!(s, "\"classBounds\":{},", list(&class_bounds));
    let _ = writeln!(
        s,
        "\"gammaClasses\":[{},{}],",
        list(gammas),
        list(&gamma_classes)
    );
    let _ = writeln!(s, "\"splitSide\":[{}],", sides.join(","));
    let _ = writeln!(s, "\"dequantize\":[{}],", dq.join(","));
    let _ = writeln!(s, "\"ycocgR\":[{}]", rgb.join(","));
    s.push_str("}\n");
    s
}

// ---------------------------------------------------------------------------------------

/// Asserts that the encoder paths cover what the JavaScript decoder must get right.
fn check_coverage(cases: &[Case], models: &[(String, CodecModel)]) {
    let mut seen = std::collections::BTreeSet::new();
    for c in cases {
        let model = &models.iter().find(|(n, _)| *n == c.model).unwrap().1;
        let got = c.decode(model).unwrap();
        let raster = c.name.starts_with("raster");
        if got.child_classes.iter().any(|&e| e & NO_DATA != 0) {
            seen.insert(if raster { "raster no-data" } else { "no-data" });
        }
        if c.cells.as_ref().is_some_and(|m| m.iter().any(|&v| !v)) {
            seen.insert(if raster { "raster mask" } else { "mask" });
        }
        if got.q.iter().all(|&x| x == 0) {
            seen.insert("all zero");
        }
        if got.q.contains(&i32::MIN) && got.q.contains(&i32::MAX) {
            seen.insert("extremes");
        }
        if c.step > 256 {
            let n = c.n;
            let b = n.min(4);
            let dense = (0..n / b).any(|bi| {
                (0..n / b).any(|bj| {
                    (0..b * b)
                        .filter(|k| got.q[(bi * b + k / b) * n + bj * b + k % b] != 0)
                        .count()
                        >= HIDDEN_SIGN_MIN
                })
            });
            seen.insert(if dense {
                "hidden sign"
            } else {
                "deferred sign"
            });
            if raster {
                seen.insert("raster quantised");
            }
        } else if raster {
            seen.insert("raster exact");
        }
    }
    for what in [
        "no-data",
        "raster no-data",
        "mask",
        "raster mask",
        "all zero",
        "extremes",
        "hidden sign",
        "deferred sign",
        "raster quantised",
        "raster exact",
    ] {
        assert!(seen.contains(what), "no vector covers {what}: {seen:?}");
    }
}

#[test]
fn js_golden_vectors_are_unchanged() {
    let bless = std::env::var("QUINCUNX_BLESS").is_ok_and(|v| v == "1");
    let (golden_models, golden) = committed_golden();
    let (path_models, paths) = encoder_paths();
    check_coverage(&paths, &path_models);
    let hostile_cases = hostile(&paths, &path_models);
    // Matrices decoded with the default model are those of the trained one: hashed.
    let json = |cases: &[Case], models: &[(String, CodecModel)], full: bool| -> Vec<String> {
        cases
            .iter()
            .map(|c| c.json(models, full && c.model != "default"))
            .collect()
    };
    let files = [
        (
            "codec-committed-golden.json",
            file_text(
                "the golden blobs of codec/tests/golden",
                &golden_models,
                &json(&golden, &golden_models, true),
            ),
        ),
        (
            "codec-encoder-paths.json",
            file_text(
                "blobs covering every decoding path",
                &path_models,
                &json(&paths, &path_models, true),
            ),
        ),
        (
            "codec-hostile.json",
            file_text(
                "random and corrupted blobs with blob::decode's result or error; contexts and models are those of codec-encoder-paths.json",
                &[],
                &json(&hostile_cases, &path_models, false),
            ),
        ),
        ("codec-tables.json", tables()),
    ];
    let total: usize = files.iter().map(|(_, t)| t.len()).sum();
    for (name, text) in &files {
        println!(
            "{name}: {} bytes, {} lines",
            text.len(),
            text.lines().count()
        );
    }
    assert!(total < 200_000, "golden vectors take {total} bytes");
    let dir = out_dir();
    if bless {
        std::fs::create_dir_all(&dir).unwrap();
        for (name, text) in &files {
            std::fs::write(dir.join(name), text).unwrap();
        }
        println!(
            "blessed {} files ({total} bytes) in {}",
            files.len(),
            dir.display()
        );
        return;
    }
    let mut problems = Vec::new();
    for (name, text) in &files {
        match std::fs::read_to_string(dir.join(name)) {
            Ok(committed) if committed == *text => {}
            Ok(committed) => {
                let line = committed
                    .lines()
                    .zip(text.lines())
                    .position(|(a, b)| a != b)
                    .unwrap_or(committed.lines().count().min(text.lines().count()));
                problems.push(format!("{name}: differs from line {}", line + 1));
            }
            Err(e) => problems.push(format!("{name}: {e}")),
        }
    }
    assert!(
        problems.is_empty(),
        "the JavaScript decoder's golden vectors in {} are stale:\n  {}\n\
         After a deliberate change of the encoder or of the format (bump blob::VERSION and \
         port it to web-demo/js/codec.mjs), re-bless with \
         `QUINCUNX_BLESS=1 cargo test --release -p quincunx-codec --test js_golden` and run \
         `node --test web-demo/test/`.",
        dir.display(),
        problems.join("\n  ")
    );
}
