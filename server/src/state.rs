//! What the server holds: the open repositories, their precomputed JSON, the hot blob
//! cache and the metrics.

use std::collections::{HashMap, HashSet};
use std::sync::atomic::{AtomicBool, Ordering::Relaxed};
use std::sync::{Arc, Mutex};

use axum::http::HeaderValue;
use bytes::Bytes;
use quincunx_store::Repository;
pub use quincunx_store::answer::IdSpace;

use crate::ServeError;
use crate::config::{Cors, ServerConfig};
use crate::error::ApiError;
use crate::metrics::Metrics;

/// Shared, cheaply cloned server state.
#[derive(Clone)]
pub struct AppState(Arc<Inner>);

/// The fields behind [`AppState`].
pub struct Inner {
    repos: Vec<Served>,
    by_name: HashMap<String, usize>,
    cache: BlobCache,
    /// Blobs whose read failure was logged (each is logged once).
    failed: Mutex<HashSet<BlobKey>>,
    /// Whether `failed` filled up and later failures went unlogged.
    failed_overflow: AtomicBool,
    /// Request and connection counters.
    pub metrics: Metrics,
    /// CORS policy.
    pub cors: Cors,
    /// `GET /repos` body.
    pub listing: Bytes,
}

impl std::ops::Deref for AppState {
    type Target = Inner;
    fn deref(&self) -> &Inner {
        &self.0
    }
}

/// One repository being served.
pub struct Served {
    /// Name in URLs.
    pub name: String,
    repo: Repository,
    /// Its id space.
    pub domain: IdSpace,
    levels: u32,
    /// Whether `.../p/` serves packages (the repository has an inlining limit).
    pub packaged: bool,
    /// First 16 hex digits of the content hash: the version in blob URLs.
    pub version: String,
    /// `GET /repos/<name>/metadata.json` body (byte-identical to `quincunx export`'s).
    pub metadata_json: Bytes,
    /// Strong validator of the metadata.
    pub metadata_etag: HeaderValue,
}

/// A blob (or the empty body of a leaf) ready to send.
#[derive(Clone)]
pub struct CachedBlob {
    /// The bytes; empty for a leaf.
    pub body: Bytes,
    /// Strong validator: repository version + centre (blob URLs are immutable).
    pub etag: HeaderValue,
}

#[derive(Clone)]
struct BlobWeighter;

/// Per-entry bookkeeping beyond the body, counted against the byte budget.
const ENTRY_OVERHEAD_BYTES: u64 = 96;

impl quick_cache::Weighter<BlobKey, CachedBlob> for BlobWeighter {
    fn weight(&self, _key: &BlobKey, val: &CachedBlob) -> u64 {
        val.body.len() as u64 + val.etag.len() as u64 + ENTRY_OVERHEAD_BYTES
    }
}

/// `(repository index, centre, package?)`.
type BlobKey = (u32, [i64; 3], bool);

/// Failed blobs remembered so that each is logged once.
const MAX_LOGGED_FAILURES: usize = 4096;

/// The hot cache: blob or package by [`BlobKey`], bounded in bytes.
type BlobCache = quick_cache::sync::Cache<BlobKey, CachedBlob, BlobWeighter>;

impl AppState {
    /// Opens every configured repository (read-only).
    pub fn open(config: &ServerConfig) -> Result<AppState, ServeError> {
        let mut repos = Vec::new();
        for rc in &config.repos {
            let repo = Repository::open(&rc.path).map_err(|source| ServeError::Store {
                name: rc.name.clone(),
                source,
            })?;
            repos.push(Served::new(rc.name.clone(), repo)?);
        }
        AppState::from_served(repos, config)
    }

    fn from_served(repos: Vec<Served>, config: &ServerConfig) -> Result<AppState, ServeError> {
        let by_name = repos
            .iter()
            .enumerate()
            .map(|(i, r)| (r.name.clone(), i))
            .collect();
        let listing = serde_json::to_vec(&serde_json::json!({
            "repositories": repos.iter().map(Served::summary).collect::<Vec<_>>()
        }))
        .map_err(|e| ServeError::Config(format!("listing: {e}")))?;
        let estimated_items = (config.cache_bytes / 512).clamp(16, 1 << 24) as usize;
        Ok(AppState(Arc::new(Inner {
            repos,
            by_name,
            cache: BlobCache::with_weighter(
                estimated_items,
                config.cache_bytes.max(1),
                BlobWeighter,
            ),
            failed: Mutex::new(HashSet::new()),
            failed_overflow: AtomicBool::new(false),
            metrics: Metrics::default(),
            cors: config.cors.clone(),
            listing: Bytes::from(listing),
        })))
    }

    /// A repository by name.
    pub fn repo(&self, name: &str) -> Option<(u32, &Served)> {
        let &i = self.by_name.get(name)?;
        Some((i as u32, &self.repos[i]))
    }

