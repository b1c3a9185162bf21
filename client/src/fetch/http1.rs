//! A minimal pipelined HTTP/1.1 client: persistent TCP connections, GET requests written
//! in batches, responses read back in order. Used by the [`Transport::Pipelined`]
//! transport of the fetch layer and by `quincunx loadtest`.
//!
//! [`Transport::Pipelined`]: super::Transport::Pipelined
//!
//! Responses are framed strictly: a status line and headers parsed by `httparse`, a body of
//! exactly `Content-Length` bytes (none for 204 and 304). Interim (1xx) answers such as
//! `100 Continue` are skipped before the final one; `101 Switching Protocols`, chunked
//! bodies, oversized heads and bodies are errors, never panics, and no allocation follows a
//! length field beyond [`Limits::max_body_bytes`].
//!
//! `https://` endpoints speak TLS ([`super::tls`]); the framing is the same.
//!
//! The byte-level framing lives in [`ResponseDecoder`], which is pure (bytes in, responses
//! out) so it can be tested with responses split anywhere; [`Connection`] feeds it from a
//! socket.

use std::net::SocketAddr;

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

use super::tls::{ConnectOptions, Stream, TlsClient, tls_cause};

/// Most headers accepted in one response.
pub const MAX_HEADERS: usize = 64;

/// Size bounds on responses.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Limits {
    /// Longest accepted status line plus headers, in bytes.
    pub max_head_bytes: usize,
    /// Largest accepted body, in bytes.
    pub max_body_bytes: usize,
}

impl Default for Limits {
    fn default() -> Self {
        Limits {
            max_head_bytes: 64 * 1024,
            max_body_bytes: 16 * 1024 * 1024,
        }
    }
}

/// Why a response could not be read.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum Http1Error {
    /// The socket failed.
    #[error("connection: {0}")]
    Io(#[from] std::io::Error),
    /// The server closed the connection before a whole response arrived.
    #[error("connection closed by the server")]
    Closed,
    /// The status line or headers are not valid HTTP/1.x.
    #[error("malformed response head: {0}")]
    Malformed(httparse::Error),
    /// The status line and headers exceed [`Limits::max_head_bytes`].
    #[error("response head longer than {0} bytes")]
    HeadTooLarge(usize),
    /// `Content-Length` exceeds [`Limits::max_body_bytes`].
    #[error("response body of {0} bytes exceeds the limit")]
    BodyTooLarge(u64),
    /// No `Content-Length` on a response that has a body.
    #[error("response without Content-Length")]
    MissingContentLength,
    /// `Content-Length` is not a decimal number, or two of them disagree.
    #[error("invalid Content-Length")]
    BadContentLength,
    /// `Content-Range` is not `bytes <first>-<last>/<total>` or `bytes */<total>`.
    #[error("invalid Content-Range")]
    BadContentRange,
    /// `Transfer-Encoding` is set (chunked bodies are not supported).
    #[error("Transfer-Encoding is not supported")]
    TransferEncoding,
    /// A `101 Switching Protocols` answer (this client never asks for one).
    #[error("unexpected informational response {0}")]
    Informational(u16),
    /// The URL is not `http://host[:port][/prefix]` or `https://host[:port][/prefix]`.
    #[error("bad URL {0:?}: expected http://host[:port][/prefix] or https://host[:port][/prefix]")]
    BadUrl(String),
    /// The TLS handshake failed or the certificate was refused (the message names why:
    /// unknown issuer, wrong host name, expired), or TLS could not be set up.
    #[error("{0}")]
    Tls(String),
    /// No whole response within the time allowed ([`get_blocking`]).
    #[error("timed out after {} s", .0.as_secs_f64())]
    TimedOut(std::time::Duration),
}

/// Where requests go: a resolved address, the `Host` header value, a path prefix and,
/// for `https://`, the TLS settings.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Endpoint {
    /// The server's socket address (or [`ConnectOptions::connect_to`]).
    pub addr: SocketAddr,
    /// `Host` header value (`host[:port]` as written in the URL).
    pub host: String,
    /// Path prefix without a trailing slash (empty for the server root).
    pub prefix: String,
    /// TLS to the URL's host (`https://`), `None` for `http://`.
    pub tls: Option<TlsClient>,
}

impl Endpoint {
    /// Parses `http://host[:port][/prefix]` or `https://host[:port][/prefix]` and
    /// resolves the host (blocking DNS lookup); `https://` trusts the system's roots.
    pub fn from_url(url: &str) -> Result<Endpoint, Http1Error> {
        Endpoint::from_url_with(url, &ConnectOptions::default())
    }

