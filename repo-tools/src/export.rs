//! `quincunx export`: one static file per blob, at the path the server serves it under.
//!
//! Layout (mirrors `docs/http-api.md`):
//! ```text
//! <dir>/repos/<name>/metadata.json
//! <dir>/repos/<name>/v/<hash16>/d/<x>/<y>        planar blob of the diamond centred at (x, y)
//! <dir>/repos/<name>/v/<hash16>/d/<x>/<y>/<z>    sphere blob
//! ```
//! `hash16` is the first 16 hex digits of the content hash, so a rebuilt repository gets
//! new URLs and caches never serve stale blobs. Leaves (no blob) have no file. A
//! repository with an inlining limit also gets each diamond's package (its blob with its
//! small owned children's, `quincunx_store::answer`) at `.../p/<centre>`. The exported
//! `metadata.json` has `static_export: true`, so clients take the 404 a static server
//! answers for a leaf's missing file as a leaf (no special server rule needed).

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use quincunx_codec::diamond::{PlanarDomain, SphereDomain};
use quincunx_store::answer::IdSpace;
use quincunx_store::{Domain, Metadata, Repository};

use crate::progress;

/// The URL path (no leading slash) of a blob, from its storage key.
pub fn blob_path(meta: &Metadata, name: &str, key: &[u8]) -> Result<String> {
    Ok(path_centre(meta, name, key, "d")?.0)
}

/// The URL path of a diamond's blob (`kind` "d") or package ("p"), and its centre
/// (`z = 0` for planar ids).
fn path_centre(meta: &Metadata, name: &str, key: &[u8], kind: &str) -> Result<(String, [i64; 3])> {
    let version = &meta.content_hash[..meta.content_hash.len().min(16)];
    let (centre, c) = match meta.domain {
        Domain::Planar => {
            let id = PlanarDomain::new(meta.m)?.id_from_key(key)?;
            (format!("{}/{}", id.x, id.y), [id.x, id.y, 0])
        }
        Domain::Sphere => {
            let id = SphereDomain::new(meta.m)?.id_from_key(key)?;
            let [x, y, z] = id.c;
            (format!("{x}/{y}/{z}"), id.c)
        }
    };
    Ok((format!("repos/{name}/v/{version}/{kind}/{centre}"), c))
}

fn write_file(file: &Path, bytes: &[u8]) -> Result<()> {
    if let Some(parent) = file.parent() {
        std::fs::create_dir_all(parent)
            .with_context(|| format!("creating {}", parent.display()))?;
    }
    std::fs::write(file, bytes).with_context(|| format!("writing {}", file.display()))
}

/// Runs `quincunx export`.
pub fn run(path: &Path, dir: &Path, name: Option<&str>) -> Result<()> {
    let repo = Repository::open(path).with_context(|| format!("opening {}", path.display()))?;
    let name = match name {
        Some(n) => n.to_string(),
        None => path
            .file_name()
            .map(|s| s.to_string_lossy().into_owned())
            .context("repository path has no name; pass --name")?,
    };
    if !quincunx_store::is_valid_name(&name) {
        bail!("repository name {name:?} must be ASCII letters, digits, '-', '_' or '.'");
    }
    let meta = repo.metadata();
    let root: PathBuf = dir.join("repos").join(&name);
    std::fs::create_dir_all(&root).with_context(|| format!("creating {}", root.display()))?;
    let domain = IdSpace::of(meta).map_err(anyhow::Error::msg)?;
    let pb = progress::bar(repo.blob_count() as u64, "exporting", "blobs");
    let mut files = 0u64;
    for kv in repo.blobs() {
        let (key, blob) = kv?;
        let (path, centre) = path_centre(meta, &name, &key, "d")?;
        if meta.inline_max_bytes.is_some() {
            let package = repo.package(&domain, centre)?.unwrap_or_default();
            write_file(&dir.join(path_centre(meta, &name, &key, "p")?.0), &package)?;
        }
        write_file(&dir.join(path), &blob)?;
        files += 1;
        pb.inc(1);
    }
    pb.finish_and_clear();
    let meta_file = root.join("metadata.json");
    // Served as files, a leaf's URL is a 404: the record says so (`static_export`).
    let exported = Metadata {
        static_export: true,
        ..meta.clone()
    };
    std::fs::write(&meta_file, serde_json::to_vec(&exported)?)
        .with_context(|| format!("writing {}", meta_file.display()))?;
    outln!(
        "exported {files} blobs and metadata.json to {}",
        root.display()
    );
    Ok(())
}
