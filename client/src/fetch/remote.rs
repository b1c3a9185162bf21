//! Where a repository's blobs are: base URL, name, version, and the URL of a key; or a
//! repository file read with range requests.

use std::sync::Arc;
use std::time::Duration;

use quincunx_client_core::fetch::range_answer::{self, PackIdentity, is_strong};
use quincunx_client_core::fetch::ranges::{self, PackIndex};
use quincunx_meta::Metadata;

use super::http1::{self, Endpoint};
use super::tls::ConnectOptions;
use super::{FetchError, Key};

/// A served repository: everything needed to name its blobs.
///
/// Blob paths are `{prefix}/repos/{name}/v/{version}/d/{x}/{y}` (planar) or
/// `.../d/{x}/{y}/{z}` (sphere), where `version` is the first 16 hex digits of the
/// repository's `content_hash` (see `docs/http-api.md`).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Remote {
    /// Resolved server address, `Host` header and path prefix.
    pub endpoint: Endpoint,
    /// The base URL as given, without a trailing slash.
    pub base_url: String,
    /// Repository name.
    pub name: String,
    /// First 16 hex digits of the content hash.
    pub version: String,
    /// Sphere domain (three coordinates in URLs) rather than planar.
    pub sphere: bool,
    /// A folder of static files (`quincunx export`, the metadata's `static_export`): a
    /// 404 on a blob or package URL is a leaf, not an error.
    pub static_export: bool,
    /// A repository file (`<name>` ends in `.pack`) read with range requests, instead of
    /// a server's blob URLs.
    pub pack: Option<Arc<PackFile>>,
}

/// A repository file on an HTTP(S) server that honours `Range` (nginx, S3, R2, GCS,
/// Azure, a CDN), as opened.
#[derive(Debug)]
pub struct PackFile {
    /// Its path (with the endpoint's prefix).
    pub path: String,
    /// Header, root directory and tiling.
    pub index: Arc<PackIndex>,
    /// Its `ETag` when opened: sent as `If-Match` with every request and compared with
    /// every answer's, so a replaced file is an error, never a mix of two builds.
    pub etag: Option<String>,
    /// Requests opening it took (1, or 2 when header, root and metadata exceed the
    /// first read).
    pub open_requests: u64,
    /// Bytes opening it read.
    pub open_bytes: u64,
    /// A file in a bucket (`s3://`, `gs://`, `az://`), read through `object_store`
    /// rather than from an HTTP endpoint; `path` is then its URL.
    #[cfg(feature = "object-store")]
    pub(crate) object: Option<super::transport::object_store::ObjectSource>,
}

impl PartialEq for PackFile {
    fn eq(&self, o: &Self) -> bool {
        self.path == o.path && self.etag == o.etag && self.index.header == o.index.header
    }
}

impl Eq for PackFile {}

impl PackFile {
    /// The extra header lines of a request for `range`: `Range`, and `If-Match` with
    /// the pinned `ETag`.
    pub fn headers(&self, range: &ranges::RangeRequest) -> String {
        match self.etag.as_deref().filter(|e| is_strong(e)) {
            Some(etag) => format!("Range: {}\r\nIf-Match: {etag}\r\n", range.header_value()),
            None => format!("Range: {}\r\n", range.header_value()),
        }
    }

    /// Checks a range answer against what was asked (`range`) and the file opened, and
    /// gives its body ([`PackIdentity::check_answer`], shared with the browser).
    pub fn check_answer(
        &self,
        range: quincunx_meta::pack::Section,
        status: u16,
        body: bytes::Bytes,
        content_range: Option<[u64; 3]>,
        etag: Option<&str>,
    ) -> Result<bytes::Bytes, FetchError> {
        self.identity()
            .check_answer(range, status, body, content_range, etag)
    }

    /// What every answer must match.
    pub fn identity(&self) -> PackIdentity {
        PackIdentity {
            path: self.path.clone(),
            file_len: self.index.header.file_len,
            etag: self.etag.clone(),
        }
    }
}