    /// [`Endpoint::from_url`] with an extra trusted CA and an address override.
    pub fn from_url_with(url: &str, options: &ConnectOptions) -> Result<Endpoint, Http1Error> {
        let bad = || Http1Error::BadUrl(url.to_string());
        let (rest, https) = match (url.strip_prefix("http://"), url.strip_prefix("https://")) {
            (Some(rest), _) => (rest, false),
            (None, Some(rest)) => (rest, true),
            (None, None) => return Err(bad()),
        };
        let (authority, path) = match rest.find('/') {
            Some(i) => rest.split_at(i),
            None => (rest, ""),
        };
        if authority.is_empty()
            || path.contains(['?', '#', ' '])
            || !authority
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || "-._:[]".contains(c))
        {
            return Err(bad());
        }
        let has_port = !authority.ends_with(']') && authority.contains(':');
        let with_port = if has_port {
            authority.to_string()
        } else {
            format!("{authority}:{}", if https { 443 } else { 80 })
        };
        let addr = match options.connect_to {
            Some(addr) => addr,
            None => std::net::ToSocketAddrs::to_socket_addrs(&with_port)
                .map_err(|_| bad())?
                .next()
                .ok_or_else(bad)?,
        };
        let tls = if https {
            let name = match with_port.rfind(':') {
                Some(i) => &with_port[..i],
                None => with_port.as_str(),
            };
            let name = name.trim_start_matches('[').trim_end_matches(']');
            let client = TlsClient::new(name, options.ca_cert_pem.as_deref())
                .map_err(|e| Http1Error::Tls(e.to_string()))?;
            Some(client)
        } else {
            None
        };
        Ok(Endpoint {
            addr,
            host: authority.to_string(),
            prefix: path.trim_end_matches('/').to_string(),
            tls,
        })
    }

    /// The URL's host without port or brackets (a name or an address).
    pub fn host_name(&self) -> &str {
        let h = self.host.as_str();
        let h = match (h.rfind(':'), h.rfind(']')) {
            (Some(colon), Some(bracket)) if colon > bracket => &h[..colon],
            (Some(colon), None) => &h[..colon],
            _ => h,
        };
        h.trim_start_matches('[').trim_end_matches(']')
    }

    /// `https` or `http`.
    pub fn scheme(&self) -> &'static str {
        if self.tls.is_some() { "https" } else { "http" }
    }

    /// The absolute URL of `path` (which starts with the prefix).
    pub fn url(&self, path: &str) -> String {
        format!("{}://{}{path}", self.scheme(), self.host)
    }

    /// A connection to the server: TCP (`TCP_NODELAY`), then TLS for `https://`.
    pub async fn connect(&self) -> Result<Stream, Http1Error> {
        let tcp = TcpStream::connect(self.addr).await?;
        tcp.set_nodelay(true)?;
        match &self.tls {
            None => Ok(Stream::Plain(tcp)),
            Some(tls) => tls.connect(tcp).await.map_err(|e| io_error(e, self)),
        }
    }
}

/// An I/O error as an [`Http1Error`]: a TLS failure inside it is named as such.
pub(crate) fn io_error(e: std::io::Error, endpoint: &Endpoint) -> Http1Error {
    match endpoint.tls.as_ref().and_then(|t| tls_cause(&e, &t.host())) {
        Some(msg) => Http1Error::Tls(msg),
        None => Http1Error::Io(e),
    }
}

/// Appends `GET <path> HTTP/1.1` with a `Host` header to `out`.
pub fn write_get(out: &mut Vec<u8>, host: &str, path: &[u8]) {
    write_get_with(out, host, path, b"");
}

/// [`write_get`] with more header lines (`extra`: each ending in CR LF, e.g. a `Range`).
pub fn write_get_with(out: &mut Vec<u8>, host: &str, path: &[u8], extra: &[u8]) {
    out.extend_from_slice(b"GET ");
    out.extend_from_slice(path);
    out.extend_from_slice(b" HTTP/1.1\r\nHost: ");
    out.extend_from_slice(host.as_bytes());
    out.extend_from_slice(b"\r\n");
    out.extend_from_slice(extra);
    out.extend_from_slice(b"\r\n");
}

/// Pre-rendered request bytes for GETs of paths sharing a prefix: rendering one request is
/// three copies, with no formatting and no allocation once `out` has grown.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct GetTemplate {
    head: Vec<u8>,
    tail: Vec<u8>,
}

