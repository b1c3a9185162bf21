//! The bad-request suite: a table of malformed, hostile and borderline requests sent over
//! raw loopback sockets, each with the status and connection behaviour it must get, while
//! a well-behaved client on its own connection keeps making valid requests (every one of
//! which must succeed).
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use std::io::Write;
use std::net::SocketAddr;
use std::time::Duration;

use common::*;

/// What a request must get.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Expect {
    /// This status, and the connection stays usable: a following valid request on it is
    /// answered 200.
    Keep(u16),
    /// This status, then the server closes the connection.
    Close(u16),
    /// Closed without an answer.
    Dropped,
    /// HTTP/2: GOAWAY with this error code, then the connection closes.
    Goaway(u32),
    /// HTTP/2: stream 1 (or the given one) is reset with this code; the connection lives.
    Reset(u32, u32),
    /// HTTP/2: stream 1 is answered 200.
    H2Ok,
    /// HTTP/2: stream 1 is answered with this status.
    H2Status(u16),
    /// HTTP/2: closed without answering (a GOAWAY may come first).
    H2Closed,
}

use Expect::*;

// HTTP/2 error codes (RFC 9113 7).
const NO_ERROR: u32 = 0;
const PROTOCOL_ERROR: u32 = 1;
const FLOW_CONTROL_ERROR: u32 = 3;
const FRAME_SIZE_ERROR: u32 = 6;
const REFUSED_STREAM: u32 = 7;
const ENHANCE_YOUR_CALM: u32 = 11;

/// An HTTP/1.1 request for `path` with `extra` header lines (each ending in CRLF).
fn h1(method: &str, path: &str, extra: &str) -> Vec<u8> {
    format!("{method} {path} HTTP/1.1\r\nHost: t\r\n{extra}\r\n").into_bytes()
}

fn raw(s: &str) -> Vec<u8> {
    s.as_bytes().to_vec()
}

/// Preface and SETTINGS, then `frames`.
fn h2(frames: &[Vec<u8>]) -> Vec<u8> {
    let mut out = h2::PREFACE.to_vec();
    out.extend(h2::settings(&[]));
    for f in frames {
        out.extend_from_slice(f);
    }
    out
}

fn headers(stream: u32, flags: u8, block: &[u8]) -> Vec<u8> {
    h2::frame(h2::HEADERS, flags, stream, block)
}

fn get(stream: u32) -> Vec<u8> {
    headers(
        stream,
        h2::END_HEADERS | h2::END_STREAM,
        &h2::get_block("/healthz"),
    )
}