impl Remote {
    /// Fetches `GET {base_url}/repos/{name}/metadata.json` (blocking, on a fresh
    /// connection, within `timeout`) and names the repository's blobs from it.
    pub fn open(
        base_url: &str,
        name: &str,
        timeout: Duration,
    ) -> Result<(Remote, Metadata), FetchError> {
        Remote::open_with(base_url, name, timeout, &ConnectOptions::default())
    }

    /// [`Remote::open`] with an extra trusted CA and an address override (`https://`
    /// URLs get TLS; the blobs later travel the same way).
    pub fn open_with(
        base_url: &str,
        name: &str,
        timeout: Duration,
        options: &ConnectOptions,
    ) -> Result<(Remote, Metadata), FetchError> {
        check_name(name)?;
        if is_object_url(base_url) {
            if !name.ends_with(".pack") {
                return Err(FetchError::BadUrl(format!(
                    "{base_url}: a bucket holds repository files; name one ending in .pack, \
                     not {name:?}"
                )));
            }
            return Remote::open_object(base_url, name, timeout, options);
        }
        // A query string (a presigned URL's signature) goes with every request.
        let (base_url, query) = match base_url.split_once('?') {
            Some((base, query)) => (base, Some(query)),
            None => (base_url, None),
        };
        let endpoint = endpoint(base_url, options)?;
        if name.ends_with(".pack") {
            return Remote::open_pack(endpoint, base_url, query, name, timeout);
        }
        if query.is_some() {
            return Err(FetchError::BadUrl(format!(
                "{base_url}: a query string is kept only for a repository file (a name \
                 ending in .pack), not for a server's repository {name:?}"
            )));
        }
        let path = format!("{}/repos/{name}/metadata.json", endpoint.prefix);
        let url = endpoint.url(&path);
        let (status, body) =
            http1::get_blocking(&endpoint, &path, timeout).map_err(|e| match e {
                http1::Http1Error::TimedOut(t) => FetchError::Metadata(format!(
                    "timed out after {} s fetching the metadata from {url}",
                    t.as_secs_f64()
                )),
                http1::Http1Error::Tls(msg) => FetchError::Tls(format!("GET {url}: {msg}")),
                e => FetchError::Metadata(format!("GET {url}: {e}")),
            })?;
        if status != 200 {
            return Err(FetchError::Metadata(format!("GET {path}: status {status}")));
        }
        let meta: Metadata = serde_json::from_slice(&body)
            .map_err(|e| FetchError::Metadata(format!("{path}: {e}")))?;
        let remote = Remote::with_endpoint(endpoint, base_url, name, &meta)?;
        Ok((remote, meta))
    }

    /// Opens the file `name` in the bucket folder `base_url` through `object_store`.
    #[cfg(feature = "object-store")]
    fn open_object(
        base_url: &str,
        name: &str,
        timeout: Duration,
        options: &ConnectOptions,
    ) -> Result<(Remote, Metadata), FetchError> {
        let opened = super::transport::object_store::open(base_url, name, timeout, options)?;
        // Unused: the object's client reaches the bucket.
        let endpoint = Endpoint {
            addr: std::net::SocketAddr::from(([0, 0, 0, 0], 0)),
            host: String::new(),
            prefix: String::new(),
            tls: None,
        };
        let mut remote = Remote::with_endpoint(endpoint, base_url, name, &opened.meta)?;
        remote.pack = Some(Arc::new(PackFile {
            path: opened.source.url().to_string(),
            index: Arc::new(opened.index),
            etag: opened.etag,
            open_requests: opened.requests,
            open_bytes: opened.bytes,
            object: Some(opened.source),
        }));
        Ok((remote, opened.meta))
    }

    #[cfg(not(feature = "object-store"))]
    fn open_object(
        base_url: &str,
        _name: &str,
        _timeout: Duration,
        _options: &ConnectOptions,
    ) -> Result<(Remote, Metadata), FetchError> {
        Err(FetchError::BadUrl(format!(
            "{base_url}: bucket URLs need quincunx built with the `object-store` feature"
        )))
    }

