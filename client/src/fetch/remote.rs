//! Where a repository's blobs are: base URL, name, version, and the URL of a key.

use std::time::Duration;

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
        let endpoint = endpoint(base_url, options)?;
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
    fn bad_names_are_refused() {
        for bad in ["", ".x", "a/b", "a b", "é"] {
            assert!(check_name(bad).is_err(), "{bad}");
        }
        assert!(check_name("korea_4097.v2-x").is_ok());
    }
}
