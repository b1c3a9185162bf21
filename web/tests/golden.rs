//! What the browser's decoder must give: answers of small repositories built in memory,
//! decoded natively through [`Module`] (the calls the WebAssembly exports make), written
//! to `web-demo/test/golden/wasm-decode.json`, where `web-demo/test/wasm.test.mjs` checks
//! that the module (`web-demo/js/quincunx.wasm`) decodes each to the same bytes (SHA-256
//! of the output) or fails with the same message.
//!
//! The cases cover every coding path: the committed golden blobs of `codec/tests/golden`
//! (versions 4 and 5), an encoded raster in the RMS and max-error modes with packages,
//! synthetic matrices in real contexts (every diamond size from 2 to 64, lossless and
//! quantised levels with sign hiding, masks, side information with no-data flags,
//! magnitude escapes up to `i32::MIN` and `i32::MAX`, all-zero matrices, a trained and
//! the default model), a sparse planar repository with a coverage, a colour layer (three
//! framed channels), and small planets (dense, sparse, colour). Each case also holds
//! hostile answers (truncated, mutated, resealed and random payloads, packages that lie,
//! keys of no diamond, layers that do not exist) with the native error text.
//!
//! `QUINCUNX_BLESS=1` writes the file; otherwise the test checks that the committed file
//! is exactly what the code gives now, so a change of the format, the encoder or an
//! error message shows up here (re-bless, rebuild the module, run the node test).
#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::collections::{BTreeMap, BTreeSet};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use quincunx_codec::blob::{self, BlobContext};
use quincunx_codec::encode::{Encoded, Grid, RateMode, encode, encode_sphere};
use quincunx_codec::entropy::{self, CodecModel, ContextCounts, HIDDEN_SIGN_MIN, NO_DATA};
use quincunx_codec::raster::RasterGeometry;
use quincunx_meta::answer::{self, IdSpace};
use quincunx_meta::channels::frame_channels;
use quincunx_meta::{ChannelCoding, Domain, LevelStats, Metadata, Rate};
use quincunx_web::api::Module;

mod common;
use common::{geometry_of, metadata, options, planet, raster};
use serde_json::{Value, json};

type Key = [i64; 3];

const GOLDEN: &str = "wasm-decode.json";

/// The workspace root.
fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR")).parent().unwrap()
}

fn golden_path() -> PathBuf {
    root().join("web-demo/test/golden").join(GOLDEN)
}

fn codec_golden_dir() -> PathBuf {
    root().join("codec/tests/golden")
}

// ---------------------------------------------------------------------------------------
// Encodings of the file.

/// SHA-256 (hex), what node:crypto gives.
fn sha256(data: &[u8]) -> String {
    use sha2::Digest;
    hex(&sha2::Sha256::digest(data))
}

/// Lower-case hex.
fn hex(bytes: &[u8]) -> String {
    bytes.iter().fold(String::new(), |mut s, b| {
        let _ = write!(s, "{b:02x}");
        s
    })
}

/// Standard padded base64 (`Buffer.from(text, "base64")` in node).
fn base64(bytes: &[u8]) -> String {
    const ABC: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut out = String::with_capacity(bytes.len().div_ceil(3) * 4);
    for chunk in bytes.chunks(3) {
        let byte = |k: usize| u32::from(chunk.get(k).copied().unwrap_or(0));
        let v = (byte(0) << 16) | (byte(1) << 8) | byte(2);
        for k in 0..4 {
            out.push(if k <= chunk.len() {
                ABC[(v >> (18 - 6 * k)) as usize & 63] as char
            } else {
                '='
            });
        }
    }
    out
}