    /// Opens the repository file `{base_url}/{name}` (or `base_url` itself if it ends in
    /// `/{name}`, as a presigned URL does) with range requests, `?{query}` on every one:
    /// the first [`ranges::FIRST_READ`] bytes, and the rest of header, root directory and
    /// metadata if they are longer (at most two round trips).
    fn open_pack(
        endpoint: Endpoint,
        base_url: &str,
        query: Option<&str>,
        name: &str,
        timeout: Duration,
    ) -> Result<(Remote, Metadata), FetchError> {
        let mut path = match endpoint.prefix.strip_suffix(name) {
            Some(folder) if folder.ends_with('/') => endpoint.prefix.clone(),
            _ => format!("{}/{name}", endpoint.prefix),
        };
        if let Some(q) = query {
            path = format!("{path}?{q}");
        }
        let url = endpoint.url(&path);
        let get = |from: u64, to: u64, etag: Option<&str>| {
            let mut extra = format!("Range: bytes={from}-{}\r\n", to - 1);
            if let Some(e) = etag {
                extra.push_str(&format!("If-Match: {e}\r\n"));
            }
            http1::get_blocking_with(&endpoint, &path, extra.as_bytes(), timeout).map_err(|e| {
                match e {
                    http1::Http1Error::TimedOut(t) => FetchError::Metadata(format!(
                        "timed out after {} s reading {url}",
                        t.as_secs_f64()
                    )),
                    http1::Http1Error::Tls(msg) => FetchError::Tls(format!("GET {url}: {msg}")),
                    http1::Http1Error::BodyTooLarge(n) => FetchError::Metadata(format!(
                        "GET {url}: answered {n} bytes to a range request: the server does \
                         not honour Range (range requests are needed to read a repository \
                         file)"
                    )),
                    e => FetchError::Metadata(format!("GET {url}: {e}")),
                }
            })
        };
        let first = get(0, ranges::FIRST_READ, None)?;
        let total = range_answer::opened_len(
            &url,
            first.status,
            first.content_range,
            first.body.len() as u64,
            ranges::FIRST_READ,
        )
        .map_err(FetchError::Metadata)?;
        let bad = |e: quincunx_meta::pack::PackError| FetchError::Metadata(format!("{url}: {e}"));
        let mut front = first.body;
        let need = ranges::open_len(&front).map_err(bad)?.min(total);
        let mut requests = 1;
        if need > front.len() as u64 {
            let strong = first.etag.as_deref().filter(|e| is_strong(e));
            let rest = get(front.len() as u64, need, strong)?;
            requests += 1;
            match (rest.status, rest.content_range) {
                (206, Some([a, b, t]))
                    if a == front.len() as u64 && b + 1 == need && t == total =>
                {
                    front.extend_from_slice(&rest.body);
                }
                (412, _) => {
                    return Err(FetchError::Changed(format!(
                        "{url} changed while it was being opened (412)"
                    )));
                }
                (status, range) => {
                    return Err(FetchError::Metadata(format!(
                        "GET {url} (bytes {}-{}): status {status}, Content-Range {range:?}",
                        front.len(),
                        need - 1
                    )));
                }
            }
        }
        let open_bytes = front.len() as u64;
        let (index, meta) = PackIndex::open(&front, total).map_err(bad)?;
        let mut remote = Remote::with_endpoint(endpoint, base_url, name, &meta)?;
        remote.pack = Some(Arc::new(PackFile {
            path,
            index: Arc::new(index),
            etag: first.etag,
            open_requests: requests,
            open_bytes,
            #[cfg(feature = "object-store")]
            object: None,
        }));
        Ok((remote, meta))
    }

    /// Names the blobs of repository `name` described by `meta`, served at `base_url`.
    pub fn from_metadata(
        base_url: &str,
        name: &str,
        meta: &Metadata,
    ) -> Result<Remote, FetchError> {
        let endpoint = endpoint(base_url, &ConnectOptions::default())?;
        Remote::with_endpoint(endpoint, base_url, name, meta)
    }

