//! Source files are untrusted: every reader of `quincunx build` must return `Err` on
//! arbitrary bytes, never panic or allocate from an unchecked header. The first byte picks
//! the format; the rest is the file.
#![no_main]

use libfuzzer_sys::fuzz_target;
use quincunx_repo_tools::input::{probe_heights, read_heights, read_rgb};

fuzz_target!(|data: &[u8]| {
    let Some((&kind, body)) = data.split_first() else {
        return;
    };
    let dir = std::env::temp_dir().join(format!("quincunx-fuzz-{}", std::process::id()));
    if std::fs::create_dir_all(&dir).is_err() {
        return;
    }
    let (name, rgb) = match kind % 6 {
        0 => ("x.tif", false),
        1 => ("x.png", false),
        2 => ("x.png", true),
        3 => ("x.jpg", true),
        4 => ("N10E020.hgt", false),
        _ => ("x.json", false),
    };
    let path = dir.join(name);
    if std::fs::write(&path, body).is_err() {
        return;
    }
    if name == "x.json" {
        // A sidecar pointing at a small raw file.
        let _ = std::fs::write(dir.join("x.i16"), [0u8; 64]);
    }
    let _ = if rgb {
        read_rgb(&path).map(|_| ())
    } else {
        // A mosaic reads each tile's header first, then the tile.
        let _ = probe_heights(&path);
        read_heights(&path).map(|_| ())
    };
});