#[test]
fn base64_known_answers() {
    for (bytes, text) in [
        (&b""[..], ""),
        (b"f", "Zg=="),
        (b"fo", "Zm8="),
        (b"foo", "Zm9v"),
        (b"foob", "Zm9vYg=="),
        (b"foobar", "Zm9vYmFy"),
        (&[0xfb, 0xff, 0xbf], "+/+/"),
    ] {
        assert_eq!(base64(bytes), text);
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
// Repositories in memory.

/// A repository as a server holds it: metadata, blobs by centre, storage keys.
struct Repo {
    name: String,
    meta: Metadata,
    /// Stored blobs by centre (a colour repository's framed).
    blobs: BTreeMap<Key, Vec<u8>>,
    /// Storage keys by centre (what a blob's checksum covers).
    keys: BTreeMap<Key, Vec<u8>>,
}

impl Repo {
    fn space(&self) -> IdSpace {
        IdSpace::of(&self.meta).unwrap()
    }

    fn level(&self, c: Key) -> u32 {
        self.space().level(c).unwrap()
    }

    /// What the server answers for a package of `c` (`quincunx_store`'s
    /// `Repository::package`, over the blobs in memory).
    fn package(&self, c: Key) -> Option<Vec<u8>> {
        let limit = self.meta.inline_max_bytes? as usize;
        self.package_within(&self.space(), c, usize::MAX, limit)
    }

    fn package_within(&self, space: &IdSpace, c: Key, cap: usize, limit: usize) -> Option<Vec<u8>> {
        let level = space.level(c).ok()?;
        let blob = self.blobs.get(&c)?;
        let mut size = 1 + answer::varint_len(blob.len()) + blob.len();
        if size > cap {
            return None;
        }
        let mut children = Vec::new();
        if level + 1 < self.meta.levels {
            for (i, k) in space.owned_children(c).unwrap().into_iter().enumerate() {
                if let Some(a) = self.package_within(space, k, limit, limit) {
                    size += answer::varint_len(a.len()) + a.len();
                    if size > cap {
                        return None;
                    }
                    children.push((i, a));
                }
            }
        }
        Some(answer::write(blob, &children, true))
    }
}

fn channel(
    name: &str,
    steps: Vec<u32>,
    model: &CodecModel,
    roots: Vec<Vec<i32>>,
    rate: Rate,
) -> ChannelCoding {
    ChannelCoding {
        name: name.into(),
        value_scale: 1.0,
        value_offset: 0.0,
        steps,
        model: model.to_bytes(),
        roots,
        rate,
    }
}

/// A repository of `meta` holding `blobs`: level statistics filled in, checked as every
/// reader checks it.
fn repo(name: &str, mut meta: Metadata, blobs: BTreeMap<Key, Vec<u8>>) -> Repo {
    let space = IdSpace::of(&meta).unwrap();
    let mut stats: BTreeMap<u32, LevelStats> = BTreeMap::new();
    let mut keys = BTreeMap::new();
    for (c, b) in &blobs {
        let (key, level) = space.key_level(*c).unwrap();
        keys.insert(*c, key);
        let s = stats.entry(level).or_default();
        s.level = level;
        s.blobs += 1;
        s.bytes += b.len() as u64;
    }
    meta.level_stats = stats.into_values().collect();
    meta.validate().unwrap();
    Repo {
        name: name.into(),
        meta,
        blobs,
        keys,
    }
}

/// A repository of encoded channels `encs` (one geometry; three: colour).
fn encoded_repo(name: &str, encs: &[&Encoded], inline_max_bytes: Option<u32>) -> Repo {
    let e = encs[0];
    let (domain, m, levels, extent) = geometry_of(e);
    let names = if encs.len() == 3 {
        &["Y", "Co", "Cg"][..]
    } else {
        &["height"][..]
    };
    let channels = encs
        .iter()
        .zip(names)
        .map(|(e, name)| ChannelCoding {
            value_scale: e.value_scale_m,
            value_offset: e.value_offset_m,
            ..channel(
                name,
                e.steps.clone(),
                &e.model,
                e.roots.clone(),
                Rate::Lossless,
            )
        })
        .collect();
    let coverage = e.coverage.as_ref().map(|c| c.to_bytes());
    let meta = metadata(
        domain,
        m,
        e.n,
        levels,
        extent,
        channels,
        coverage,
        inline_max_bytes,
    );
    let space = IdSpace::of(&meta).unwrap();
    let centre = |k: &[u8]| -> Key {
        match space {
            IdSpace::Planar(d) => {
                let id = d.id_from_key(k).unwrap();
                [id.x, id.y, 0]
            }
            IdSpace::Sphere(d) => d.id_from_key(k).unwrap().c,
        }
    };
    let by_key: Vec<_> = encs.iter().map(|e| e.blobs_by_key().unwrap()).collect();
    let all: BTreeSet<&Vec<u8>> = by_key.iter().flat_map(|m| m.keys()).collect();
    let blobs = all
        .into_iter()
        .filter_map(|k| {
            let parts: Vec<Option<&[u8]>> =
                by_key.iter().map(|m| m.get(k).map(Vec::as_slice)).collect();
            Some((centre(k), frame_channels(&parts)?))
        })
        .collect();
    repo(name, meta, blobs)
}

/// A 45 x 29 terrain (integer arithmetic only): a hill, a steep ridge and a flat plateau
/// whose diamonds have no details (their owners flag them no-data).
fn plateau_raster() -> Grid {
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
// The committed golden blobs of codec/tests/golden (65 x 65, N = 32).

/// The root grid of `root.bin` (`encode::root_grid_bytes`: zigzag varints of deltas).
fn root_grid(bytes: &[u8]) -> Vec<i32> {
    let mut out = Vec::new();
    let (mut prev, mut z, mut shift) = (0i64, 0u64, 0);
    for &b in bytes {
        z |= u64::from(b & 0x7F) << shift;
        shift += 7;
        if b & 0x80 == 0 {
            prev += (z >> 1) as i64 ^ -((z & 1) as i64);
            out.push(prev as i32);
            (z, shift) = (0, 0);
        }
    }
    out
}

fn committed_golden(mode: &str) -> Repo {
    let dir = codec_golden_dir().join(mode);
    let read = |name: &str| std::fs::read(dir.join(name)).unwrap();
    let params: Value = serde_json::from_slice(&read("steps.json")).unwrap();
    let (w, h, n) = (65, 65, 32);
    assert_eq!(params["width"], w);
    assert_eq!(params["n"], n);
    let steps: Vec<u32> = params["steps"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s.as_u64().unwrap() as u32)
        .collect();
    let model = CodecModel::from_bytes(&read("model.bin")).unwrap();
    let root = root_grid(&read("root.bin"));
    assert_eq!(root.len(), (n + 1) * (n + 1));
    let geom = RasterGeometry::new(w, h, n).unwrap();
    let rate = if mode == "lossless" {
        Rate::Lossless
    } else {
        Rate::Rms(2.0)
    };
    let ch = ChannelCoding {
        value_scale: params["value_scale_m"].as_f64().unwrap(),
        value_offset: params["value_offset_m"].as_f64().unwrap(),
        ..channel("height", steps, &model, vec![root], rate)
    };
    let extent = [w as u64, h as u64];
    let meta = metadata(
        Domain::Planar,
        geom.domain().m(),
        n,
        geom.detail_levels(),
        extent,
        vec![ch],
        None,
        None,
    );
    let mut blobs = BTreeMap::new();
    for l in 0..geom.detail_levels() {
        for (i, s) in geom.level(l).iter().enumerate() {
            if let Ok(b) = std::fs::read(dir.join(format!("{l}_{i}.bin"))) {
                blobs.insert([s.id.x, s.id.y, 0], b);
            }
        }
    }
    assert!(blobs.len() >= 5, "{mode}: golden blobs missing");
    repo(&format!("golden/{mode}"), meta, blobs)
}

// ---------------------------------------------------------------------------------------
// Synthetic matrices in the contexts of a real raster geometry.

/// How a synthetic matrix is filled.
#[derive(Clone, Copy, Debug)]
enum Style {
    /// All zero, with every kind of side information.
    Zero,
    /// `density` cells in 16 nonzero, magnitudes below `amp`.
    Random { density: u64, amp: u64 },
    /// Extreme magnitudes: `i32::MIN`, `i32::MAX`, saturated activities, long escapes.
    Escapes,
}

const STYLES: [(&str, Style); 6] = [
    ("zero", Style::Zero),
    ("sparse", Style::Random { density: 1, amp: 6 }),
    (
        "medium",
        Style::Random {
            density: 5,
            amp: 30,
        },
    ),
    (
        "dense",
        Style::Random {
            density: 12,
            amp: 200,
        },
    ),
    (
        "dense_small",
        Style::Random {
            density: 14,
            amp: 3,
        },
    ),
    ("escapes", Style::Escapes),
];

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

fn matrix(rng: &mut Rng, n: usize, style: Style) -> Vec<i32> {
    match style {
        Style::Zero => vec![0; n * n],
        Style::Random { density, amp } => random_matrix(rng, n, density, amp),
        Style::Escapes => {
            let mut q = random_matrix(rng, n, 3, 20);
            q[0] = i32::MIN;
            q[n * n - 1] = i32::MAX;
            if n >= 8 {
                q[n + 5] = 1 << 20;
                q[n + 6] = -(1 << 24) - 3;
                q[3 * n + 4] = 70_000;
                q[5 * n + 1] = -5_000;
            }
            // A block of extremes: activities saturate, the hidden sign of a dense block
            // may be that of `i32::MIN`.
            if n >= 16 {
                for i in n / 4..n / 4 + 4 {
                    for j in n / 4..n / 4 + 8 {
                        q[i * n + j] = match ((i + j) % 2, j < n / 4 + 4) {
                            (0, true) => i32::MAX,
                            (_, true) => i32::MIN + 1,
                            (0, false) => i32::MIN,
                            _ => 1 << 29,
                        };
                    }
                }
            }
            q
        }
    }
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

/// One synthetic blob's content in the context of slot `index` of `level`.
struct Synthetic {
    level: usize,
    index: usize,
    style: &'static str,
    classes: Vec<u8>,
    q: Vec<i32>,
}

/// The quantiser steps of a synthetic repository: lossless, then quantised levels (sign
/// hiding), in turn.
fn synthetic_step(level: usize) -> u32 {
    [256, 700, 4000][level % 3]
}

/// A synthetic matrix's blob: its centre, what it holds, its bytes.
type Matrix = (Key, String, Vec<u8>);

/// A planar repository of `w x h`, N = `n`, and synthetic matrices of every style at
/// every level in its contexts (a masked slot for every other style, where the level has
/// one), coded with a model trained on them or with the default model. The repository
/// holds the first matrix of each slot.
fn synthetic(
    n: usize,
    w: usize,
    h: usize,
    trained: bool,
    styles: &[(&'static str, Style)],
) -> (Repo, Vec<Matrix>) {
    let geom = RasterGeometry::new(w, h, n).unwrap();
    let levels = geom.detail_levels();
    let steps: Vec<u32> = (0..levels).map(synthetic_step).collect();
    let mut rng = Rng(n as u64 * 31 + u64::from(trained));
    let mut contents = Vec::new();
    for level in 0..levels {
        let slots = geom.level(level);
        let masked: Vec<usize> = (0..slots.len())
            .filter(|&i| slots[i].mask.is_some())
            .collect();
        for (k, &(style_name, style)) in styles.iter().enumerate() {
            let index = if k % 2 == 1 && !masked.is_empty() {
                masked[(k / 2 + level) % masked.len()]
            } else {
                (k * 7 + level) % slots.len()
            };
            let ctx = geom.blob_context(level, index);
            let mut q = matrix(&mut rng, n, style);
            if let Some(mask) = ctx.mask {
                for (x, &ok) in q.iter_mut().zip(mask.cells()) {
                    if !ok {
                        *x = 0;
                    }
                }
            }
            if steps[level] > 256 {
                obey_parity(n, &mut q);
            }
            let classes = (0..ctx.owned_children)
                .map(|c| match style {
                    Style::Zero => [0, 5 | NO_DATA, 63, 1 | NO_DATA][c % 4],
                    _ => {
                        let class = rng.below(64) as u8;
                        if class > 0 && rng.below(2) == 0 {
                            class | NO_DATA
                        } else {
                            class
                        }
                    }
                })
                .collect();
            contents.push(Synthetic {
                level,
                index,
                style: style_name,
                classes,
                q,
            });
        }
    }
    let context = |s: &Synthetic| BlobContext {
        step: steps[s.level],
        ..geom.blob_context(s.level, s.index)
    };
    let model = if trained {
        let mut counts = ContextCounts::default();
        for s in &contents {
            let ctx = context(s);
            entropy::write_gammas(&mut counts, ctx.group, &s.classes);
            let cells = ctx.mask.map(|m| m.cells());
            entropy::write_matrix(&mut counts, ctx.group, n, &s.q, cells, ctx.hides_signs());
        }
        CodecModel::from_counts(&counts)
    } else {
        CodecModel::default()
    };
    let mut blobs = BTreeMap::new();
    let mut matrices = Vec::new();
    for s in &contents {
        let ctx = context(s);
        let bytes = blob::encode(&ctx, &model, &s.classes, &s.q);
        // The decoder gives back what was encoded (a no-data flag only with a class).
        let got = blob::decode(&bytes, &ctx, &model).unwrap();
        assert_eq!(got.q, s.q, "n {n} level {} {}", s.level, s.style);
        let classes: Vec<u8> = s
            .classes
            .iter()
            .map(|&e| if e & !NO_DATA == 0 { 0 } else { e })
            .collect();
        assert_eq!(got.child_classes, classes);
        let id = geom.level(s.level)[s.index].id;
        let c = [id.x, id.y, 0];
        blobs.entry(c).or_insert_with(|| bytes.clone());
        matrices.push((c, format!("{} at level {}", s.style, s.level), bytes));
    }
    let roots = vec![vec![0; (n + 1) * (n + 1)]];
    let ch = channel("height", steps, &model, roots, Rate::Rms(1.0));
    let extent = [w as u64, h as u64];
    let meta = metadata(
        Domain::Planar,
        geom.domain().m(),
        n,
        levels,
        extent,
        vec![ch],
        None,
        None,
    );
    let model_name = if trained { "trained" } else { "default" };
    let r = repo(&format!("paths/synthetic_n{n}_{model_name}"), meta, blobs);
    (r, matrices)
}

// ---------------------------------------------------------------------------------------
// Answers.

/// One answer the decoder is given.
struct Answer {
    what: String,
    layer: u8,
    key: Key,
    packaged: bool,
    bytes: Vec<u8>,
    /// The storage key, for a bare elevation blob (the test reseals mutated payloads).
    storage_key: Option<Vec<u8>>,
}

/// A session and the answers its decoder is given.
struct Case {
    name: String,
    open: Value,
    answers: Vec<Answer>,
}

fn open(elevation: &Repo, colour: Option<&Repo>) -> Value {
    let layer = |r: &Repo| json!({"name": r.name, "meta": r.meta});
    json!({
        "elevation": layer(elevation),
        "colour": colour.map(layer),
        "config": {},
    })
}

fn key_name(c: Key, space: &IdSpace) -> String {
    match space.dims() {
        2 => format!("{}/{}", c[0], c[1]),
        _ => format!("{}/{}/{}", c[0], c[1], c[2]),
    }
}

/// The blobs of `r` (every blob above the finest level, at most `finest` of it, evenly
/// spread) bare, and the packages among them that carry children (at most `packages`).
fn answers(r: &Repo, layer: u8, finest: usize, packages: usize) -> Vec<Answer> {
    let space = r.space();
    let last = r.meta.levels.saturating_sub(1);
    let in_finest = r.blobs.keys().filter(|c| r.level(**c) == last).count();
    let stride = in_finest.div_ceil(finest.max(1)).max(1);
    let mut out = Vec::new();
    let mut k = 0;
    for (c, b) in &r.blobs {
        if r.level(*c) == last {
            k += 1;
            if (k - 1) % stride != 0 {
                continue;
            }
        }
        out.push(Answer {
            what: format!("blob {}", key_name(*c, &space)),
            layer,
            key: *c,
            packaged: false,
            bytes: b.clone(),
            storage_key: (layer == 0).then(|| r.keys[c].clone()),
        });
    }
    let carrying: Vec<(Key, Vec<u8>)> = r
        .blobs
        .iter()
        .filter_map(|(c, b)| {
            let p = r.package(*c)?;
            // Only packages that carry something: `0xF0` alone is a lone blob.
            (p[0] != 0xF0 || p.len() > 1 + answer::varint_len(b.len()) + b.len()).then_some((*c, p))
        })
        .collect();
    let stride = carrying.len().div_ceil(packages.max(1)).max(1);
    for (c, p) in carrying.into_iter().step_by(stride) {
        out.push(Answer {
            what: format!("package {}", key_name(c, &space)),
            layer,
            key: c,
            packaged: true,
            bytes: p,
            storage_key: None,
        });
    }
    out
}

/// `payload` behind the header `head` and a valid checksum for storage key `key`.
fn sealed(head: u8, key: &[u8], payload: &[u8]) -> Vec<u8> {
    let crc = blob::crc16(&[key, &[head], payload]);
    let mut out = vec![head];
    out.extend_from_slice(&crc.to_le_bytes());
    out.extend_from_slice(payload);
    out
}

/// Hostile answers made from `seeds` of `r`'s blobs of `layer` (the largest ones, spread
/// over the levels): truncations, header damage, a blob under another key, payloads
/// patched or random behind a valid checksum (elevation), packages that lie, keys of no
/// diamond, layers that do not exist.
fn hostile(r: &Repo, layer: u8, seeds: usize, rng: &mut Rng) -> Vec<Answer> {
    let space = r.space();
    let mut out = Vec::new();
    let mut push = |what: String, key: Key, packaged: bool, bytes: Vec<u8>| {
        out.push(Answer {
            what: format!("hostile: {what}"),
            layer,
            key,
            packaged,
            storage_key: (layer == 0).then(|| r.keys.get(&key).cloned()).flatten(),
            bytes,
        });
    };
    let mut by_size: Vec<(&Key, &Vec<u8>)> = r.blobs.iter().collect();
    by_size.sort_by_key(|(c, b)| (std::cmp::Reverse(b.len()), **c));
    let seed_blobs: Vec<(Key, Vec<u8>)> = by_size
        .iter()
        .step_by((by_size.len() / seeds.max(1)).max(1))
        .take(seeds)
        .map(|(c, b)| (**c, (*b).clone()))
        .collect();
    for (c, b) in &seed_blobs {
        let name = key_name(*c, &space);
        for len in [0, 2, 3, b.len() / 2, b.len() - 1] {
            push(
                format!("{name} cut to {len} bytes"),
                *c,
                false,
                b[..len].to_vec(),
            );
        }
        let mut longer = b.clone();
        longer.push(0);
        push(format!("{name} and a byte"), *c, false, longer);
        if layer == 1 {
            let mut x = b.clone();
            let mid = x.len() / 2;
            x[mid] ^= 0x21;
            push(format!("{name} with a byte flipped"), *c, false, x);
            continue;
        }
        let log_n = b[0] & 0x0F;
        for (what, head) in [
            ("version 3", 0x30 | log_n),
            ("version 6", 0x60 | log_n),
            ("version 0", log_n),
            ("another size", (b[0] & 0xF0) | ((log_n + 1) & 0x0F)),
        ] {
            let mut x = b.clone();
            x[0] = head;
            push(format!("{name} of {what}"), *c, false, x);
        }
        let mut x = b.clone();
        x[1] ^= 0x10;
        push(format!("{name} with its checksum flipped"), *c, false, x);
        let mut x = b.clone();
        *x.last_mut().unwrap() ^= 1;
        push(format!("{name} with its last byte flipped"), *c, false, x);
        // The same bytes under another diamond of the same level.
        if let Some(other) = r
            .blobs
            .keys()
            .find(|o| *o != c && r.level(**o) == r.level(*c))
        {
            push(
                format!("{name} under {}", key_name(*other, &space)),
                *other,
                false,
                b.clone(),
            );
        }
        // Payloads behind a valid checksum reach the entropy decoder.
        let key = &r.keys[c];
        let payload = &b[blob::HEADER_BYTES..];
        for k in 0..4 {
            let mut p = payload.to_vec();
            if p.is_empty() {
                break;
            }
            for _ in 0..1 + rng.below(3) {
                let at = rng.below(p.len() as u64) as usize;
                p[at] ^= 1 + rng.below(255) as u8;
            }
            if k == 3 {
                p.truncate(p.len() / 2);
            }
            push(
                format!("{name} patched and resealed ({k})"),
                *c,
                false,
                sealed(b[0], key, &p),
            );
        }
        for k in 0..6 {
            let len = [4, 16, 48, 120][k % 4];
            let len = rng.below(len) as usize;
            let p: Vec<u8> = (0..len)
                .map(|_| match k % 3 {
                    0 => rng.below(256) as u8,
                    // Mostly ones: long unary runs and escapes.
                    1 => 0xFF ^ (1 << rng.below(8)) as u8,
                    _ => (rng.below(4) as u8) << 6,
                })
                .collect();
            push(
                format!("{name} random payload ({k})"),
                *c,
                false,
                sealed(b[0], key, &p),
            );
        }
    }
    // Packages that lie.
    if r.meta.inline_max_bytes.is_some() {
        let (c, b) = &seed_blobs[0];
        let name = key_name(*c, &space);
        push(
            format!("{name} bare, asked as a package"),
            *c,
            true,
            b.clone(),
        );
        let p = r.package(*c).unwrap();
        push(format!("package {name} taken bare"), *c, false, p.clone());
        push(
            format!("package {name} cut by one"),
            *c,
            true,
            p[..p.len() - 1].to_vec(),
        );
        let mut longer = p.clone();
        longer.push(7);
        push(format!("package {name} and a byte"), *c, true, longer);
        // A finest-level diamond's package carrying a child; one claiming a fifth child.
        if let Some((f, fb)) = r
            .blobs
            .iter()
            .find(|(k, _)| r.level(**k) + 1 == r.meta.levels)
        {
            let lying = answer::write(fb, &[(0, answer::write(fb, &[], true))], true);
            push(
                format!("package {} with a child", key_name(*f, &space)),
                *f,
                true,
                lying,
            );
        }
        let mut fifth = answer::write(b, &[], true);
        fifth[0] |= 0x08;
        fifth.extend_from_slice(&[2, 0x50, 0]);
        push(
            format!("package {name} carrying owned child 3"),
            *c,
            true,
            fifth,
        );
    }
    // Keys of no diamond here, layers that do not exist.
    let (c, b) = &seed_blobs[0];
    let size = match space {
        IdSpace::Planar(d) => d.size(),
        IdSpace::Sphere(d) => d.size(),
    };
    for key in [
        [size * 4, 3, 0],
        [-1, -1, 0],
        [1, 2, 3],
        [size, size, size],
        [0, 0, 0],
    ] {
        push(
            format!("blob {} at {key:?}", key_name(*c, &space)),
            key,
            false,
            b.clone(),
        );
    }
    if layer == 0 {
        let name = key_name(*c, &space);
        for other in [1u8, 2, 255] {
            out.push(Answer {
                what: format!("hostile: {name} as layer {other}"),
                layer: other,
                key: *c,
                packaged: false,
                bytes: b.clone(),
                storage_key: None,
            });
        }
    }
    out
}

// ---------------------------------------------------------------------------------------
// The cases.

fn cases() -> Vec<Case> {
    let mut rng = Rng(2024);
    let mut cases = Vec::new();
    let mut case = |elevation: &Repo, colour: Option<&Repo>, answers: Vec<Answer>| {
        let name = match colour {
            Some(c) => format!("{} with {}", elevation.name, c.name),
            None => elevation.name.clone(),
        };
        cases.push(Case {
            name,
            open: open(elevation, colour),
            answers,
        });
    };

    // The committed golden blobs, versions 5 and 4.
    for mode in ["lossless", "rms_2m", "rms_2m_rdo", "v4_rms_2m"] {
        let r = committed_golden(mode);
        let mut a = answers(&r, 0, usize::MAX, 0);
        if mode == "lossless" {
            a.extend(hostile(&r, 0, 1, &mut rng));
        }
        case(&r, None, a);
    }

    // A raster through the whole encoder: border masks, several levels of owned
    // children, side information of real subtrees, no-data plateaus; packages.
    for (name, mode) in [
        ("rms", RateMode::RmsM(1.5)),
        ("max_error", RateMode::MaxErrorM(4.0)),
    ] {
        let e = encode(&plateau_raster(), options(8, mode, false)).unwrap();
        let r = encoded_repo(&format!("paths/raster_{name}_45x29_n8"), &[&e], Some(96));
        let mut a = answers(&r, 0, usize::MAX, 8);
        if name == "rms" {
            a.extend(hostile(&r, 0, 2, &mut rng));
        }
        case(&r, None, a);
    }

    // Synthetic matrices: every size class, both models.
    let small: Vec<(&'static str, Style)> = STYLES
        .iter()
        .copied()
        .filter(|(name, _)| !name.starts_with("dense") && *name != "medium")
        .collect();
    for (n, w, h, trained, styles) in [
        (2usize, 11usize, 7usize, true, &STYLES[..]),
        (4, 21, 13, true, &STYLES[..]),
        (8, 41, 27, true, &STYLES[..]),
        (16, 81, 50, true, &STYLES[..]),
        (32, 150, 100, true, &STYLES[..]),
        (32, 150, 100, false, &STYLES[..]),
        (64, 150, 100, true, &small[..]),
    ] {
        let (r, matrices) = synthetic(n, w, h, trained, styles);
        let space = r.space();
        let mut a: Vec<Answer> = matrices
            .into_iter()
            .map(|(c, what, bytes)| Answer {
                what: format!("{what}, blob {}", key_name(c, &space)),
                layer: 0,
                key: c,
                packaged: false,
                bytes,
                storage_key: Some(r.keys[&c].clone()),
            })
            .collect();
        if n == 32 && trained {
            a.extend(hostile(&r, 0, 2, &mut rng));
        }
        case(&r, None, a);
    }

    // A sparse planar repository: a coverage with holes, raster edges, packages.
    let hole = |x: usize, y: usize| (40..85).contains(&x) && (20..60).contains(&y) || x + y < 12;
    let e = encode(
        &raster(120, 90, 4, hole),
        options(8, RateMode::MaxErrorM(2.0), true),
    )
    .unwrap();
    let coverage = e.coverage.as_ref().unwrap();
    assert!(coverage.covered_blocks() < coverage.blocks(), "no hole");
    let r = encoded_repo("sparse/planar_120x90_n8", &[&e], Some(80));
    let mut a = answers(&r, 0, 24, 8);
    a.extend(hostile(&r, 0, 2, &mut rng));
    case(&r, None, a);

    // A colour layer over an elevation repository of the same ground.
    let elevation = encode(
        &raster(65, 49, 7, |_, _| false),
        options(8, RateMode::RmsM(1.0), false),
    )
    .unwrap();
    let channels: Vec<Encoded> = [
        (1u64, RateMode::MaxErrorM(1.0)),
        (2, RateMode::RmsM(2.0)),
        (3, RateMode::Lossless),
    ]
    .into_iter()
    .map(|(seed, mode)| {
        encode(&raster(65, 49, seed, |_, _| false), options(8, mode, false)).unwrap()
    })
    .collect();
    let er = encoded_repo("colour/elevation_65x49_n8", &[&elevation], None);
    let refs: Vec<&Encoded> = channels.iter().collect();
    let cr = encoded_repo("colour/colour_65x49_n8", &refs, Some(200));
    let mut a = answers(&er, 0, 6, 0);
    a.extend(answers(&cr, 1, 24, 6));
    a.extend(hostile(&cr, 1, 2, &mut rng));
    case(&er, Some(&cr), a);

    // Small planets: dense lossless with packages, sparse (a cap across three faces),
    // and a colour layer.
    let dense = encode_sphere(
        &planet(16, 4, 0.0, |_| false),
        options(4, RateMode::Lossless, false),
    )
    .unwrap();
    let r = encoded_repo("planet/dense_lossless_16_n4", &[&dense], Some(64));
    let mut a = answers(&r, 0, 16, 8);
    a.extend(hostile(&r, 0, 2, &mut rng));
    case(&r, None, a);
    let centre = [0.6f64, 0.5, 0.62];
    let len = centre.iter().map(|c| c * c).sum::<f64>().sqrt();
    let far = move |q: [f64; 3]| {
        (0..3).map(|k| q[k] * centre[k] / len).sum::<f64>() < 50f64.to_radians().cos()
    };
    let sparse = encode_sphere(
        &planet(32, 8, 0.3, far),
        options(8, RateMode::MaxErrorM(3.0), true),
    )
    .unwrap();
    assert!(sparse.coverage.is_some());
    let r = encoded_repo("planet/sparse_max_error_32_n8", &[&sparse], Some(96));
    let mut a = answers(&r, 0, 16, 8);
    a.extend(hostile(&r, 0, 1, &mut rng));
    case(&r, None, a);
    let colour: Vec<Encoded> = [
        (0.5, RateMode::Lossless),
        (-0.4, RateMode::RmsM(6.0)),
        (0.2, RateMode::MaxErrorM(20.0)),
    ]
    .into_iter()
    .map(|(shift, mode)| {
        encode_sphere(&planet(16, 4, shift, |_| false), options(4, mode, false)).unwrap()
    })
    .collect();
    let er = encoded_repo("planet/elevation_16_n4", &[&dense], None);
    let refs: Vec<&Encoded> = colour.iter().collect();
    let cr = encoded_repo("planet/colour_16_n4", &refs, Some(160));
    let mut a = answers(&er, 0, 4, 0);
    a.extend(answers(&cr, 1, 16, 6));
    a.extend(hostile(&cr, 1, 1, &mut rng));
    case(&er, Some(&cr), a);
    cases
}

/// The decoder's input: `u8 layer, u8 packaged, key`, then the bytes (`api::decoder_decode`).
fn input(a: &Answer) -> Vec<u8> {
    let mut out = vec![a.layer, u8::from(a.packaged)];
    for v in a.key {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out.extend_from_slice(&a.bytes);
    out
}

/// `v` as JSON text.
fn js<T: serde::Serialize + ?Sized>(v: &T) -> String {
    serde_json::to_string(v).unwrap()
}

/// The file: one case a line, then one answer a line, each with what the native module
/// gives.
/// Returns the text, every error message, and the answers that are not hostile but failed.
fn golden_text(cases: &[Case]) -> (String, Vec<String>, Vec<String>) {
    let mut s = String::new();
    s.push_str("{\"about\":\"answers decoded natively by quincunx_web::api::Module: output sha256 or error text (written by web/tests/golden.rs; bless with QUINCUNX_BLESS=1; checked against the WebAssembly module by web-demo/test/wasm.test.mjs)\",\n");
    let _ = writeln!(s, "\"blobVersion\":{},", blob::VERSION);
    s.push_str("\"cases\":[\n");
    let mut errors = Vec::new();
    let mut failed = Vec::new();
    for (k, c) in cases.iter().enumerate() {
        let mut module = Module::default();
        let open_text = serde_json::to_string(&c.open).unwrap();
        let h = module.decoder_new(open_text.as_bytes()).unwrap();
        let _ = writeln!(
            s,
            "{{\"name\":{},\"open\":{open_text},\"answers\":[",
            serde_json::to_string(&c.name).unwrap()
        );
        let lines: Vec<String> = c
            .answers
            .iter()
            .map(|a| {
                let result = match module.decoder_decode(h, &input(a)) {
                    Ok(out) => format!("\"sha256\":\"{}\",\"len\":{}", sha256(&out), out.len()),
                    Err(e) => {
                        if !a.what.starts_with("hostile") {
                            failed.push(format!("{}: {}: {e}", c.name, a.what));
                        }
                        errors.push(e.clone());
                        format!("\"error\":{}", js(&e))
                    }
                };
                let storage_key = a
                    .storage_key
                    .as_ref()
                    .map(|k| format!(",\"storageKey\":\"{}\"", hex(k)))
                    .unwrap_or_default();
                format!(
                    "{{\"what\":{},\"layer\":{},\"key\":{},\"packaged\":{},{result}{storage_key},\"bytes\":\"{}\"}}",
                    js(&a.what),
                    a.layer,
                    js(&a.key),
                    a.packaged,
                    base64(&a.bytes)
                )
            })
            .collect();
        s.push_str(&lines.join(",\n"));
        s.push_str(if k + 1 < cases.len() {
            "\n]},\n"
        } else {
            "\n]}\n"
        });
    }
    s.push_str("]}\n");
    (s, errors, failed)
}

#[test]
fn wasm_decode_vectors_are_unchanged() {
    let cases = cases();
    let (text, errors, failed) = golden_text(&cases);
    // Every blob and package of every coding path decodes, and every error path of the
    // blob decoder and the answer framing is reached.
    assert!(
        failed.is_empty(),
        "answers that failed:\n  {}",
        failed.join("\n  ")
    );
    for c in &cases {
        let good = c
            .answers
            .iter()
            .filter(|a| !a.what.starts_with("hostile"))
            .count();
        assert!(good > 0, "{}: no answers", c.name);
    }
    for needle in [
        "shorter than its header",
        "blob version 3 is not supported",
        "does not match the repository's N",
        "checksum mismatch",
        "coded data ends early",
        "magnitude escape longer than 32 bits",
        "not a package",
        "answer truncated",
        "trailing bytes",
        "carries children",
        "carries owned child",
        "is not refinable",
        "no colour layer",
        "no layer 2",
        "frame",
    ] {
        assert!(
            errors.iter().any(|e| e.contains(needle)),
            "no hostile answer fails with {needle:?}; errors: {:?}",
            errors.iter().collect::<BTreeSet<_>>()
        );
    }
    let answers: usize = cases.iter().map(|c| c.answers.len()).sum();
    println!(
        "{GOLDEN}: {} cases, {answers} answers ({} errors), {} bytes",
        cases.len(),
        errors.len(),
        text.len()
    );
    assert!(text.len() < 600_000, "{GOLDEN} takes {} bytes", text.len());
    let path = golden_path();
    if std::env::var("QUINCUNX_BLESS").is_ok_and(|v| v == "1") {
        std::fs::write(&path, &text).unwrap();
        println!("blessed {}", path.display());
        return;
    }
    let committed = std::fs::read_to_string(&path).unwrap_or_else(|e| {
        panic!(
            "{}: {e} (write it with QUINCUNX_BLESS=1 cargo test --release -p quincunx-web --test golden)",
            path.display()
        )
    });
    if committed != text {
        let line = committed
            .lines()
            .zip(text.lines())
            .position(|(a, b)| a != b)
            .unwrap_or(committed.lines().count().min(text.lines().count()));
        let case = text
            .lines()
            .take(line + 1)
            .filter_map(|l| l.strip_prefix("{\"name\":"))
            .last()
            .and_then(|l| l.split(",\"open\"").next())
            .unwrap_or("(header)");
        let shown: String = text
            .lines()
            .nth(line)
            .unwrap_or("")
            .chars()
            .take(160)
            .collect();
        panic!(
            "{} differs from what the code gives now, from line {} (case {case}):\n  {shown}\n\
             After a deliberate change of the format, the encoder or an error message, re-bless \
             with `QUINCUNX_BLESS=1 cargo test --release -p quincunx-web --test golden`, rebuild \
             the module (web-demo/build-wasm.sh) and run `node --test web-demo/test/wasm.test.mjs`.",
            path.display(),
            line + 1
        );
    }
}
