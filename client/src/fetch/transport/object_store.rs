//! Repository files in private buckets (`s3://`, `gs://`, `az://` URLs) through the
//! `object_store` crate: opening, and a transport that turns each range request into a
//! signed `GET` with `Range` and `If-Match`.
//!
//! Credentials and endpoints come from the environment, as the providers' own tools read
//! them (`AWS_*`, `GOOGLE_*`, `AZURE_*`). Answers carry the same [`RangeMeta`] as an HTTP
//! answer's (content range from the returned range and the object's size, the object's
//! `ETag`), so the worker checks them the same way (`PackFile::check_answer`, the
//! blobs' CRCs).

use std::sync::Arc;
use std::time::Duration;

use bytes::Bytes;
use object_store::path::Path;
use object_store::{GetOptions, GetRange, ObjectStore, ObjectStoreScheme, RetryConfig};
use tokio::sync::mpsc::UnboundedSender;

use quincunx_client_core::fetch::ranges::{self, PackIndex};
use quincunx_meta::Metadata;

use super::{Completion, RangeMeta, Request, Slots};
use crate::fetch::tls::ConnectOptions;
use crate::fetch::{FetchConfig, FetchError};

/// A repository file in a bucket: its URL and the settings to reach it, from which each
/// runtime builds its own client (a client's connections belong to the runtime that
/// made them).
#[derive(Clone)]
pub(crate) struct ObjectSource {
    /// `s3://bucket/path/file.pack` and so on.
    url: url::Url,
    /// `(config key, value)`: the environment's, then ours.
    options: Vec<(String, String)>,
    timeout: Duration,
}

impl ObjectSource {
    /// The file `name` in the bucket folder `base_url`; `connect_to` (an emulated link in
    /// front of an `http://` S3 endpoint) replaces the endpoint's address.
    fn new(
        base_url: &str,
        name: &str,
        timeout: Duration,
        options: &ConnectOptions,
    ) -> Result<ObjectSource, FetchError> {
        let full = format!("{}/{name}", base_url.trim_end_matches('/'));
        let url = url::Url::parse(&full).map_err(|e| FetchError::BadUrl(format!("{full}: {e}")))?;
        let prefixes = ["AWS_", "GOOGLE_", "AZURE_"];
        let mut pairs: Vec<(String, String)> = std::env::vars()
            .filter(|(k, _)| prefixes.iter().any(|p| k.starts_with(p)))
            .map(|(k, v)| (k.to_ascii_lowercase(), v))
            .collect();
        pairs.extend(
            options
                .bucket
                .0
                .iter()
                .map(|(k, v)| (k.to_ascii_lowercase(), v.clone())),
        );
        let secs = format!("{}ms", timeout.as_millis().max(1));
        pairs.push(("connect_timeout".into(), secs.clone()));
        pairs.push(("timeout".into(), secs));
        if let Some(addr) = options.connect_to {
            let endpoint = pairs
                .iter()
                .find(|(k, _)| k == "aws_endpoint_url" || k == "aws_endpoint")
                .map(|(_, v)| v.clone());
            match endpoint {
                Some(e) if e.starts_with("http://") => {
                    pairs.push(("aws_endpoint".into(), format!("http://{addr}")));
                }
                _ => {
                    return Err(FetchError::BadUrl(format!(
                        "{full}: an address override (emulated link) needs an http:// \
                         endpoint in AWS_ENDPOINT_URL"
                    )));
                }
            }
        }
        Ok(ObjectSource {
            url,
            options: pairs,
            timeout,
        })
    }

    /// The URL, for messages.
    pub fn url(&self) -> &str {
        self.url.as_str()
    }