impl GetTemplate {
    /// Requests for `<path_prefix><suffix>` with `Host: host`.
    pub fn new(host: &str, path_prefix: &str) -> Self {
        GetTemplate {
            head: format!("GET {path_prefix}").into_bytes(),
            tail: format!(" HTTP/1.1\r\nHost: {host}\r\n\r\n").into_bytes(),
        }
    }

    /// Appends the request for `suffix` to `out`.
    pub fn push(&self, out: &mut Vec<u8>, suffix: &[u8]) {
        out.extend_from_slice(&self.head);
        out.extend_from_slice(suffix);
        out.extend_from_slice(&self.tail);
    }
}

/// One response, borrowed from the decoder's buffer until the next one is decoded.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Response<'a> {
    /// Status code.
    pub status: u16,
    /// The body (empty for 204 and 304).
    pub body: &'a [u8],
    /// The server announced `Connection: close`: nothing more will arrive.
    pub close: bool,
    /// `Content-Range: bytes <first>-<last>/<total>`, when given (`total` = `u64::MAX`
    /// for `*`; `first` = `u64::MAX` for `bytes */<total>`, a 416's).
    pub content_range: Option<[u64; 3]>,
    /// The `ETag` header's value, when given.
    pub etag: Option<&'a [u8]>,
}

/// Where a decoded response lies in the buffer.
#[derive(Clone, Copy, Debug)]
struct Frame {
    status: u16,
    body_start: usize,
    end: usize,
    close: bool,
    content_range: Option<[u64; 3]>,
    /// The ETag value's place in the buffer.
    etag: Option<(usize, usize)>,
}

/// Splits a byte stream into responses. Reuses one buffer, which grows only as far as the
/// largest response (bounded by [`Limits`]).
#[derive(Debug)]
pub struct ResponseDecoder {
    limits: Limits,
    buf: Vec<u8>,
    /// Unconsumed bytes are `buf[start..end]`.
    start: usize,
    end: usize,
    /// Length of the response handed out last, dropped at the next decode.
    pending: usize,
}

/// Initial (and minimum free) buffer space, in bytes.
const READ_CHUNK: usize = 16 * 1024;

impl ResponseDecoder {
    /// An empty decoder; allocates on first use.
    pub fn new(limits: Limits) -> Self {
        ResponseDecoder {
            limits,
            buf: Vec::new(),
            start: 0,
            end: 0,
            pending: 0,
        }
    }

    /// Bytes received and not yet part of a decoded response.
    pub fn buffered(&self) -> usize {
        self.end - self.start - self.pending
    }

    /// Forgets all buffered bytes (after a reconnect).
    pub fn clear(&mut self) {
        self.start = 0;
        self.end = 0;
        self.pending = 0;
    }

    fn consume_pending(&mut self) {
        self.start += self.pending;
        self.pending = 0;
        if self.start == self.end {
            self.start = 0;
            self.end = 0;
        }
    }

    /// Free space to receive into; call [`ResponseDecoder::filled`] with the count written.
    /// Compacts or grows the buffer, up to the largest response [`Limits`] allow.
    pub fn spare(&mut self) -> Result<&mut [u8], Http1Error> {
        self.consume_pending();
        if self.buf.len() - self.end < READ_CHUNK / 4 && self.start > 0 {
            self.buf.copy_within(self.start..self.end, 0);
            self.end -= self.start;
            self.start = 0;
        }
        if self.buf.len() - self.end < READ_CHUNK / 4 {
            let cap = self.limits.max_head_bytes + self.limits.max_body_bytes + READ_CHUNK;
            if self.buf.len() >= cap {
                // Unreachable while decode() enforces the limits; an error, not a panic.
                return Err(Http1Error::HeadTooLarge(self.limits.max_head_bytes));
            }
            let grown = (self.buf.len() * 2).clamp(READ_CHUNK, cap);
            self.buf.resize(grown, 0);
        }
        Ok(&mut self.buf[self.end..])
    }

    /// Records that `n` bytes were written at the start of [`ResponseDecoder::spare`].
    pub fn filled(&mut self, n: usize) {
        self.end = (self.end + n).min(self.buf.len());
    }

    /// Appends bytes (for tests and callers that do not read into [`ResponseDecoder::spare`]).
    pub fn extend(&mut self, mut bytes: &[u8]) -> Result<(), Http1Error> {
        while !bytes.is_empty() {
            let spare = self.spare()?;
            let n = spare.len().min(bytes.len());
            spare[..n].copy_from_slice(&bytes[..n]);
            self.filled(n);
            bytes = &bytes[n..];
        }
        Ok(())
    }

