//! The WebAssembly module's code, natively: the same calls `web-demo/tools/bench-codec.mjs`
//! and `decode-repo.mjs` time in node and Chromium, so the cost of running in WebAssembly
//! is a ratio of one code on one machine. Prints one JSON line.
//!
//! ```text
//! cargo run --release -p quincunx-web --example native_speed -- answers
//! cargo run --release -p quincunx-web --example native_speed -- repo <export dir> <name>...
//! ```
//!
//! `answers`: every answer of `web-demo/test/golden/wasm-decode.json` that decodes, through
//! `AnswerDecoder::decode` (medians of 7 runs of at least 300 ms, as bench-codec.mjs).
//! `repo`: the whole-repository reconstruction of each named repository of a static
//! export (`reconstruct_call`, by the whole-raster decoder and by the refiners, median of
//! 5 runs each): the decode alone as the call times it (`decode_*`, what `verify` times)
//! and the whole call (`call_*`: parsing the input, metadata and geometry, writing the
//! output), samples counted as `quincunx verify` counts them.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::collections::HashMap;
use std::path::Path;
use std::time::Instant;

use quincunx_web::decode::AnswerDecoder;
use quincunx_web::open::Open;
use quincunx_web::reconstruct::{Decoder, reconstruct_call};

/// The wall clock the call times its decode with.
struct Wall(Instant);

impl quincunx_client_core::refine::Clock for Wall {
    fn now(&self) -> std::time::Duration {
        self.0.elapsed()
    }
}

fn median(mut xs: Vec<f64>) -> f64 {
    xs.sort_by(f64::total_cmp);
    xs[xs.len() / 2]
}

fn base64(s: &str) -> Vec<u8> {
    let value = |c: u8| match c {
        b'A'..=b'Z' => c - b'A',
        b'a'..=b'z' => c - b'a' + 26,
        b'0'..=b'9' => c - b'0' + 52,
        b'+' => 62,
        _ => 63,
    };
    let digits: Vec<u8> = s.bytes().filter(|&c| c != b'=').map(value).collect();
    let mut out = Vec::with_capacity(digits.len() * 3 / 4);
    for chunk in digits.chunks(4) {
        let n = chunk.iter().fold(0u32, |n, &d| n << 6 | u32::from(d)) << (6 * (4 - chunk.len()));
        out.extend_from_slice(&n.to_be_bytes()[1..chunk.len()]);
    }
    out
}

struct Answer {
    decoder: usize,
    set: String,
    layer: u8,
    key: [i64; 3],
    packaged: bool,
    bytes: Vec<u8>,
    samples: usize,
}

fn answers() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let text = std::fs::read_to_string(root.join("web-demo/test/golden/wasm-decode.json")).unwrap();
    let golden: serde_json::Value = serde_json::from_str(&text).unwrap();
    let mut decoders = Vec::new();
    let mut all = Vec::new();
    for c in golden["cases"].as_array().unwrap() {
        let open: Open = serde_json::from_value(c["open"].clone()).unwrap();
        decoders.push(AnswerDecoder::new(&open).unwrap());
        let d = decoders.len() - 1;
        for a in c["answers"].as_array().unwrap() {
            if a.get("error").is_some() || a["what"].as_str().unwrap().starts_with("hostile") {
                continue;
            }
            let key: Vec<i64> = a["key"]
                .as_array()
                .unwrap()
                .iter()
                .map(|k| k.as_i64().unwrap())
                .collect();
            let mut answer = Answer {
                decoder: d,
                set: c["name"]
                    .as_str()
                    .unwrap()
                    .split('/')
                    .next()
                    .unwrap()
                    .to_string(),
                layer: a["layer"].as_u64().unwrap() as u8,
                key: [key[0], key[1], key.get(2).copied().unwrap_or(0)],
                packaged: a["packaged"].as_bool().unwrap(),
                bytes: base64(a["bytes"].as_str().unwrap()),
                samples: 0,
            };
            let out = decoders[d]
                .decode(answer.layer, answer.key, &answer.bytes, answer.packaged)
                .unwrap();
            if answer.layer == 0 {
                answer.samples = u32::from_le_bytes([out[0], out[1], out[2], out[3]]) as usize;
            }
            all.push(answer);
        }
    }
    let measure = |set: &[&Answer]| {
        let bytes: usize = set.iter().map(|a| a.bytes.len()).sum();
        let samples: usize = set.iter().map(|a| a.samples).sum();
        let (mut blobs_s, mut bytes_s, mut samples_s) = (Vec::new(), Vec::new(), Vec::new());
        for _ in 0..7 {
            let start = Instant::now();
            let mut rounds = 0;
            while start.elapsed().as_secs_f64() < 0.3 {
                for a in set {
                    let out = decoders[a.decoder].decode(a.layer, a.key, &a.bytes, a.packaged);
                    std::hint::black_box(out).unwrap();
                }
                rounds += 1;
            }
            let s = start.elapsed().as_secs_f64();
            blobs_s.push((rounds * set.len()) as f64 / s);
            bytes_s.push((rounds * bytes) as f64 / s);
            samples_s.push((rounds * samples) as f64 / s);
        }
        (
            median(blobs_s),
            median(bytes_s) / 1e6,
            median(samples_s) / 1e6,
        )
    };
    let every: Vec<&Answer> = all.iter().collect();
    let committed: Vec<&Answer> = all.iter().filter(|a| a.set == "golden").collect();
    let (b, mb, _) = measure(&every);
    let (cb, cmb, cms) = measure(&committed);
    println!(
        "{}",
        serde_json::json!({
            "native": true,
            "blobs_per_s": b.round(),
            "mbytes_per_s": mb,
            "committed_golden_blobs_per_s": cb.round(),
            "committed_golden_mbytes_per_s": cmb,
            "committed_golden_msamples_per_s": cms,
            "blobs": every.len(),
        })
    );
}

