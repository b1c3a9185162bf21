//! `quincunx info`: what a repository holds.

use std::path::Path;

use anyhow::{Context, Result};
use quincunx_codec::encode::root_grid_bytes;
use quincunx_store::Repository;
use serde::Serialize;

/// The `--json` output of `quincunx info`.
#[derive(Serialize)]
struct Info<'a> {
    path: String,
    metadata: &'a quincunx_store::Metadata,
    samples: u64,
    blob_count: u64,
    blob_bytes: u64,
    side_bytes: u64,
    bits_per_sample: f64,
    repository_bytes: u64,
    storage_overhead: f64,
    layout: Layout,
}

/// How the repository file is laid out for readers (`docs/repository-format.md`).
#[derive(Serialize)]
struct Layout {
    /// Bytes before the first blob a reader needs: header, root directory and metadata
    /// (what a range reader fetches to open the file).
    open_bytes: u64,
    /// The root directory's bytes (deflated).
    root_bytes: u64,
    /// The metadata record's bytes (deflated).
    metadata_bytes: u64,
    /// Blobs listed in the root directory.
    root_entries: usize,
    /// Tiles with a leaf directory.
    tiles: usize,
    /// All leaf directories' bytes.
    leaf_bytes: u64,
    /// Levels below this one are in the root; deeper ones in tiles (when there are any).
    split_level: u32,
    /// Tiles are squares of side `2^tile_shift` id units.
    tile_shift: u32,
}

/// Input samples a repository covers (planar: width x height; sphere: distinct cube points).
pub fn samples(meta: &quincunx_store::Metadata) -> u64 {
    let [a, b] = meta.extent;
    if meta.domain == quincunx_store::Domain::Sphere {
        6 * a * b + 2
    } else {
        a * b
    }
}

/// Bytes of root grids, models and steps.
pub fn side_bytes(meta: &quincunx_store::Metadata) -> u64 {
    meta.channels
        .iter()
        .map(|c| {
            (c.model.len()
                + 4 * c.steps.len()
                + c.roots
                    .iter()
                    .map(|r| root_grid_bytes(r).len())
                    .sum::<usize>()) as u64
        })
        .sum()
}

/// Runs `quincunx info`.
pub fn run(path: &Path, json: bool) -> Result<()> {
    let repo = Repository::open(path).with_context(|| format!("opening {}", path.display()))?;
    let meta = repo.metadata();
    let blob_bytes: u64 = meta.level_stats.iter().map(|s| s.bytes).sum();
    let blob_count: u64 = meta.level_stats.iter().map(|s| s.blobs).sum();
    let side = side_bytes(meta);
    let samples = samples(meta);
    let repository_bytes = repo.size_on_disk()?;
    let info = Info {
        path: path.display().to_string(),
        metadata: meta,
        samples,
        blob_count,
        blob_bytes,
        side_bytes: side,
        bits_per_sample: 8.0 * (blob_bytes + side) as f64 / samples.max(1) as f64,
        repository_bytes,
        storage_overhead: repository_bytes as f64 / (blob_bytes + side).max(1) as f64,
        layout: {
            let h = repo.header();
            let (root_entries, tiles) = repo.directory_sizes();
            Layout {
                open_bytes: h.open_len(),
                root_bytes: h.root.len,
                metadata_bytes: h.metadata.len,
                root_entries,
                tiles,
                leaf_bytes: h.leaves.len,
                split_level: h.split_level,
                tile_shift: h.tile_shift,
            }
        },
    };
    if json {
        outln!("{}", serde_json::to_string(&info)?);
        return Ok(());
    }
    outln!("repository     {}", info.path);
    outln!("content hash   {}", meta.content_hash);
    outln!(
        "domain         {} (m = {}), N = {}, {} detail levels, extent {} x {}",
        meta.domain,
        meta.m,
        meta.n,
        meta.levels,
        meta.extent[0],
        meta.extent[1]
    );
    outln!(
        "attribute      {} [{}], channels {}",
        meta.attribute.kind,
        meta.attribute.units,
        meta.channels
            .iter()
            .map(|c| format!("{} ({})", c.name, c.rate))
            .collect::<Vec<_>>()
            .join(", ")
    );
    outln!(
        "nodata         {} source samples, {}",
        meta.nodata.source_count,
        serde_json::to_string(&meta.nodata.handling)?.trim_matches('"')
    );
    if let Some(g) = &meta.georef {
        outln!("georef         {}", serde_json::to_string(g)?);
    }
    if let Some(r) = meta.radius_m {
        outln!("radius         {r} m");
    }
    match meta.inline_max_bytes {
        Some(t) => outln!("packages       carry owned children of at most {t} bytes"),
        None => outln!("packages       none (bare blobs only)"),
    }
    outln!("level      blobs        bytes  bytes/blob");
    for s in &meta.level_stats {
        outln!(
            "{:>5} {:>10} {:>12} {:>11.1}",
            s.level,
            s.blobs,
            s.bytes,
            s.bytes as f64 / s.blobs.max(1) as f64
        );
    }
    outln!(
        "total {:>10} {:>12}   + {} bytes roots/models/steps",
        blob_count,
        blob_bytes,
        side
    );
    outln!(
        "bits/sample    {:.4} over {} samples; {} bytes on disk ({:.2}x the coded bytes)",
        info.bits_per_sample,
        samples,
        repository_bytes,
        info.storage_overhead
    );
    let l = &info.layout;
    outln!(
        "layout         {} bytes to open (root directory {} bytes, metadata {} bytes); {} \
         blobs in the root, {} tiles ({} bytes of leaf directories)",
        l.open_bytes,
        l.root_bytes,
        l.metadata_bytes,
        l.root_entries,
        l.tiles,
        l.leaf_bytes
    );
    Ok(())
}