    /// The next complete response, `None` if more bytes are needed.
    pub fn decode(&mut self) -> Result<Option<Response<'_>>, Http1Error> {
        Ok(self.decode_frame()?.map(|f| self.response(f)))
    }

    fn response(&self, f: Frame) -> Response<'_> {
        Response {
            status: f.status,
            body: &self.buf[f.body_start..f.end],
            close: f.close,
            content_range: f.content_range,
            etag: f.etag.map(|(a, b)| &self.buf[a..b]),
        }
    }

    fn decode_frame(&mut self) -> Result<Option<Frame>, Http1Error> {
        self.consume_pending();
        loop {
            match self.decode_head()? {
                Head::Partial => return Ok(None),
                Head::Frame(f) => return Ok(Some(f)),
                Head::Interim(len) => {
                    // An interim answer (100 Continue, 103 Early Hints): no body, and the
                    // final answer to the same request follows.
                    self.start += len;
                    if self.start == self.end {
                        self.start = 0;
                        self.end = 0;
                    }
                }
            }
        }
    }

    fn decode_head(&mut self) -> Result<Head, Http1Error> {
        let data = &self.buf[self.start..self.end];
        if data.is_empty() {
            return Ok(Head::Partial);
        }
        let mut headers = [httparse::EMPTY_HEADER; MAX_HEADERS];
        let mut resp = httparse::Response::new(&mut headers);
        let head_len = match resp.parse(data).map_err(Http1Error::Malformed)? {
            httparse::Status::Complete(n) => n,
            httparse::Status::Partial => {
                if data.len() > self.limits.max_head_bytes {
                    return Err(Http1Error::HeadTooLarge(self.limits.max_head_bytes));
                }
                return Ok(Head::Partial);
            }
        };
        if head_len > self.limits.max_head_bytes {
            return Err(Http1Error::HeadTooLarge(self.limits.max_head_bytes));
        }
        let status = resp
            .code
            .ok_or(Http1Error::Malformed(httparse::Error::Status))?;
        if status == 101 {
            return Err(Http1Error::Informational(status));
        }
        if (100..200).contains(&status) {
            return Ok(Head::Interim(head_len));
        }
        let mut length: Option<u64> = None;
        let mut close = false;
        let mut content_range = None;
        let mut etag = None;
        let base = data.as_ptr() as usize;
        for h in resp.headers.iter() {
            if h.name.eq_ignore_ascii_case("content-length") {
                let v = parse_length(h.value).ok_or(Http1Error::BadContentLength)?;
                if length.is_some_and(|old| old != v) {
                    return Err(Http1Error::BadContentLength);
                }
                length = Some(v);
            } else if h.name.eq_ignore_ascii_case("transfer-encoding") {
                return Err(Http1Error::TransferEncoding);
            } else if h.name.eq_ignore_ascii_case("content-range") {
                content_range =
                    Some(parse_content_range(h.value).ok_or(Http1Error::BadContentRange)?);
            } else if h.name.eq_ignore_ascii_case("etag") {
                let at = self.start + (h.value.as_ptr() as usize - base);
                etag = Some((at, at + h.value.len()));
            } else if h.name.eq_ignore_ascii_case("connection") {
                close = h
                    .value
                    .split(|&b| b == b',')
                    .any(|t| t.trim_ascii().eq_ignore_ascii_case(b"close"));
            }
        }
        let body_len = match (status, length) {
            (204 | 304, _) => 0,
            (_, Some(n)) => n,
            (_, None) => return Err(Http1Error::MissingContentLength),
        };
        if body_len > self.limits.max_body_bytes as u64 {
            return Err(Http1Error::BodyTooLarge(body_len));
        }
        let total = head_len + body_len as usize;
        if data.len() < total {
            return Ok(Head::Partial);
        }
        let frame = Frame {
            status,
            body_start: self.start + head_len,
            end: self.start + total,
            close,
            content_range,
            etag,
        };
        self.pending = total;
        Ok(Head::Frame(frame))
    }
}

/// What the bytes at the front of the buffer hold.
enum Head {
    /// Not a whole response yet.
    Partial,
    /// An interim (1xx) answer of this many bytes.
    Interim(usize),
    /// A whole final response.
    Frame(Frame),
}

/// `bytes <first>-<last>/<total>` (total `*`: `u64::MAX`), with `first <= last < total`,
/// or `bytes */<total>` (`[u64::MAX, 0, total]`).
pub(crate) fn parse_content_range(v: &[u8]) -> Option<[u64; 3]> {
    quincunx_client_core::fetch::range_answer::parse_content_range(v)
}