    /// A client for the current runtime, and the object's path in its bucket.
    fn build(&self) -> Result<(Arc<dyn ObjectStore>, Path), FetchError> {
        // reqwest's rustls has no bundled provider here: ours, unless one is installed.
        let _ =
            rustls::crypto::CryptoProvider::install_default(rustls_graviola::default_provider());
        let bad = |e: &dyn std::fmt::Display| FetchError::BadUrl(format!("{}: {e}", self.url));
        let (scheme, path) = ObjectStoreScheme::parse(&self.url).map_err(|e| bad(&e))?;
        let path = Path::parse(path).map_err(|e| bad(&e))?;
        // The worker retries (and counts) failures itself.
        let retry = RetryConfig {
            max_retries: 0,
            retry_timeout: self.timeout,
            ..RetryConfig::default()
        };
        macro_rules! build {
            ($builder:ty) => {{
                let b = self.options.iter().fold(
                    <$builder>::new().with_url(self.url.as_str()),
                    |b, (k, v)| match k.parse() {
                        Ok(key) => b.with_config(key, v),
                        Err(_) => b,
                    },
                );
                Arc::new(b.with_retry(retry).build().map_err(|e| bad(&e))?) as Arc<dyn ObjectStore>
            }};
        }
        let store = match scheme {
            ObjectStoreScheme::AmazonS3 => build!(object_store::aws::AmazonS3Builder),
            ObjectStoreScheme::GoogleCloudStorage => {
                build!(object_store::gcp::GoogleCloudStorageBuilder)
            }
            ObjectStoreScheme::MicrosoftAzure => build!(object_store::azure::MicrosoftAzureBuilder),
            other => return Err(bad(&format!("{other:?} is not a bucket"))),
        };
        Ok((store, path))
    }
}

impl std::fmt::Debug for ObjectSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        // The options' values hold secrets.
        let keys: Vec<&str> = self.options.iter().map(|(k, _)| k.as_str()).collect();
        f.debug_struct("ObjectSource")
            .field("url", &self.url.as_str())
            .field("options", &keys)
            .finish()
    }
}

/// A repository file opened in a bucket.
pub(crate) struct Opened {
    pub source: ObjectSource,
    pub index: PackIndex,
    pub meta: Metadata,
    pub etag: Option<String>,
    pub requests: u64,
    pub bytes: u64,
}

/// Opens the file `name` in the bucket folder `base_url`: the first
/// [`ranges::FIRST_READ`] bytes, and the rest of header, root directory and metadata if
/// they are longer (at most two round trips). Blocks; runs on a thread of its own, so it
/// may be called from anywhere, an async context included.
pub(crate) fn open(
    base_url: &str,
    name: &str,
    timeout: Duration,
    options: &ConnectOptions,
) -> Result<Opened, FetchError> {
    let source = ObjectSource::new(base_url, name, timeout, options)?;
    let opened = std::thread::scope(|s| {
        s.spawn(|| {
            let runtime = tokio::runtime::Builder::new_current_thread()
                .enable_all()
                .build()
                .map_err(|e| FetchError::Thread(format!("runtime: {e}")))?;
            runtime.block_on(read_front(&source, timeout))
        })
        .join()
    });
    let (index, meta, etag, requests, bytes) =
        opened.map_err(|_| FetchError::Thread("opening the file panicked".into()))??;
    Ok(Opened {
        source,
        index,
        meta,
        etag,
        requests,
        bytes,
    })
}

type Front = (PackIndex, Metadata, Option<String>, u64, u64);