    /// The blob of the diamond centred at `c` in repository `index`, or with `packaged`
    /// its package (`quincunx_store::answer`): from the hot cache, else validated, read
    /// from the repository file and cached. In-domain diamonds without a blob (leaves, holes of sparse
    /// repositories, levels deeper than the repository) get an empty body.
    pub fn blob(&self, index: u32, c: [i64; 3], packaged: bool) -> Result<CachedBlob, ApiError> {
        if let Some(hit) = self.cache.get(&(index, c, packaged)) {
            self.metrics
                .cache_hits
                .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            return Ok(hit);
        }
        self.metrics
            .cache_misses
            .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let served = &self.repos[index as usize];
        let (key, level) = served
            .domain
            .key_level(c)
            .map_err(|e| ApiError::bad_request(format!("not a diamond of this repository: {e}")))?;
        let body = if level >= served.levels {
            Bytes::new()
        } else if packaged {
            match served.repo.package(&served.domain, c) {
                Ok(Some(answer)) => Bytes::from(answer),
                Ok(None) => Bytes::new(),
                Err(e) => return Err(self.read_failed((index, c, packaged), &e)),
            }
        } else {
            match served.repo.get(&key) {
                Ok(Some(blob)) => blob,
                Ok(None) => Bytes::new(),
                Err(e) => return Err(self.read_failed((index, c, packaged), &e)),
            }
        };
        let kind = if packaged { "p." } else { "" };
        let etag = match served.domain {
            IdSpace::Planar(_) => format!("\"{}.{kind}{}.{}\"", served.version, c[0], c[1]),
            IdSpace::Sphere(_) => {
                format!("\"{}.{kind}{}.{}.{}\"", served.version, c[0], c[1], c[2])
            }
        };
        let blob = CachedBlob {
            body,
            etag: HeaderValue::try_from(etag).map_err(|e| ApiError::internal(&served.name, &e))?,
        };
        self.cache.insert((index, c, packaged), blob.clone());
        Ok(blob)
    }

    /// Counts a failed read of `key` and logs it if it is the first for that blob (or
    /// package): a corrupt blob asked for by every client logs one line, not one per
    /// request. At most [`MAX_LOGGED_FAILURES`] blobs are remembered; past that one more
    /// line says further failures are only counted.
    fn read_failed(&self, key: BlobKey, cause: &dyn std::fmt::Display) -> ApiError {
        self.metrics.repository_read_errors.fetch_add(1, Relaxed);
        let first = {
            let mut failed = self.failed.lock().unwrap_or_else(|e| e.into_inner());
            if failed.len() < MAX_LOGGED_FAILURES {
                failed.insert(key)
            } else {
                if !failed.contains(&key) && !self.failed_overflow.swap(true, Relaxed) {
                    tracing::error!(
                        "{MAX_LOGGED_FAILURES} blobs failed to read; further failures are only \
                         counted (quincunx_repository_read_errors_total)"
                    );
                }
                false
            }
        };
        if first {
            let (index, c, packaged) = key;
            let repo = &self.repos[index as usize].name;
            let kind = if packaged { "package" } else { "blob" };
            tracing::error!(
                repo,
                centre = ?c,
                "reading the {kind} failed: {cause} (logged once per {kind}; \
                 quincunx_repository_read_errors_total counts every failure)"
            );
        }
        ApiError::unreadable()
    }

    /// Hot cache occupancy: bytes (as weighed) and entries.
    pub fn cache_usage(&self) -> (u64, usize) {
        (self.cache.weight(), self.cache.len())
    }
}

impl Served {
    fn new(name: String, repo: Repository) -> Result<Served, ServeError> {
        let meta = repo.metadata();
        let bad = |what: String| ServeError::Config(format!("repository {name:?}: {what}"));
        let domain = IdSpace::of(meta).map_err(bad)?;
        if meta.content_hash.len() < 16 || !meta.content_hash.bytes().all(|b| b.is_ascii_hexdigit())
        {
            return Err(bad("content hash missing or malformed".into()));
        }
        let version = meta.content_hash[..16].to_string();
        let metadata_json = serde_json::to_vec(meta).map_err(|e| bad(e.to_string()))?;
        let metadata_etag = HeaderValue::try_from(format!("\"{}\"", meta.content_hash))
            .map_err(|e| bad(e.to_string()))?;
        Ok(Served {
            levels: meta.levels,
            packaged: meta.inline_max_bytes.is_some(),
            name,
            repo,
            domain,
            version,
            metadata_json: Bytes::from(metadata_json),
            metadata_etag,
        })
    }

    /// The repository's entry in `GET /repos`.
    fn summary(&self) -> serde_json::Value {
        let meta = self.repo.metadata();
        let centre = match self.domain {
            IdSpace::Planar(_) => "{x}/{y}",
            IdSpace::Sphere(_) => "{x}/{y}/{z}",
        };
        serde_json::json!({
            "name": self.name,
            "domain": meta.domain,
            "attribute": meta.attribute.kind,
            "units": meta.attribute.units,
            "m": meta.m,
            "n": meta.n,
            "levels": meta.levels,
            "radius_m": meta.radius_m,
            "blobs": meta.level_stats.iter().map(|l| l.blobs).sum::<u64>(),
            "content_hash": meta.content_hash,
            "metadata_url": format!("/repos/{}/metadata.json", self.name),
            "blob_url_template": format!("/repos/{}/v/{}/d/{centre}", self.name, self.version),
        })
    }
}