use quincunx_client_core::fetch::range_answer::parse_length;

/// One persistent HTTP/1.1 connection (`TCP_NODELAY`, TLS for `https://`), for
/// pipelined GETs.
#[derive(Debug)]
pub struct Connection {
    stream: Stream,
    decoder: ResponseDecoder,
    closing: bool,
}

impl Connection {
    /// Connects to `addr`.
    pub async fn connect(addr: SocketAddr, limits: Limits) -> Result<Connection, Http1Error> {
        let stream = TcpStream::connect(addr).await?;
        stream.set_nodelay(true)?;
        Ok(Connection {
            stream: Stream::Plain(stream),
            decoder: ResponseDecoder::new(limits),
            closing: false,
        })
    }

    /// Connects to `endpoint`: plain TCP, or TLS (ALPN `http/1.1`) for `https://`.
    pub async fn open(endpoint: &Endpoint, limits: Limits) -> Result<Connection, Http1Error> {
        Ok(Connection {
            stream: endpoint.connect().await?,
            decoder: ResponseDecoder::new(limits),
            closing: false,
        })
    }

    /// Writes a batch of already rendered requests (see [`write_get`]) in one write.
    pub async fn send(&mut self, requests: &[u8]) -> Result<(), Http1Error> {
        self.stream.write_all(requests).await?;
        self.stream.flush().await?;
        Ok(())
    }

    /// Reads the next response; the body is valid until the next call.
    pub async fn read_response(&mut self) -> Result<Response<'_>, Http1Error> {
        let frame = loop {
            if let Some(f) = self.decoder.decode_frame()? {
                break f;
            }
            let spare = self.decoder.spare()?;
            let n = self.stream.read(spare).await?;
            if n == 0 {
                return Err(Http1Error::Closed);
            }
            self.decoder.filled(n);
        };
        self.closing |= frame.close;
        Ok(self.decoder.response(frame))
    }

    /// Whether the server announced it closes the connection after a response read so far.
    pub fn closing(&self) -> bool {
        self.closing
    }

    /// Waits until the server closes the connection (or sends anything, or fails); for
    /// holding a connection idle and noticing when the server drops it.
    pub async fn wait_closed(&mut self) -> Result<(), Http1Error> {
        let mut byte = [0u8; 1];
        match self.stream.read(&mut byte).await? {
            0 => Ok(()),
            _ => Err(Http1Error::Malformed(httparse::Error::Status)),
        }
    }
}

/// Fetches one resource on a fresh connection, blocking (std sockets, usable inside or
/// outside an async runtime): status and body. `timeout` bounds the whole exchange
/// (connect, write and every read together): [`Http1Error::TimedOut`] when it passes.
pub fn get_blocking(
    endpoint: &Endpoint,
    path: &str,
    timeout: std::time::Duration,
) -> Result<(u16, Vec<u8>), Http1Error> {
    get_blocking_with(endpoint, path, b"", timeout).map(|a| (a.status, a.body))
}

/// A whole answer of [`get_blocking_with`].
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Answer {
    /// Status code.
    pub status: u16,
    /// The body.
    pub body: Vec<u8>,
    /// `Content-Range`, as [`Response::content_range`].
    pub content_range: Option<[u64; 3]>,
    /// The `ETag` header's value.
    pub etag: Option<String>,
}