fn repo(dir: &Path, name: &str) {
    let repo = dir.join("repos").join(name);
    let meta_text = std::fs::read(repo.join("metadata.json")).unwrap();
    let meta: serde_json::Value = serde_json::from_slice(&meta_text).unwrap();
    let version = &meta["content_hash"].as_str().unwrap()[..16];
    let mut blobs: HashMap<[i64; 3], Vec<u8>> = HashMap::new();
    fn walk(path: &Path, parts: &mut Vec<i64>, out: &mut HashMap<[i64; 3], Vec<u8>>) {
        for entry in std::fs::read_dir(path).unwrap() {
            let entry = entry.unwrap();
            parts.push(entry.file_name().to_string_lossy().parse().unwrap());
            if entry.file_type().unwrap().is_dir() {
                walk(&entry.path(), parts, out);
            } else {
                let key = [parts[0], parts[1], parts.get(2).copied().unwrap_or(0)];
                out.insert(key, std::fs::read(entry.path()).unwrap());
            }
            parts.pop();
        }
    }
    walk(
        &repo.join("v").join(version).join("d"),
        &mut Vec::new(),
        &mut blobs,
    );
    let mut input = Vec::new();
    input.extend_from_slice(&(meta_text.len() as u32).to_le_bytes());
    input.extend_from_slice(&meta_text);
    input.extend_from_slice(&(blobs.len() as u32).to_le_bytes());
    for (k, b) in &blobs {
        for v in k {
            input.extend_from_slice(&v.to_le_bytes());
        }
        input.extend_from_slice(&(b.len() as u32).to_le_bytes());
        input.extend_from_slice(b);
    }
    let extent = meta["extent"].as_array().unwrap();
    let (a, b) = (extent[0].as_u64().unwrap(), extent[1].as_u64().unwrap());
    let channels = meta["channels"].as_array().unwrap().len() as u64;
    let counted = if meta["domain"] == "sphere" {
        6 * a * b + 2
    } else {
        a * b
    } * channels;
    for (decoder, label) in [(Decoder::Whole, "whole"), (Decoder::Refiners, "refiners")] {
        let (mut calls, mut decodes) = (Vec::new(), Vec::new());
        for _ in 0..5 {
            let start = Instant::now();
            let out = std::hint::black_box(reconstruct_call(&input, decoder, &Wall(start)));
            calls.push(start.elapsed().as_secs_f64());
            decodes.push(f64::from_le_bytes(out.unwrap()[8..16].try_into().unwrap()));
        }
        let (call, decode) = (median(calls), median(decodes));
        let rate = |s: f64| counted as f64 / s / 1e6;
        println!(
            "{}",
            serde_json::json!({
                "native": true, "repo": name, "decoder": label,
                "decode_seconds": decode, "decode_msamples_per_s": rate(decode),
                "call_seconds": call, "call_msamples_per_s": rate(call),
            })
        );
    }
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    match args.first().map(String::as_str) {
        Some("answers") => answers(),
        Some("repo") if args.len() >= 3 => {
            for name in &args[2..] {
                repo(Path::new(&args[1]), name);
            }
        }
        _ => {
            eprintln!("usage: native_speed answers | native_speed repo <export dir> <name>...");
            std::process::exit(2);
        }
    }
}