async fn read_front(source: &ObjectSource, timeout: Duration) -> Result<Front, FetchError> {
    let url = source.url();
    let (store, path) = source.build()?;
    let get = |range: std::ops::Range<u64>, if_match: Option<String>| {
        let (store, path) = (Arc::clone(&store), path.clone());
        async move {
            let options = GetOptions {
                range: Some(GetRange::Bounded(range)),
                if_match,
                ..GetOptions::default()
            };
            let read = async {
                let got = store.get_opts(&path, options).await?;
                let (range, size, etag) =
                    (got.range.clone(), got.meta.size, got.meta.e_tag.clone());
                Ok::<_, object_store::Error>((range, size, etag, got.bytes().await?))
            };
            match tokio::time::timeout(timeout, read).await {
                Ok(r) => r.map_err(|e| open_error(url, &e)),
                Err(_) => Err(FetchError::Metadata(format!(
                    "timed out after {} s reading {url}",
                    timeout.as_secs_f64()
                ))),
            }
        }
    };
    let (range, total, etag, first) = get(0..ranges::FIRST_READ, None).await?;
    if range.start != 0 || range.end - range.start != first.len() as u64 {
        return Err(FetchError::Metadata(format!(
            "{url}: asked for bytes 0-{}, got {range:?} ({} bytes)",
            ranges::FIRST_READ - 1,
            first.len()
        )));
    }
    let bad = |e: quincunx_meta::pack::PackError| FetchError::Metadata(format!("{url}: {e}"));
    let mut front = first.to_vec();
    let need = ranges::open_len(&front).map_err(bad)?.min(total);
    let mut requests = 1;
    if need > front.len() as u64 {
        let from = front.len() as u64;
        let (r, t, e, rest) = get(from..need, etag.clone()).await?;
        requests += 1;
        if r != (from..need) || t != total || e != etag || rest.len() as u64 != need - from {
            return Err(FetchError::Changed(format!(
                "{url} changed while it was being opened"
            )));
        }
        front.extend_from_slice(&rest);
    }
    let bytes = front.len() as u64;
    let (index, meta) = PackIndex::open(&front, total).map_err(bad)?;
    Ok((index, meta, etag, requests, bytes))
}

/// An error opening the file, naming the URL and what to check.
fn open_error(url: &str, e: &object_store::Error) -> FetchError {
    use object_store::Error as E;
    match e {
        E::NotFound { .. } => {
            FetchError::Metadata(format!("{url}: 404 no such key or bucket: {e}"))
        }
        E::PermissionDenied { .. } | E::Unauthenticated { .. } => FetchError::Metadata(format!(
            "{url}: 403 access denied (check the credentials: AWS_ACCESS_KEY_ID and \
             AWS_SECRET_ACCESS_KEY, GOOGLE_APPLICATION_CREDENTIALS or AZURE_STORAGE_*): {e}"
        )),
        E::Precondition { .. } => {
            FetchError::Changed(format!("{url} changed while it was being opened (412)"))
        }
        e => FetchError::Metadata(format!("{url}: {e}")),
    }
}

/// The status an `object_store` error stands for, when it stands for one; else the
/// error (a connection failure: transient).
fn status_of(e: object_store::Error) -> Result<u16, FetchError> {
    use object_store::Error as E;
    match e {
        E::NotFound { .. } => Ok(404),
        E::PermissionDenied { .. } => Ok(403),
        E::Unauthenticated { .. } => Ok(401),
        E::Precondition { .. } => Ok(412),
        E::NotModified { .. } => Ok(304),
        E::Generic { .. } => {
            let msg = error_chain(&e);
            if msg.contains("416") || msg.contains("Range Not Satisfiable") {
                Ok(416)
            } else {
                Err(FetchError::Connection(msg))
            }
        }
        e => Err(FetchError::Protocol(error_chain(&e))),
    }
}

fn error_chain(e: &dyn std::error::Error) -> String {
    let mut msg = e.to_string();
    let mut source = e.source();
    while let Some(s) = source {
        msg.push_str(": ");
        msg.push_str(&s.to_string());
        source = s.source();
    }
    msg
}

/// The range and pinned `ETag` of a range request's header lines (`PackFile::headers`).
fn range_and_etag(headers: &str) -> Option<(std::ops::Range<u64>, Option<String>)> {
    let mut range = None;
    let mut etag = None;
    for line in headers.split_terminator("\r\n") {
        let (name, value) = line.split_once(':')?;
        let value = value.trim();
        if name.eq_ignore_ascii_case("range") {
            let (a, b) = value.strip_prefix("bytes=")?.split_once('-')?;
            let (a, b): (u64, u64) = (a.parse().ok()?, b.parse().ok()?);
            range = (a <= b).then(|| a..b + 1);
        } else if name.eq_ignore_ascii_case("if-match") {
            etag = Some(value.to_string());
        }
    }
    Some((range?, etag))
}

