//! Dependency-direction invariants that `cargo tree` can check (see STYLE.md).
#![allow(clippy::unwrap_used, clippy::expect_used)]

use crate::common;

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

/// `cargo tree` of `crate_name` (normal and build edges), one crate a line.
fn tree_of(crate_name: &str) -> String {
    cargo_tree(crate_name, "normal,build", &[])
}

/// `cargo tree` of `crate_name` over the dependency kinds `edges`, one crate a line, with
/// `extra` arguments (a `--target`).
fn cargo_tree(crate_name: &str, edges: &str, extra: &[&str]) -> String {
    let output = Command::new(env!("CARGO"))
        .current_dir(common::workspace_root())
        .args([
            "tree",
            "--offline",
            "-p",
            crate_name,
            "-e",
            edges,
            "--prefix",
            "none",
        ])
        .args(extra)
        .output()
        .unwrap();
    assert!(
        output.status.success(),
        "cargo tree -p {crate_name} -e {edges} {extra:?} failed: {}",
        String::from_utf8_lossy(&output.stderr)
    );
    String::from_utf8_lossy(&output.stdout).into_owned()
}

fn wgpu_crates(tree: &str) -> Vec<&str> {
    tree.lines().filter(|l| l.starts_with("wgpu")).collect()
}

#[test]
fn client_and_server_do_not_depend_on_wgpu() {
    // The renderer does: the filter finds wgpu where it is.
    assert!(
        !wgpu_crates(&tree_of("quincunx-render")).is_empty(),
        "quincunx-render's tree lists no wgpu"
    );
    for (crate_name, known) in [
        ("quincunx-client", "quincunx-decoder "),
        ("quincunx-server", "quincunx-store "),
    ] {
        let tree = tree_of(crate_name);
        // A dependency it does have: an empty output would prove nothing.
        assert!(tree.lines().any(|l| l.starts_with(known)), "{tree}");
        let wgpu = wgpu_crates(&tree);
        assert!(wgpu.is_empty(), "{crate_name} depends on {wgpu:?}");
    }
}

/// Crates of `tree` whose names are in `names`.
fn named<'t>(tree: &'t str, names: &[&str]) -> Vec<&'t str> {
    tree.lines()
        .filter(|l| names.iter().any(|n| l.starts_with(&format!("{n} "))))
        .collect()
}

/// The names of `names` that no crate of `tree` has.
fn unnamed<'n>(tree: &str, names: &[&'n str]) -> Vec<&'n str> {
    names
        .iter()
        .copied()
        .filter(|n| named(tree, &[n]).is_empty())
        .collect()
}

#[test]
fn clients_decode_without_the_encoder_and_the_core_without_io() {
    // The codec itself is built on the decoder and rayon: the filter finds them there.
    let codec = tree_of("quincunx-codec");
    assert_eq!(
        named(&codec, &["quincunx-decoder", "rayon"]).len(),
        2,
        "{codec}"
    );
    for crate_name in [
        "quincunx-decoder",
        "quincunx-client-core",
        "quincunx-client",
        "quincunx-render",
    ] {
        let tree = tree_of(crate_name);
        assert!(
            !named(&tree, &["quincunx-diamond"]).is_empty(),
            "{crate_name}: {tree}"
        );
        let encoder = named(&tree, &["quincunx-codec", "rayon"]);
        assert!(encoder.is_empty(), "{crate_name} depends on {encoder:?}");
    }
    // The sans-IO core: no runtime, HTTP or TLS (the native client has them all).
    let io = ["tokio", "reqwest", "hyper", "rustls", "mio"];
    assert!(named(&tree_of("quincunx-client"), &io).len() >= 4);
    let core = tree_of("quincunx-client-core");
    let found = named(&core, &io);
    assert!(
        found.is_empty(),
        "quincunx-client-core depends on {found:?}"
    );
}

#[test]
fn the_web_module_has_no_encoder_io_or_gpu() {
    // The browser's module (web-demo/js/quincunx.wasm) decodes and streams with the same
    // crates as the native client, minus everything the page does itself: the network is
    // fetch(), threads are workers, drawing is WebGL2. Every target's dependencies count,
    // wasm32's included.
    let all_targets = ["--target", "all"];
    let encoder = ["quincunx-codec", "rayon"];
    let io = ["tokio", "reqwest", "hyper", "rustls", "mio"];
    // The filters find each kind where it is: the encoder in the module's own tests (the
    // codec encodes what they decode), I/O in the native client, wgpu in the renderer.
    let with_tests = cargo_tree("quincunx-web", "normal,build,dev", &all_targets);
    let missing = unnamed(&with_tests, &encoder);
    assert!(missing.is_empty(), "no {missing:?} in {with_tests}");
    assert!(named(&tree_of("quincunx-client"), &io).len() >= 4);
    assert!(!wgpu_crates(&tree_of("quincunx-render")).is_empty());

    let tree = cargo_tree("quincunx-web", "normal,build", &all_targets);
    // What it is built on: an empty output would prove nothing.
    let base = ["quincunx-decoder", "quincunx-client-core"];
    let missing = unnamed(&tree, &base);
    assert!(missing.is_empty(), "no {missing:?} in {tree}");
    let mut found = named(&tree, &encoder);
    found.extend(named(&tree, &io));
    found.extend(wgpu_crates(&tree));
    assert!(found.is_empty(), "quincunx-web depends on {found:?}");
}

#[test]
fn the_client_reads_metadata_without_the_store() {
    let tree = tree_of("quincunx-client");
    // What it shares with the server and store: the metadata crate.
    assert!(
        tree.lines().any(|l| l.starts_with("quincunx-meta ")),
        "{tree}"
    );
    let store: Vec<&str> = tree
        .lines()
        .filter(|l| l.starts_with("quincunx-store") || l.starts_with("sled"))
        .collect();
    assert!(store.is_empty(), "quincunx-client depends on {store:?}");
    // The store and server share the same crate.
    for crate_name in ["quincunx-store", "quincunx-server"] {
        let tree = tree_of(crate_name);
        assert!(
            tree.lines().any(|l| l.starts_with("quincunx-meta ")),
            "{crate_name}: {tree}"
        );
    }
}

#[test]
fn the_small_cli_builds_and_serves_without_wgpu_winit_or_plotters() {
    // `quincunx-repo-tools --no-default-features` (the container image's build): the
    // server, store and encoder, and none of the renderer's or the charts' crates, which
    // the default build has (the filter finds them there).
    let gui = ["wgpu", "winit", "plotters", "quincunx-render"];
    let full = cargo_tree("quincunx-repo-tools", "normal,build", &[]);
    let missing = unnamed(&full, &gui);
    assert!(missing.is_empty(), "the default build has no {missing:?}");
    let small = cargo_tree(
        "quincunx-repo-tools",
        "normal,build",
        &["--no-default-features"],
    );
    let base = [
        "quincunx-server",
        "quincunx-store",
        "quincunx-codec",
        "quincunx-client",
    ];
    let missing = unnamed(&small, &base);
    assert!(missing.is_empty(), "no {missing:?} in {small}");
    let found = named(&small, &gui);
    assert!(found.is_empty(), "the small build depends on {found:?}");
}
