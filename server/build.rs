//! Compiles the web demo's page and modules into the binary: writes `demo_files.rs`, the
//! table (path, content type, ETag, bytes) `site.rs` serves `/demo/<path>` from (`web-demo/index.html` and every file under
//! `web-demo/js/`, the WebAssembly module included; the demo's tools, tests and npm
//! packages stay out).

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

fn content_type(path: &Path) -> Option<&'static str> {
    Some(match path.extension()?.to_str()? {
        "html" => "text/html; charset=utf-8",
        "mjs" | "js" => "text/javascript; charset=utf-8",
        "css" => "text/css; charset=utf-8",
        "json" => "application/json",
        "svg" => "image/svg+xml",
        "png" => "image/png",
        "wasm" => "application/wasm",
        _ => return None,
    })
}

fn collect(dir: &Path, out: &mut Vec<PathBuf>) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for entry in entries.flatten() {
        let path = entry.path();
        if path.is_dir() {
            collect(&path, out);
        } else if content_type(&path).is_some() {
            out.push(path);
        }
    }
}

/// FNV-1a, 64 bits: the file's ETag (a validator, not a security hash: the page's files
/// are the server's own).
fn fnv1a(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325, |h, &b| {
        (h ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3)
    })
}

fn main() {
    let manifest = PathBuf::from(std::env::var_os("CARGO_MANIFEST_DIR").unwrap_or_default());
    let demo = manifest.join("../web-demo");
    let index = demo.join("index.html");
    let js = demo.join("js");
    println!("cargo:rerun-if-changed={}", index.display());
    println!("cargo:rerun-if-changed={}", js.display());
    let mut files = vec![index];
    collect(&js, &mut files);
    files.sort();
    let mut table = String::from("&[\n");
    for file in &files {
        let Ok(name) = file.strip_prefix(&demo) else {
            continue;
        };
        let name = name.to_string_lossy().replace('\\', "/");
        let Some(kind) = content_type(file) else {
            continue;
        };
        let absolute = std::fs::canonicalize(file).unwrap_or_else(|_| file.clone());
        let bytes = match std::fs::read(&absolute) {
            Ok(b) => b,
            Err(e) => panic!("reading {}: {e}", absolute.display()),
        };
        let etag = format!("\"{:016x}-{:x}\"", fnv1a(&bytes), bytes.len());
        let _ = writeln!(
            table,
            "    ({name:?}, {kind:?}, {etag:?}, include_bytes!({:?})),",
            absolute.display().to_string()
        );
    }
    table.push(']');
    let out = PathBuf::from(std::env::var_os("OUT_DIR").unwrap_or_default()).join("demo_files.rs");
    if let Err(e) = std::fs::write(&out, table) {
        panic!("writing {}: {e}", out.display());
    }
}