/// [`get_blocking`] with more header lines (`extra`, each ending in CR LF), giving the
/// `Content-Range` and `ETag` headers too.
pub fn get_blocking_with(
    endpoint: &Endpoint,
    path: &str,
    extra: &[u8],
    timeout: std::time::Duration,
) -> Result<Answer, Http1Error> {
    use std::io::{ErrorKind, Read, Write};
    let deadline = std::time::Instant::now() + timeout;
    // A socket timeout surfaces as `WouldBlock` ("Resource temporarily unavailable") or
    // `TimedOut`: say what it is.
    let timed_out = |e: std::io::Error| match e.kind() {
        ErrorKind::WouldBlock | ErrorKind::TimedOut => Http1Error::TimedOut(timeout),
        _ => Http1Error::Io(e),
    };
    let remaining = || {
        deadline
            .checked_duration_since(std::time::Instant::now())
            .filter(|d| !d.is_zero())
            .ok_or(Http1Error::TimedOut(timeout))
    };
    let tcp = std::net::TcpStream::connect_timeout(&endpoint.addr, timeout).map_err(timed_out)?;
    let socket = tcp.try_clone()?;
    socket.set_write_timeout(Some(remaining()?))?;
    socket.set_read_timeout(Some(remaining()?))?;
    let mut stream: Box<dyn ReadWrite> = match &endpoint.tls {
        None => Box::new(tcp),
        Some(tls) => {
            let conn = rustls::ClientConnection::new(tls.http1_config(), tls.server_name.clone())
                .map_err(|e| Http1Error::Tls(super::tls::describe(&e, &tls.host())))?;
            Box::new(rustls::StreamOwned::new(conn, tcp))
        }
    };
    // A TLS failure is named; a socket timeout is a timeout.
    let failed = |e: std::io::Error| match io_error(e, endpoint) {
        Http1Error::Io(e) => timed_out(e),
        other => other,
    };
    let mut req = Vec::new();
    write_get_with(&mut req, &endpoint.host, path.as_bytes(), extra);
    stream.write_all(&req).map_err(failed)?;
    stream.flush().map_err(failed)?;
    let mut decoder = ResponseDecoder::new(Limits::default());
    loop {
        if let Some(resp) = decoder.decode()? {
            return Ok(Answer {
                status: resp.status,
                body: resp.body.to_vec(),
                content_range: resp.content_range,
                etag: resp.etag.map(|e| String::from_utf8_lossy(e).into_owned()),
            });
        }
        let spare = decoder.spare()?;
        // The whole exchange within `timeout`, however slowly the bytes trickle in.
        socket.set_read_timeout(Some(remaining()?))?;
        let n = stream.read(spare).map_err(failed)?;
        if n == 0 {
            return Err(Http1Error::Closed);
        }
        decoder.filled(n);
    }
}

/// A blocking byte stream: TCP or TLS over TCP.
trait ReadWrite: std::io::Read + std::io::Write {}

impl<T: std::io::Read + std::io::Write> ReadWrite for T {}