/// The table: (class, request bytes, expected outcome).
fn cases(blob: &str, sphere: &str) -> Vec<(&'static str, Vec<u8>, Expect)> {
    let pad = "a".repeat(20 << 10);
    let many: String = (0..200).map(|i| format!("X-{i}: v\r\n")).collect();
    let long_path = format!("/healthz?{}", "q".repeat(20 << 10));
    let smuggled = "GET /repos/nope HTTP/1.1\r\nHost: t\r\n\r\n";
    let mut big_settings = Vec::new();
    for i in 0..2000u16 {
        big_settings.push((0x100 + i, 1u32)); // unknown settings: to be ignored
    }
    let mut upper = vec![0x82, 0x86, 0x04, 8];
    upper.extend_from_slice(b"/healthz");
    upper.extend_from_slice(&[0x00, 4]);
    upper.extend_from_slice(b"Host");
    upper.extend_from_slice(&[1, b't']);
    let mut conn_header = h2::get_block("/healthz");
    conn_header.extend_from_slice(&[0x00, 10]);
    conn_header.extend_from_slice(b"connection");
    conn_header.extend_from_slice(&[5]);
    conn_header.extend_from_slice(b"close");
    let mut huge_block = h2::get_block("/healthz");
    for i in 0..40 {
        huge_block.extend_from_slice(&[0x00, 4]);
        huge_block.extend_from_slice(format!("x-{i:02}").as_bytes());
        huge_block.extend_from_slice(&[0x7f, 0x81, 0x03]); // length 127 + 385 = 512
        huge_block.extend_from_slice(&[b'v'; 512]);
    }
    let rapid_reset: Vec<Vec<u8>> = (0..200u32)
        .flat_map(|i| {
            let id = 2 * i + 1;
            [
                get(id),
                h2::frame(h2::RST_STREAM, 0, id, &8u32.to_be_bytes()),
            ]
        })
        .collect();
    let no_path = vec![0x82, 0x86, 0x01, 0x01, b't'];
    let stalled: Vec<Vec<u8>> = (0..5u32)
        .map(|i| {
            headers(
                2 * i + 1,
                h2::END_HEADERS | h2::END_STREAM,
                &h2::get_block(blob),
            )
        })
        .collect();
    let mut stalled_with_window_0 = vec![h2::settings(&[(4, 0)])];
    stalled_with_window_0.extend(stalled);
    vec![
        // Request lines.
        ("not a request line", raw("GARBAGE\r\n\r\n"), Close(400)),
        ("method only", raw("GET\r\n\r\n"), Close(400)),
        ("HTTP/0.9 request", raw("GET /healthz\r\n\r\n"), Close(400)),
        (
            "extra token in request line",
            raw("GET /healthz HTTP/1.1 x\r\nHost: t\r\n\r\n"),
            Close(400),
        ),
        (
            "two spaces after method",
            raw("GET  /healthz HTTP/1.1\r\nHost: t\r\n\r\n"),
            Close(400),
        ),
        (
            "leading space",
            raw(" GET /healthz HTTP/1.1\r\nHost: t\r\n\r\n"),
            Close(400),
        ),
        (
            "tabs as separators",
            raw("GET\t/healthz\tHTTP/1.1\r\nHost: t\r\n\r\n"),
            Close(400),
        ),
        (
            "space after version",
            raw("GET /healthz HTTP/1.1 \r\nHost: t\r\n\r\n"),
            Close(400),
        ),
        (
            "NUL in the target",
            raw("GET /heal\0thz HTTP/1.1\r\nHost: t\r\n\r\n"),
            Close(400),
        ),
        // hyper passes raw non-ASCII bytes through; no resource has such a name.
        (
            "non-ASCII in the target",
            b"GET /h\xc3\xa9 HTTP/1.1\r\nHost: t\r\n\r\n".to_vec(),
            Keep(404),
        ),
        (
            "target without a slash",
            raw("GET healthz HTTP/1.1\r\nHost: t\r\n\r\n"),
            Close(400),
        ),
        // hyper's URI parser drops the fragment before the server sees it.
        (
            "fragment in the target",
            raw("GET /healthz#x HTTP/1.1\r\nHost: t\r\n\r\n"),
            Keep(200),
        ),
        (
            "target past the head limit",
            h1("GET", &long_path, ""),
            Close(431),
        ),
        // Methods.
        ("lower-case method", h1("get", "/healthz", ""), Keep(405)),
        ("unknown method", h1("FOO", "/healthz", ""), Keep(405)),
        (
            "method with a non-token byte",
            h1("G@T", "/healthz", ""),
            Close(400),
        ),
        (
            "POST",
            h1("POST", "/healthz", "Content-Length: 0\r\n"),
            Keep(405),
        ),
        (
            "PUT on a blob",
            h1("PUT", blob, "Content-Length: 0\r\n"),
            Keep(405),
        ),
        ("DELETE on a blob", h1("DELETE", blob, ""), Keep(405)),
        ("TRACE", h1("TRACE", "/healthz", ""), Keep(405)),
        (
            "CONNECT (authority-form)",
            raw("CONNECT t:80 HTTP/1.1\r\nHost: t:80\r\n\r\n"),
            Keep(405),
        ),
        (
            "OPTIONS * (asterisk-form)",
            raw("OPTIONS * HTTP/1.1\r\nHost: t\r\n\r\n"),
            Keep(404),
        ),
        ("HEAD", h1("HEAD", "/healthz", ""), Keep(200)),
        // Targets.
        (
            "absolute-form target",
            raw("GET http://t/healthz HTTP/1.1\r\nHost: t\r\n\r\n"),
            Keep(200),
        ),
        (
            "absolute-form, other Host",
            raw("GET http://a/healthz HTTP/1.1\r\nHost: b\r\n\r\n"),
            Keep(200),
        ),
        ("query string", h1("GET", "/healthz?x=1", ""), Keep(200)),
        ("double slash", h1("GET", "//healthz", ""), Keep(404)),
        (
            "dot segments",
            h1("GET", "/demo/../../etc/passwd", ""),
            Keep(404),
        ),
        (
            "encoded dot segments",
            h1("GET", "/demo/%2e%2e/%2e%2e/etc/passwd", ""),
            Keep(404),
        ),
        (
            "traversal under /repos",
            h1("GET", "/repos/../healthz", ""),
            Keep(404),
        ),
        ("encoded NUL", h1("GET", "/demo/a%00b", ""), Keep(404)),
        (
            "bad percent-encoding in an id",
            h1("GET", &blob.replace("/32/32", "/%ZZ/32"), ""),
            Keep(400),
        ),
        (
            "percent-encoded id digits",
            h1("GET", &blob.replace("/32/32", "/%33%32/32"), ""),
            Keep(400),
        ),
        (
            "id at a domain corner",
            h1("GET", &blob.replace("/32/32", "/0/0"), ""),
            Keep(400),
        ),
        (
            "id outside the domain",
            h1("GET", &blob.replace("/32/32", "/99999/3"), ""),
            Keep(400),
        ),
        (
            "id past i64",
            h1("GET", &blob.replace("/32/32", "/9223372036854775808/0"), ""),
            Keep(400),
        ),
        (
            "two coordinates on a sphere",
            h1("GET", sphere, ""),
            Keep(400),
        ),
        (
            "leading zero in an id",
            h1("GET", &blob.replace("/32/32", "/032/32"), ""),
            Keep(400),
        ),
        // Versions.
        (
            "HTTP/1.2",
            raw("GET /healthz HTTP/1.2\r\nHost: t\r\n\r\n"),
            Close(400),
        ),
        (
            "HTTP/2.0 in an HTTP/1 request line",
            raw("GET /healthz HTTP/2.0\r\nHost: t\r\n\r\n"),
            Close(400),
        ),
        (
            "lower-case version",
            raw("GET /healthz http/1.1\r\nHost: t\r\n\r\n"),
            Close(400),
        ),
        (
            "HTTP/1.0 without Host",
            raw("GET /healthz HTTP/1.0\r\n\r\n"),
            Close(200),
        ),
        // Host.
        (
            "HTTP/1.1 without Host",
            raw("GET /healthz HTTP/1.1\r\n\r\n"),
            Close(400),
        ),
        (
            "two Host headers",
            h1("GET", "/healthz", "Host: u\r\n"),
            Close(400),
        ),
        (
            "two Host headers on HTTP/1.0",
            raw("GET /healthz HTTP/1.0\r\nHost: a\r\nHost: b\r\n\r\n"),
            Close(400),
        ),
        (
            "Host with a space",
            raw("GET /healthz HTTP/1.1\r\nHost: a b\r\n\r\n"),
            Close(400),
        ),
        (
            "Host with a path",
            raw("GET /healthz HTTP/1.1\r\nHost: t/x\r\n\r\n"),
            Close(400),
        ),
        (
            "Host with userinfo",
            raw("GET /healthz HTTP/1.1\r\nHost: u@t\r\n\r\n"),
            Close(400),
        ),
        (
            "Host with a bad port",
            raw("GET /healthz HTTP/1.1\r\nHost: t:x\r\n\r\n"),
            Close(400),
        ),
        (
            "Host with an open IPv6 bracket",
            raw("GET /healthz HTTP/1.1\r\nHost: [::1\r\n\r\n"),
            Close(400),
        ),
        (
            "Host as an IPv6 literal and port",
            raw("GET /healthz HTTP/1.1\r\nHost: [::1]:80\r\n\r\n"),
            Keep(200),
        ),
        (
            "empty Host",
            raw("GET /healthz HTTP/1.1\r\nHost:\r\n\r\n"),
            Keep(200),
        ),
        // Header syntax.
        (
            "obsolete line folding",
            h1("GET", "/healthz", "X-A: b\r\n c\r\n"),
            Close(400),
        ),
        (
            "header line without a colon",
            h1("GET", "/healthz", "Bad Header\r\n"),
            Close(400),
        ),
        (
            "space before the colon",
            h1("GET", "/healthz", "X-A : b\r\n"),
            Close(400),
        ),
        (
            "empty header name",
            h1("GET", "/healthz", ": b\r\n"),
            Close(400),
        ),
        (
            "non-token header name",
            h1("GET", "/healthz", "X(A): b\r\n"),
            Close(400),
        ),
        (
            "NUL in a header value",
            h1("GET", "/healthz", "X-A: b\0c\r\n"),
            Close(400),
        ),
        (
            "control byte in a header value",
            h1("GET", "/healthz", "X-A: b\x01c\r\n"),
            Close(400),
        ),
        (
            "bare CR in a header value",
            h1("GET", "/healthz", "X-A: b\rc\r\n"),
            Close(400),
        ),
        (
            "bare LF line ends",
            raw("GET /healthz HTTP/1.1\nHost: t\n\n"),
            Keep(200),
        ),
        (
            "head past max_header_bytes",
            h1("GET", "/healthz", &format!("X-Pad: {pad}\r\n")),
            Close(431),
        ),
        (
            "more than max_headers",
            h1("GET", "/healthz", &many),
            Close(431),
        ),
        (
            "two empty lines first",
            [&b"\r\n\r\n"[..], &h1("GET", "/healthz", "")].concat(),
            Keep(200),
        ),
        (
            "more empty lines than tolerated",
            raw(&"\r\n".repeat(8)),
            Dropped,
        ),
        // Bodies and framing.
        (
            "negative Content-Length",
            h1("GET", "/healthz", "Content-Length: -1\r\n"),
            Close(400),
        ),
        (
            "non-numeric Content-Length",
            h1("GET", "/healthz", "Content-Length: abc\r\n"),
            Close(400),
        ),
        (
            "Content-Length with a plus",
            h1("GET", "/healthz", "Content-Length: +3\r\n"),
            Close(400),
        ),
        (
            "Content-Length past u64",
            h1(
                "GET",
                "/healthz",
                "Content-Length: 99999999999999999999\r\n",
            ),
            Close(400),
        ),
        (
            "two different Content-Lengths",
            h1(
                "GET",
                "/healthz",
                "Content-Length: 3\r\nContent-Length: 4\r\n",
            ),
            Close(400),
        ),
        (
            "Content-Length list that disagrees",
            h1("GET", "/healthz", "Content-Length: 3, 4\r\n"),
            Close(400),
        ),
        (
            "GET with a body that looks like a request",
            [
                h1(
                    "GET",
                    "/healthz",
                    &format!("Content-Length: {}\r\n", smuggled.len()),
                ),
                raw(smuggled),
            ]
            .concat(),
            Keep(200),
        ),
        (
            "GET with a chunked body",
            [
                h1("GET", "/healthz", "Transfer-Encoding: chunked\r\n"),
                raw("5\r\nhello\r\n0\r\n\r\n"),
            ]
            .concat(),
            Keep(200),
        ),
        // hyper drops the Content-Length and closes after answering (RFC 9112 6.3).
        (
            "Transfer-Encoding and Content-Length",
            [
                h1(
                    "GET",
                    "/healthz",
                    "Transfer-Encoding: chunked\r\nContent-Length: 3\r\n",
                ),
                raw("0\r\n\r\n"),
            ]
            .concat(),
            Close(200),
        ),
        (
            "chunked not last",
            h1("GET", "/healthz", "Transfer-Encoding: chunked, gzip\r\n"),
            Close(400),
        ),
        // Not 501: with chunked not last, the body's end is unknowable (RFC 9112 6.3).
        (
            "unknown transfer coding",
            h1("GET", "/healthz", "Transfer-Encoding: xchunked\r\n"),
            Close(400),
        ),
        (
            "chunked then another Transfer-Encoding line",
            h1(
                "GET",
                "/healthz",
                "Transfer-Encoding: chunked\r\nTransfer-Encoding: identity\r\n",
            ),
            Close(400),
        ),
        (
            "Transfer-Encoding with a space before the colon",
            h1("GET", "/healthz", "Transfer-Encoding : chunked\r\n"),
            Close(400),
        ),
        (
            "Transfer-Encoding on HTTP/1.0",
            raw("GET /healthz HTTP/1.0\r\nTransfer-Encoding: chunked\r\n\r\n0\r\n\r\n"),
            Close(400),
        ),
        (
            "malformed chunk size",
            [
                h1("GET", "/healthz", "Transfer-Encoding: chunked\r\n"),
                raw("zz\r\nhello\r\n0\r\n\r\n"),
            ]
            .concat(),
            Close(200),
        ),
        (
            "body shorter than its Content-Length",
            [
                h1("GET", "/healthz", "Content-Length: 100\r\n"),
                raw("short"),
            ]
            .concat(),
            Close(200),
        ),
        (
            "Expect: 100-continue on GET",
            h1("GET", "/healthz", "Expect: 100-continue\r\n"),
            Keep(200),
        ),
        (
            "Upgrade: h2c",
            h1(
                "GET",
                "/healthz",
                "Connection: Upgrade, HTTP2-Settings\r\nUpgrade: h2c\r\nHTTP2-Settings: AAMAAABkAAQAAP__\r\n",
            ),
            Keep(200),
        ),
        // HTTP/2 frame abuse.
        (
            "HTTP/2: bad preface",
            raw("PRI * HTTP/2.0\r\n\r\nXX\r\n\r\n"),
            H2Closed,
        ),
        // h2 tolerates it; with no request, the connection meets the head timer.
        (
            "HTTP/2: first frame not SETTINGS",
            [h2::PREFACE.to_vec(), h2::frame(h2::PING, 0, 0, &[0; 8])].concat(),
            Goaway(NO_ERROR),
        ),
        (
            "HTTP/2: SETTINGS past the frame size",
            h2(&[h2::frame(h2::SETTINGS, 0, 0, &vec![0; 20_000])]),
            Goaway(FRAME_SIZE_ERROR),
        ),
        (
            "HTTP/2: SETTINGS of a bad length",
            h2(&[h2::frame(h2::SETTINGS, 0, 0, &[0; 7])]),
            Goaway(PROTOCOL_ERROR),
        ),
        (
            "HTTP/2: 2,000 unknown settings",
            h2(&[h2::settings(&big_settings), get(1)]),
            H2Ok,
        ),
        (
            "HTTP/2: window size past 2^31-1",
            h2(&[h2::settings(&[(4, 1 << 31)])]),
            Goaway(PROTOCOL_ERROR),
        ),
        (
            "HTTP/2: ENABLE_PUSH = 2",
            h2(&[h2::settings(&[(2, 2)])]),
            Goaway(PROTOCOL_ERROR),
        ),
        (
            "HTTP/2: unknown frame type",
            h2(&[h2::frame(0xfa, 0, 0, b"whatever"), get(1)]),
            H2Ok,
        ),
        (
            "HTTP/2: HEADERS on stream 0",
            h2(&[get(0)]),
            Goaway(PROTOCOL_ERROR),
        ),
        (
            "HTTP/2: HEADERS on an even stream",
            h2(&[get(2)]),
            Goaway(PROTOCOL_ERROR),
        ),
        (
            "HTTP/2: DATA on an idle stream",
            h2(&[h2::frame(h2::DATA, 0, 1, b"x")]),
            Goaway(PROTOCOL_ERROR),
        ),
        (
            "HTTP/2: stream ids going down",
            h2(&[get(3), get(1)]),
            Goaway(PROTOCOL_ERROR),
        ),
        (
            "HTTP/2: connection window overflow",
            h2(&[h2::frame(
                h2::WINDOW_UPDATE,
                0,
                0,
                &0x7fff_ffffu32.to_be_bytes(),
            )]),
            Goaway(FLOW_CONTROL_ERROR),
        ),
        (
            "HTTP/2: WINDOW_UPDATE of 0",
            h2(&[h2::frame(h2::WINDOW_UPDATE, 0, 0, &0u32.to_be_bytes())]),
            Goaway(PROTOCOL_ERROR),
        ),
        (
            "HTTP/2: CONTINUATION without HEADERS",
            h2(&[h2::frame(h2::CONTINUATION, h2::END_HEADERS, 1, &[0x82])]),
            Goaway(PROTOCOL_ERROR),
        ),
        (
            "HTTP/2: PING of a bad length",
            h2(&[h2::frame(h2::PING, 0, 0, &[0; 7])]),
            Goaway(PROTOCOL_ERROR),
        ),
        (
            "HTTP/2: RST_STREAM on an idle stream",
            h2(&[h2::frame(h2::RST_STREAM, 0, 1, &8u32.to_be_bytes())]),
            Goaway(PROTOCOL_ERROR),
        ),
        (
            "HTTP/2: invalid HPACK index",
            h2(&[headers(
                1,
                h2::END_HEADERS | h2::END_STREAM,
                &[0x82, 0xff, 0x7f],
            )]),
            Goaway(PROTOCOL_ERROR),
        ),
        (
            "HTTP/2: request without :path",
            h2(&[headers(1, h2::END_HEADERS | h2::END_STREAM, &no_path)]),
            Reset(1, PROTOCOL_ERROR),
        ),
        (
            "HTTP/2: upper-case header name",
            h2(&[headers(1, h2::END_HEADERS | h2::END_STREAM, &upper)]),
            Goaway(PROTOCOL_ERROR),
        ),
        (
            "HTTP/2: connection-specific header",
            h2(&[headers(1, h2::END_HEADERS | h2::END_STREAM, &conn_header)]),
            Reset(1, PROTOCOL_ERROR),
        ),
        (
            "HTTP/2: HEADERS past the frame size",
            h2(&[headers(1, h2::END_HEADERS | h2::END_STREAM, &huge_block)]),
            Goaway(FRAME_SIZE_ERROR),
        ),
        (
            "HTTP/2: header list past the limit",
            h2(&[
                headers(1, h2::END_STREAM, &huge_block[..10_000]),
                h2::frame(h2::CONTINUATION, h2::END_HEADERS, 1, &huge_block[10_000..]),
            ]),
            H2Status(431),
        ),
        (
            "HTTP/2: rapid reset flood",
            h2(&rapid_reset),
            Goaway(ENHANCE_YOUR_CALM),
        ),
        (
            "HTTP/2: streams past max_concurrent_streams",
            h2(&stalled_with_window_0),
            Reset(9, REFUSED_STREAM),
        ),
    ]
}

