//! The client's modules form layers: no module reaches, through `crate::` paths, a
//! module that reaches back to it (the core's modules and the native client's, read as
//! one graph). The core does no I/O: no clock, thread, socket or runtime is named in its
//! sources. Read from the sources, so a new cycle or a clock fails here.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::collections::{BTreeMap, BTreeSet};
use std::fs;
use std::path::Path;

/// Module name -> the modules its files name as `crate::<module>`.
fn module_graph(src: &Path) -> BTreeMap<String, BTreeSet<String>> {
    let mut graph = BTreeMap::new();
    for entry in fs::read_dir(src).unwrap() {
        let path = entry.unwrap().path();
        let (name, files) = if path.is_dir() {
            let mut files: Vec<_> = fs::read_dir(&path)
                .unwrap()
                .map(|e| e.unwrap().path())
                .filter(|p| p.extension().is_some_and(|e| e == "rs"))
                .collect();
            files.sort();
            (
                path.file_name().unwrap().to_string_lossy().into_owned(),
                files,
            )
        } else if path.extension().is_some_and(|e| e == "rs") {
            let stem = path.file_stem().unwrap().to_string_lossy().into_owned();
            if stem == "lib" {
                continue;
            }
            (stem, vec![path])
        } else {
            continue;
        };
        let mut uses = BTreeSet::new();
        for file in files {
            let text = fs::read_to_string(&file).unwrap();
            for (at, _) in text.match_indices("crate::") {
                let rest = &text[at + "crate::".len()..];
                let used: String = rest
                    .chars()
                    .take_while(|c| c.is_ascii_alphanumeric() || *c == '_')
                    .collect();
                if !used.is_empty() && used != name {
                    uses.insert(used);
                }
            }
        }
        graph.insert(name, uses);
    }
    graph
}

/// A cycle through `from`, if there is one (depth-first search over the graph).
fn cycle_from(graph: &BTreeMap<String, BTreeSet<String>>, from: &str) -> Option<Vec<String>> {
    let mut stack = vec![(from.to_string(), vec![from.to_string()])];
    let mut seen = BTreeSet::new();
    while let Some((module, path)) = stack.pop() {
        for next in graph.get(&module).into_iter().flatten() {
            if next == from {
                let mut cycle = path.clone();
                cycle.push(next.clone());
                return Some(cycle);
            }
            if seen.insert(next.clone()) {
                let mut longer = path.clone();
                longer.push(next.clone());
                stack.push((next.clone(), longer));
            }
        }
    }
    None
}

/// The client's sources and the core's (`../client-core/src`), as one graph.
fn client_graph() -> BTreeMap<String, BTreeSet<String>> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let mut graph = module_graph(&root.join("src"));
    for (module, uses) in module_graph(&root.join("../client-core/src")) {
        graph.entry(module).or_default().extend(uses);
    }
    graph
}

/// Every `.rs` file under `dir`.
fn sources(dir: &Path) -> Vec<std::path::PathBuf> {
    let mut out = Vec::new();
    for entry in fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        if path.is_dir() {
            out.extend(sources(&path));
        } else if path.extension().is_some_and(|e| e == "rs") {
            out.push(path);
        }
    }
    out.sort();
    out
}

#[test]
fn the_core_names_no_clock_thread_socket_or_runtime() {
    let core = Path::new(env!("CARGO_MANIFEST_DIR")).join("../client-core/src");
    let files = sources(&core);
    assert!(files.len() >= 9, "client-core sources not found: {files:?}");
    let banned = [
        "Instant",
        "elapsed()",
        "SystemTime",
        "std::thread",
        "std::net",
        "tokio",
        "reqwest",
        "std::fs",
        "std::io::Read",
    ];
    let mut found = Vec::new();
    for file in &files {
        let text = fs::read_to_string(file).unwrap();
        // Only the code: the tests below `#[cfg(test)]` may use a real clock.
        let code = text.split("#[cfg(test)]").next().unwrap_or("");
        for word in banned {
            if code.contains(word) {
                found.push(format!("{}: {word}", file.display()));
            }
        }
    }
    assert!(found.is_empty(), "I/O in the sans-IO core: {found:#?}");
}

#[test]
fn client_modules_have_no_cycles() {
    let graph = client_graph();
    for expected in [
        "dag", "domain", "colour", "session", "refine", "open", "fetch", "view", "flight",
    ] {
        assert!(graph.contains_key(expected), "module {expected} not found");
    }
    let cycles: Vec<String> = graph
        .keys()
        .filter_map(|m| cycle_from(&graph, m))
        .map(|c| c.join(" -> "))
        .collect();
    assert!(cycles.is_empty(), "module cycles: {cycles:#?}");
}

#[test]
fn the_cycle_check_finds_a_cycle() {
    let graph: BTreeMap<String, BTreeSet<String>> = [
        ("a", vec!["b"]),
        ("b", vec!["c"]),
        ("c", vec!["a"]),
        ("d", vec!["a"]),
    ]
    .into_iter()
    .map(|(m, u)| (m.to_string(), u.into_iter().map(String::from).collect()))
    .collect();
    assert_eq!(
        cycle_from(&graph, "a").map(|c| c.join(" -> ")),
        Some("a -> b -> c -> a".to_string())
    );
    assert_eq!(cycle_from(&graph, "d"), None);
}
