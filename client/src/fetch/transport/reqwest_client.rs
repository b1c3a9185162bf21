//! Plain HTTP/1.1 (one request at a time per connection) and HTTP/2 (one connection, many
//! streams) through reqwest, for comparison with the pipelined transport.

use std::time::Duration;

use bytes::Bytes;
use tokio::sync::mpsc::UnboundedSender;

use super::{Completion, RangeMeta, Request, Slots};
use crate::fetch::tls::find_tls_cause;
use crate::fetch::{FetchConfig, FetchError, Transport};

/// A reqwest client and how many requests it may have outstanding.
pub(crate) struct ReqwestDriver {
    client: reqwest::Client,
    /// `scheme://authority` requests go to.
    origin: String,
    /// The URL's host, for messages about TLS failures.
    tls_host: Option<String>,
    slots: Slots,
    max_body_bytes: usize,
    timeout: Duration,
    deadline: Duration,
    done: UnboundedSender<Completion>,
}

impl ReqwestDriver {
    pub fn new(
        config: &FetchConfig,
        done: UnboundedSender<Completion>,
    ) -> Result<Self, FetchError> {
        let builder = reqwest::Client::builder()
            .no_proxy()
            .tcp_nodelay(true)
            .connect_timeout(config.request_timeout)
            // No progress for the timeout, or no whole response by the deadline.
            .read_timeout(config.request_timeout)
            .timeout(config.request_deadline);
        let endpoint = &config.remote.endpoint;
        let tls = endpoint.tls.as_ref();
        let (builder, slots) = match config.transport {
            // At most `connections` requests outstanding, so at most that many connections.
            Transport::Plain => (
                builder
                    .http1_only()
                    .pool_max_idle_per_host(config.connections.max(1)),
                config.connections,
            ),
            // Over TLS, HTTP/2 by ALPN where the server offers it (else HTTP/1.1).
            _ if tls.is_some() => (builder, config.max_in_flight),
            _ => (builder.http2_prior_knowledge(), config.max_in_flight),
        };
        let builder = match tls {
            // reqwest builds a rustls configuration even for http://, and without a
            // process-wide default provider that panics ("No provider set"): give it one
            // of ours, which plain HTTP never uses.
            None => builder.use_preconfigured_tls(
                crate::fetch::tls::cleartext_placeholder()
                    .map_err(|e| FetchError::Thread(format!("HTTP client: {e}")))?,
            ),
            Some(tls) => {
                let rustls = match config.transport {
                    Transport::Plain => tls.http1_config(),
                    _ => tls.h2_config(),
                };
                builder
                    .use_preconfigured_tls((*rustls).clone())
                    .https_only(true)
            }
        };
        // Requests name the URL's host (the certificate's) and go to `endpoint.addr`
        // (resolved, or a link or proxy in front of the server): the connection uses the
        // URL's port, so the authority carries the address's.
        let name = endpoint.host_name();
        let port = endpoint.addr.port();
        let (builder, authority) = if name.parse::<std::net::IpAddr>().is_ok() {
            (builder, socket_authority(endpoint.addr))
        } else {
            (
                builder.resolve(name, endpoint.addr),
                format!("{name}:{port}"),
            )
        };
        let client = builder
            .build()
            .map_err(|e| FetchError::Thread(format!("HTTP client: {e}")))?;
        Ok(ReqwestDriver {
            client,
            origin: format!("{}://{authority}", endpoint.scheme()),
            tls_host: tls.map(|t| t.host()),
            slots: Slots::new(slots),
            max_body_bytes: config.limits.max_body_bytes,
            timeout: config.request_timeout,
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
        let url = format!("{}{}", self.origin, request.path);
        let mut get = self.client.get(url);
        for line in request.headers.split_terminator("\r\n") {
            if let Some((name, value)) = line.split_once(':') {
                get = get.header(name.trim(), value.trim());
            }
        }
        let ranged = !request.headers.is_empty();
        let get = get.send();
        let done = self.done.clone();
        let max_body = self.max_body_bytes;
        let (timeout, deadline) = (self.timeout, self.deadline);
        let tls_host = self.tls_host.clone();
        let started = std::time::Instant::now();
        tokio::spawn(async move {
            let mut range = None;
            let result = match get.await {
                Ok(resp) => {
                    if ranged {
                        range = Some(range_meta(&resp));
                    }
                    read_body(resp, max_body, timeout).await
                }
                Err(e) => Err(
                    match tls_host.as_deref().and_then(|h| find_tls_cause(&e, h)) {
                        Some(msg) => FetchError::Tls(msg),
                        None => classify(&e, timeout),
                    },
                ),
            };
            // reqwest says "timed out" for both: the total one is the deadline.
            let result = match result {
                Err(FetchError::Timeout(_)) if started.elapsed() >= deadline => {
                    Err(FetchError::Deadline(deadline))
                }
                r => r,
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

async fn read_body(
    resp: reqwest::Response,
    max_body: usize,
    timeout: Duration,
) -> Result<(u16, Bytes), FetchError> {
    let status = resp.status().as_u16();
    if resp.content_length().is_some_and(|n| n > max_body as u64) {
        return Err(FetchError::Protocol(format!(
            "response body over {max_body} bytes"
        )));
    }
    // A body that ends early (truncated) is a connection failure, whatever reqwest calls it.
    let body = resp
        .bytes()
        .await
        .map_err(|e| match classify(&e, timeout) {
            FetchError::Protocol(msg) => FetchError::Connection(msg),
            other => other,
        })?;
    if body.len() > max_body {
        return Err(FetchError::Protocol(format!(
            "response body over {max_body} bytes"
        )));
    }
    Ok((status, body))
}

/// The `Content-Range` and `ETag` of an answer (a malformed `Content-Range` reads as
/// none: the range check then refuses the answer).
fn range_meta(resp: &reqwest::Response) -> RangeMeta {
    let header = |name| {
        resp.headers()
            .get(name)
            .map(|v| String::from_utf8_lossy(v.as_bytes()).into_owned())
    };
    RangeMeta {
        content_range: header("content-range")
            .and_then(|v| crate::fetch::http1::parse_content_range(v.as_bytes())),
        etag: header("etag"),
    }
}

/// `ip:port`, IPv6 in brackets.
fn socket_authority(addr: std::net::SocketAddr) -> String {
    match addr {
        std::net::SocketAddr::V6(a) => format!("[{}]:{}", a.ip(), a.port()),
        a => a.to_string(),
    }
}

/// Maps a reqwest error to our classes, with its causes in the message.
fn classify(e: &reqwest::Error, timeout: Duration) -> FetchError {
    let mut msg = e.to_string();
    let mut source = std::error::Error::source(e);
    while let Some(s) = source {
        msg.push_str(": ");
        msg.push_str(&s.to_string());
        source = s.source();
    }
    if e.is_timeout() {
        FetchError::Timeout(timeout)
    } else if e.is_connect() || e.is_body() || e.is_request() {
        FetchError::Connection(msg)
    } else {
        FetchError::Protocol(msg)
    }
}
