//! The JavaScript ports' golden vectors (`web-demo/test/golden/`): written by the Rust
//! tests under `QUINCUNX_BLESS=1`, otherwise checked against what the Rust code gives.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::path::PathBuf;

use serde_json::Value;
use sha2::Digest;

/// A vector file.
pub fn golden_file(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../web-demo/test/golden")
        .join(name)
}

/// Writes (bless) or checks one vector file; `test` names the Rust test that writes it,
/// `port` the JS module that must follow a change.
pub fn bless_or_check(name: &str, value: &Value, test: &str, port: &str) {
    let path = golden_file(name);
    let text = serde_json::to_string(value).unwrap() + "\n";
    if std::env::var("QUINCUNX_BLESS").is_ok_and(|v| v == "1") {
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        std::fs::write(&path, &text).unwrap();
        return;
    }
    let committed = std::fs::read_to_string(&path).unwrap_or_else(|e| {
        panic!(
            "{}: {e} (write it with QUINCUNX_BLESS=1 cargo test -p quincunx-codec --test {test})",
            path.display()
        )
    });
    let committed: Value = serde_json::from_str(&committed).unwrap();
    assert!(
        committed == *value,
        "{} differs from what the Rust code gives: update {port}, then re-bless with \
         QUINCUNX_BLESS=1",
        path.display()
    );
}

/// Lower-case hex.
pub fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// SHA-256 (hex) of `data`, what node:crypto gives.
pub fn sha256(data: &[u8]) -> String {
    hex(&sha2::Sha256::digest(data))
}

/// Standard padded base64 (`Buffer.from(text, "base64")` in node).
pub fn base64(bytes: &[u8]) -> String {
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