/// Fetches one resource on a fresh connection: status and body.
pub async fn get(endpoint: &Endpoint, path: &str) -> Result<(u16, Vec<u8>), Http1Error> {
    let mut conn = Connection::open(endpoint, Limits::default()).await?;
    let mut req = Vec::new();
    let full = format!("{}{path}", endpoint.prefix);
    write_get(&mut req, &endpoint.host, full.as_bytes());
    conn.send(&req).await?;
    let resp = conn.read_response().await?;
    Ok((resp.status, resp.body.to_vec()))
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use super::*;

    fn ok(body: &str) -> Vec<u8> {
        format!(
            "HTTP/1.1 200 OK\r\nContent-Type: application/octet-stream\r\nContent-Length: {}\r\n\r\n{body}",
            body.len()
        )
        .into_bytes()
    }

    /// Decodes everything in `chunks` fed one after another: (status, body) per response.
    fn decode_all(chunks: &[&[u8]], limits: Limits) -> Result<Vec<(u16, Vec<u8>)>, Http1Error> {
        let mut d = ResponseDecoder::new(limits);
        let mut out = Vec::new();
        for c in chunks {
            d.extend(c)?;
            while let Some(r) = d.decode()? {
                out.push((r.status, r.body.to_vec()));
            }
        }
        Ok(out)
    }

    /// `stream` split in two at every byte decodes to `want`.
    fn decodes_at_every_cut(stream: &[u8], want: &[(u16, Vec<u8>)]) {
        for cut in 0..=stream.len() {
            let (a, b) = stream.split_at(cut);
            assert_eq!(
                decode_all(&[a, b], Limits::default()).unwrap(),
                want,
                "{cut}"
            );
        }
    }

    #[test]
    fn a_response_split_at_every_byte_decodes_the_same() {
        let mut stream = ok("hello");
        stream.extend(b"HTTP/1.1 204 No Content\r\n\r\n");
        stream.extend(ok(""));
        stream.extend(ok("world!"));
        let want = vec![
            (200, b"hello".to_vec()),
            (204, Vec::new()),
            (200, Vec::new()),
            (200, b"world!".to_vec()),
        ];
        decodes_at_every_cut(&stream, &want);
        let bytes: Vec<&[u8]> = stream.chunks(1).collect();
        assert_eq!(decode_all(&bytes, Limits::default()).unwrap(), want);
    }

    #[test]
    fn many_responses_in_one_buffer_all_decode_in_order() {
        let mut stream = Vec::new();
        for i in 0..1000 {
            stream.extend(ok(&"x".repeat(i % 37)));
        }
        let got = decode_all(&[&stream], Limits::default()).unwrap();
        assert_eq!(got.len(), 1000);
        for (i, (status, body)) in got.iter().enumerate() {
            assert_eq!(*status, 200);
            assert_eq!(body.len(), i % 37);
        }
    }

    #[test]
    fn a_body_larger_than_the_read_chunk_is_reassembled() {
        let body = "abcdefgh".repeat(READ_CHUNK / 2);
        let stream = ok(&body);
        let chunks: Vec<&[u8]> = stream.chunks(1000).collect();
        let got = decode_all(&chunks, Limits::default()).unwrap();
        assert_eq!(got, vec![(200, body.into_bytes())]);
    }

    #[test]
    fn a_partial_response_is_not_an_error() {
        let stream = ok("abc");
        let got = decode_all(&[&stream[..stream.len() - 1]], Limits::default()).unwrap();
        assert!(got.is_empty());
    }

    #[test]
    fn missing_content_length_is_an_error() {
        let r = decode_all(
            &[b"HTTP/1.1 200 OK\r\nServer: x\r\n\r\nabc"],
            Limits::default(),
        );
        assert!(matches!(r, Err(Http1Error::MissingContentLength)), "{r:?}");
        // Except where no body is allowed.
        let r = decode_all(&[b"HTTP/1.1 304 Not Modified\r\n\r\n"], Limits::default());
        assert_eq!(r.unwrap(), vec![(304, Vec::new())]);
    }

    #[test]
    fn bad_and_conflicting_lengths_are_errors() {
        for head in [
            "Content-Length: -1",
            "Content-Length: 1x",
            "Content-Length: ",
            "Content-Length: 99999999999999999999999",
            "Content-Length: 3\r\nContent-Length: 4",
        ] {
            let msg = format!("HTTP/1.1 200 OK\r\n{head}\r\n\r\nabcd");
            let r = decode_all(&[msg.as_bytes()], Limits::default());
            assert!(
                matches!(r, Err(Http1Error::BadContentLength)),
                "{head}: {r:?}"
            );
        }
        let same = b"HTTP/1.1 200 OK\r\nContent-Length: 2\r\ncontent-length: 2\r\n\r\nab";
        assert_eq!(
            decode_all(&[same], Limits::default()).unwrap(),
            vec![(200, b"ab".to_vec())]
        );
    }

    #[test]
    fn chunked_and_informational_responses_are_errors() {
        let r = decode_all(
            &[b"HTTP/1.1 200 OK\r\nTransfer-Encoding: chunked\r\n\r\n3\r\nabc\r\n0\r\n\r\n"],
            Limits::default(),
        );
        assert!(matches!(r, Err(Http1Error::TransferEncoding)), "{r:?}");
        let r = decode_all(
            &[b"HTTP/1.1 101 Switching Protocols\r\n\r\n"],
            Limits::default(),
        );
        assert!(matches!(r, Err(Http1Error::Informational(101))), "{r:?}");
    }

    #[test]
    fn interim_answers_are_skipped_before_the_final_one() {
        let mut stream = b"HTTP/1.1 100 Continue\r\n\r\n".to_vec();
        stream.extend(b"HTTP/1.1 103 Early Hints\r\nLink: </a>; rel=preload\r\n\r\n");
        stream.extend(ok("hello"));
        stream.extend(b"HTTP/1.1 100 Continue\r\n\r\n");
        stream.extend(ok("world"));
        let want = vec![(200, b"hello".to_vec()), (200, b"world".to_vec())];
        decodes_at_every_cut(&stream, &want);
        // Only interim answers so far: nothing to hand out yet, and no error.
        let only = b"HTTP/1.1 100 Continue\r\n\r\n";
        assert!(decode_all(&[only], Limits::default()).unwrap().is_empty());
    }

    #[test]
    fn garbage_is_an_error_not_a_panic() {
        for junk in [
            &b"garbage\r\n\r\n"[..],
            b"HTTP/1.1 abc OK\r\n\r\n",
            b"HTTP/9.9 200 OK\r\n\r\n",
            b"\x00\x01\x02\x03\r\n\r\n",
            b"HTTP/1.1 200 OK\r\nbad header line\r\n\r\n",
        ] {
            let r = decode_all(&[junk], Limits::default());
            assert!(
                matches!(r, Err(Http1Error::Malformed(_))),
                "{junk:?}: {r:?}"
            );
        }
        // A deterministic byte soup never panics.
        let mut x = 0x9e37_79b9_7f4a_7c15u64;
        for _ in 0..2000 {
            let mut soup = b"HTTP/1.1 200 OK\r\nContent-Length: 5\r\n".to_vec();
            for _ in 0..40 {
                x ^= x << 13;
                x ^= x >> 7;
                x ^= x << 17;
                let alphabet = b"HTTP/1.0 2045\r\n: ContentLgh-ab";
                soup.push(alphabet[(x % alphabet.len() as u64) as usize]);
            }
            let _ = decode_all(&[&soup], Limits::default());
        }
    }

    #[test]
    fn oversized_heads_and_bodies_are_errors() {
        let limits = Limits {
            max_head_bytes: 256,
            max_body_bytes: 1000,
        };
        let long = format!("HTTP/1.1 200 OK\r\nX-Pad: {}\r\n", "p".repeat(300));
        // Incomplete head already past the limit.
        let r = decode_all(&[long.as_bytes()], limits);
        assert!(matches!(r, Err(Http1Error::HeadTooLarge(256))), "{r:?}");
        // Complete head past the limit.
        let whole = format!("{long}Content-Length: 0\r\n\r\n");
        let r = decode_all(&[whole.as_bytes()], limits);
        assert!(matches!(r, Err(Http1Error::HeadTooLarge(256))), "{r:?}");
        // A body beyond the limit is refused before it arrives (no allocation for it).
        let r = decode_all(
            &[b"HTTP/1.1 200 OK\r\nContent-Length: 1001\r\n\r\n"],
            limits,
        );
        assert!(matches!(r, Err(Http1Error::BodyTooLarge(1001))), "{r:?}");
        let r = decode_all(
            &[b"HTTP/1.1 200 OK\r\nContent-Length: 18446744073709551615\r\n\r\n"],
            Limits::default(),
        );
        assert!(matches!(r, Err(Http1Error::BodyTooLarge(_))), "{r:?}");
        // Too many headers.
        let mut many = String::from("HTTP/1.1 200 OK\r\n");
        for i in 0..=MAX_HEADERS {
            many.push_str(&format!("X-{i}: y\r\n"));
        }
        many.push_str("Content-Length: 0\r\n\r\n");
        let r = decode_all(&[many.as_bytes()], Limits::default());
        assert!(matches!(r, Err(Http1Error::Malformed(_))), "{r:?}");
    }

    #[test]
    fn connection_close_is_reported() {
        let mut d = ResponseDecoder::new(Limits::default());
        d.extend(b"HTTP/1.1 200 OK\r\nConnection: keep-alive, Close\r\nContent-Length: 0\r\n\r\n")
            .unwrap();
        assert!(d.decode().unwrap().unwrap().close);
        assert_eq!(d.buffered(), 0);
    }

    #[test]
    fn urls_parse_into_endpoints() {
        let e = Endpoint::from_url("http://127.0.0.1:8080").unwrap();
        assert_eq!(e.addr, "127.0.0.1:8080".parse().unwrap());
        assert_eq!((e.host.as_str(), e.prefix.as_str()), ("127.0.0.1:8080", ""));
        let e = Endpoint::from_url("http://127.0.0.1/tiles/").unwrap();
        assert_eq!(e.addr.port(), 80);
        assert_eq!(e.prefix, "/tiles");
        let e = Endpoint::from_url("http://[::1]:81/").unwrap();
        assert_eq!(e.addr, "[::1]:81".parse().unwrap());
        let e = Endpoint::from_url("https://127.0.0.1:8443/p").unwrap();
        assert_eq!(e.scheme(), "https");
        assert_eq!(e.url("/p/x"), "https://127.0.0.1:8443/p/x");
        let e = Endpoint::from_url("https://[::1]/").unwrap();
        assert_eq!(e.addr.port(), 443);
        for bad in [
            "ftp://x",
            "127.0.0.1:80",
            "http://",
            "http://a b/",
            "http://h/p?q",
        ] {
            assert!(Endpoint::from_url(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn requests_are_rendered_with_a_host_header() {
        let mut out = Vec::new();
        write_get(&mut out, "h:1", b"/a");
        write_get(&mut out, "h:1", b"/b");
        assert_eq!(
            out,
            b"GET /a HTTP/1.1\r\nHost: h:1\r\n\r\nGET /b HTTP/1.1\r\nHost: h:1\r\n\r\n"
        );
        let t = GetTemplate::new("h:1", "/");
        let mut again = Vec::new();
        t.push(&mut again, b"a");
        t.push(&mut again, b"b");
        assert_eq!(again, out);
    }
}