/// Range requests to one object, many at once (each its own task; the worker's window
/// decides how many).
pub(crate) struct ObjectStoreDriver {
    store: Arc<dyn ObjectStore>,
    path: Path,
    slots: Slots,
    max_body_bytes: usize,
    deadline: Duration,
    done: UnboundedSender<Completion>,
}

impl ObjectStoreDriver {
    pub fn new(
        config: &FetchConfig,
        source: &ObjectSource,
        done: UnboundedSender<Completion>,
    ) -> Result<Self, FetchError> {
        let (store, path) = source.build()?;
        Ok(ObjectStoreDriver {
            store,
            path,
            slots: Slots::new(config.max_in_flight),
            max_body_bytes: config.limits.max_body_bytes,
            deadline: config.request_deadline,
            done,
        })
    }

    pub fn free_slots(&self) -> usize {
        self.slots.free()
    }

    pub fn send(&mut self, request: Request) -> bool {
        if !self.slots.take() {
            return false;
        }
        let (store, path, done) = (
            Arc::clone(&self.store),
            self.path.clone(),
            self.done.clone(),
        );
        let (max_body, deadline) = (self.max_body_bytes, self.deadline);
        tokio::spawn(async move {
            let (range, result) = match range_and_etag(&request.headers) {
                Some((range, if_match)) if range.end - range.start <= max_body as u64 => {
                    match tokio::time::timeout(deadline, get(&*store, &path, range, if_match)).await
                    {
                        Ok(answer) => answer,
                        Err(_) => (None, Err(FetchError::Deadline(deadline))),
                    }
                }
                _ => (
                    None,
                    Err(FetchError::Protocol(format!(
                        "not a range request of at most {max_body} bytes: {:?}",
                        request.headers
                    ))),
                ),
            };
            let _ = done.send(Completion {
                key: request.key,
                tag: request.tag,
                range,
                slot: 0,
                result,
            });
        });
        true
    }

    pub fn finished(&mut self) {
        self.slots.release();
    }
}

/// One signed range `GET`: a 206 with what the answer says about itself, a status for
/// the errors that stand for one (the worker's checks name them), or a failure.
async fn get(
    store: &dyn ObjectStore,
    path: &Path,
    range: std::ops::Range<u64>,
    if_match: Option<String>,
) -> (Option<RangeMeta>, Result<(u16, Bytes), FetchError>) {
    let options = GetOptions {
        range: Some(GetRange::Bounded(range)),
        if_match,
        ..GetOptions::default()
    };
    let got = match store.get_opts(path, options).await {
        Ok(got) => got,
        Err(e) => return (None, status_of(e).map(|s| (s, Bytes::new()))),
    };
    let meta = RangeMeta {
        content_range: (got.range.end > got.range.start)
            .then(|| [got.range.start, got.range.end - 1, got.meta.size]),
        etag: got.meta.e_tag.clone(),
    };
    let want = got.range.end - got.range.start;
    let result = match got.bytes().await {
        Ok(body) if body.len() as u64 == want => Ok((206, body)),
        Ok(body) => Err(FetchError::Connection(format!(
            "{} bytes of a {want}-byte range",
            body.len()
        ))),
        Err(e) => Err(FetchError::Connection(error_chain(&e))),
    };
    (Some(meta), result)
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn range_requests_read_back_from_their_headers() {
        assert_eq!(
            range_and_etag("Range: bytes=10-19\r\nIf-Match: \"abc\"\r\n"),
            Some((10..20, Some("\"abc\"".into())))
        );
        assert_eq!(range_and_etag("Range: bytes=0-0\r\n"), Some((0..1, None)));
        for bad in [
            "",
            "Range: bytes=5-4\r\n",
            "Range: items=0-1\r\n",
            "If-Match: x\r\n",
        ] {
            assert_eq!(range_and_etag(bad), None, "{bad}");
        }
    }
}