    fn with_endpoint(
        endpoint: Endpoint,
        base_url: &str,
        name: &str,
        meta: &Metadata,
    ) -> Result<Remote, FetchError> {
        check_name(name)?;
        let hash = meta.content_hash.as_bytes();
        if hash.len() < 16 || !hash.iter().all(u8::is_ascii_hexdigit) {
            return Err(FetchError::Metadata(format!(
                "content_hash {:?} is not hex",
                meta.content_hash
            )));
        }
        let sphere = meta.domain == quincunx_meta::Domain::Sphere;
        Ok(Remote {
            endpoint,
            base_url: base_url.trim_end_matches('/').to_string(),
            name: name.to_string(),
            version: meta.content_hash[..16].to_string(),
            sphere,
            static_export: meta.static_export,
            pack: None,
        })
    }

    /// The request path of `key` (with the endpoint's prefix).
    pub fn blob_path(&self, key: Key) -> String {
        self.path(key, "d")
    }

    fn path(&self, key: Key, kind: &str) -> String {
        let [x, y, z] = key;
        let Remote {
            endpoint,
            name,
            version,
            ..
        } = self;
        let prefix = &endpoint.prefix;
        if self.sphere {
            format!("{prefix}/repos/{name}/v/{version}/{kind}/{x}/{y}/{z}")
        } else {
            format!("{prefix}/repos/{name}/v/{version}/{kind}/{x}/{y}")
        }
    }

    /// The path of `key`'s package: its blob with its small owned children's
    /// (`quincunx_meta::answer`; repositories with an inlining limit only).
    pub fn package_path(&self, key: Key) -> String {
        self.path(key, "p")
    }

    /// The absolute URL of `key`.
    pub fn blob_url(&self, key: Key) -> String {
        self.endpoint.url(&self.blob_path(key))
    }
}

/// Whether `url` names a bucket (read through `object_store`, feature `object-store`)
/// rather than an HTTP server.
fn is_object_url(url: &str) -> bool {
    const SCHEMES: [&str; 8] = [
        "s3://", "s3a://", "gs://", "az://", "adl://", "azure://", "abfs://", "abfss://",
    ];
    SCHEMES.iter().any(|s| url.starts_with(s))
}

fn endpoint(base_url: &str, options: &ConnectOptions) -> Result<Endpoint, FetchError> {
    Endpoint::from_url_with(base_url, options).map_err(|e| match e {
        http1::Http1Error::Tls(msg) => FetchError::Tls(msg),
        e => FetchError::BadUrl(e.to_string()),
    })
}

fn check_name(name: &str) -> Result<(), FetchError> {
    if name.is_empty()
        || name.starts_with('.')
        || !name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || "-_.".contains(c))
    {
        return Err(FetchError::BadUrl(format!(
            "repository name {name:?}: ASCII letters, digits, '-', '_' or '.'"
        )));
    }
    Ok(())
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use super::*;

    fn remote(sphere: bool, base: &str) -> Remote {
        Remote {
            endpoint: Endpoint::from_url(base).unwrap(),
            base_url: base.into(),
            name: "r".into(),
            version: "0123456789abcdef".into(),
            sphere,
            static_export: false,
            pack: None,
        }
    }

    #[test]
    fn planar_keys_use_two_coordinates_and_sphere_keys_three() {
        let p = remote(false, "http://127.0.0.1:9/pre");
        assert_eq!(
            p.blob_path([3, -5, 0]),
            "/pre/repos/r/v/0123456789abcdef/d/3/-5"
        );
        assert_eq!(
            p.blob_url([3, 5, 0]),
            "http://127.0.0.1:9/pre/repos/r/v/0123456789abcdef/d/3/5"
        );
        let s = remote(true, "http://127.0.0.1:9");
        assert_eq!(
            s.blob_path([1, -2, 8]),
            "/repos/r/v/0123456789abcdef/d/1/-2/8"
        );
    }

    #[test]
    fn bucket_schemes_are_told_from_http() {
        assert!(is_object_url("s3://b/k"));
        assert!(is_object_url("gs://b/k"));
        assert!(is_object_url("az://c/k"));
        assert!(!is_object_url("https://b.s3.amazonaws.com/k"));
        assert!(!is_object_url("http://127.0.0.1:9/s3://"));
    }

    #[test]
    fn bad_names_are_refused() {
        for bad in ["", ".x", "a/b", "a b", "é"] {
            assert!(check_name(bad).is_err(), "{bad}");
        }
        assert!(check_name("korea_4097.v2-x").is_ok());
    }
}