/// Sends one case on a fresh connection and checks what comes back; `Err` says how it
/// differed.
fn run(addr: SocketAddr, bytes: &[u8], expect: Expect) -> Result<(), String> {
    let mut s = connect(addr);
    // The server may close before taking everything (a 431 mid-head): not an error.
    let _ = s.write_all(bytes);
    match expect {
        Keep(status) | Close(status) => {
            let head_only = bytes.starts_with(b"HEAD ");
            let (got, rest) = read_one_response(&mut s, head_only)?;
            if got != status {
                return Err(format!("status {got}"));
            }
            if let Keep(_) = expect {
                s.write_all(b"GET /healthz HTTP/1.1\r\nHost: t\r\n\r\n")
                    .map_err(|e| format!("follow-up: {e}"))?;
                let (next, _) = read_one_response_after(&mut s, rest)?;
                if next != 200 {
                    return Err(format!("follow-up answered {next}"));
                }
            } else if !rest.is_empty() {
                return Err(format!("{} bytes after the answer", rest.len()));
            } else if !closed_within(&mut s, Duration::from_secs(10)) {
                return Err("connection left open".into());
            }
            Ok(())
        }
        Dropped => {
            let (bytes, closed) = read_to_close(&mut s);
            match (bytes.is_empty(), closed) {
                (true, true) => Ok(()),
                _ => Err(format!("got {} bytes, closed: {closed}", bytes.len())),
            }
        }
        Goaway(code) => {
            let seen = h2::read_frames(&mut s, Duration::from_secs(10), |_| false);
            if seen.goaway != Some(code) || !seen.closed {
                return Err(format!("{seen:?}"));
            }
            Ok(())
        }
        Reset(stream, code) => {
            let seen = h2::read_frames(&mut s, Duration::from_secs(10), |seen| {
                seen.resets.iter().any(|r| r.0 == stream) || seen.goaway.is_some()
            });
            if !seen.resets.contains(&(stream, code)) || seen.goaway.is_some() {
                return Err(format!("{seen:?}"));
            }
            Ok(())
        }
        H2Closed => {
            let seen = h2::read_frames(&mut s, Duration::from_secs(10), |_| false);
            if !seen.closed || !seen.statuses.is_empty() {
                return Err(format!("{seen:?}"));
            }
            Ok(())
        }
        H2Ok | H2Status(_) => {
            let status = if let H2Status(s) = expect { s } else { 200 };
            let seen = h2::read_frames(&mut s, Duration::from_secs(10), |seen| {
                !seen.statuses.is_empty() || seen.goaway.is_some()
            });
            if seen.statuses.first() != Some(&(1, status)) {
                return Err(format!("{seen:?}"));
            }
            Ok(())
        }
    }
}

