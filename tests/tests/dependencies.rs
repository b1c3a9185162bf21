//! Dependency-direction invariants that `cargo tree` can check (see STYLE.md).
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use std::process::Command;

#[test]
fn server_does_not_depend_on_the_codec() {
    let output = Command::new(env!("CARGO"))
        .current_dir(common::workspace_root())
        .args([
            "tree",
            "--offline",
            "-p",
            "quincunx-server",
            "-e",
            "normal,build",
            "--prefix",
            "none",
        ])
        .output()
        .unwrap();
    let tree = String::from_utf8_lossy(&output.stdout);
    assert!(
        output.status.success(),
        "cargo tree failed: {}",
        String::from_utf8_lossy(&output.stderr)
    );
    // The tree lists the crate itself and its store: an empty output would prove nothing.
    assert!(
        tree.lines().any(|l| l.starts_with("quincunx-store ")),
        "{tree}"
    );
    let codec: Vec<&str> = tree
        .lines()
        .filter(|l| l.starts_with("quincunx-codec"))
        .collect();
    assert!(codec.is_empty(), "quincunx-server depends on {codec:?}");
}