/// Reads one response's status; returns it with any bytes read past it.
fn read_one_response(s: &mut std::net::TcpStream, head: bool) -> Result<(u16, Vec<u8>), String> {
    read_response_from(s, Vec::new(), head)
}

fn read_one_response_after(
    s: &mut std::net::TcpStream,
    buf: Vec<u8>,
) -> Result<(u16, Vec<u8>), String> {
    read_response_from(s, buf, false)
}

fn read_response_from(
    s: &mut std::net::TcpStream,
    mut buf: Vec<u8>,
    head: bool,
) -> Result<(u16, Vec<u8>), String> {
    use std::io::Read;
    let mut chunk = [0u8; 8192];
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    loop {
        if let Some((r, used)) = parse_response(&buf, head)? {
            return Ok((r.status, buf[used..].to_vec()));
        }
        match s.read(&mut chunk) {
            Ok(0) => {
                return Err(format!(
                    "closed without an answer after {} bytes",
                    buf.len()
                ));
            }
            Ok(n) => buf.extend_from_slice(&chunk[..n]),
            Err(e) => return Err(format!("no answer ({e}) after {} bytes", buf.len())),
        }
    }
}

#[test]
fn every_bad_request_class_gets_its_answer_while_others_are_served() {
    let server = Running::start(|c| {
        c.limits.header_timeout_s = 2.0;
        c.limits.write_timeout_s = 2.0;
        c.limits.max_concurrent_streams = 4;
    });
    let blob = format!("{}/32/32", planar_prefix(&server.state));
    let sphere = format!("{}/8/0", sphere_prefix(&server.state));
    let good = WellBehaved::start(server.addr, blob.clone());
    let table = cases(&blob, &sphere);
    assert!(table.len() >= 50, "{} classes", table.len());
    let mut failures = Vec::new();
    for (class, bytes, expect) in &table {
        if let Err(how) = run(server.addr, bytes, *expect) {
            failures.push(format!("{class}: expected {expect:?}, {how}"));
        }
    }
    let served = good.stop();
    assert!(
        failures.is_empty(),
        "{} of {} classes failed:\n{}",
        failures.len(),
        table.len(),
        failures.join("\n")
    );
    eprintln!(
        "{} classes; the well-behaved client made {served} requests meanwhile",
        table.len()
    );
}
