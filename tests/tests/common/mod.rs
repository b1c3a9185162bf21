//! Shared helpers of the end-to-end tests: workspace paths and a minimal HTTP/1.1 client
//! over `std::net::TcpStream` (one request per connection, `Connection: close`).
#![allow(dead_code, clippy::unwrap_used, clippy::expect_used)]

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::path::{Path, PathBuf};
use std::time::Duration;

pub mod nginx;
pub mod pack_reads;
pub mod stream;

/// The workspace root (the parent of this package).
pub fn workspace_root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("the e2e package lives in the workspace")
        .to_path_buf()
}

pub use quincunx_testkit::http::Response;

/// `GET path` with extra header lines (each `Name: value`), on a new connection.
pub fn try_get(addr: SocketAddr, path: &str, extra: &[&str]) -> std::io::Result<Response> {
    let mut stream = TcpStream::connect_timeout(&addr, Duration::from_secs(10))?;
    stream.set_read_timeout(Some(Duration::from_secs(30)))?;
    stream.set_write_timeout(Some(Duration::from_secs(30)))?;
    let mut request = format!("GET {path} HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\n");
    for line in extra {
        request.push_str(line);
        request.push_str("\r\n");
    }
    request.push_str("\r\n");
    stream.write_all(request.as_bytes())?;
    let mut raw = Vec::new();
    stream.read_to_end(&mut raw)?;
    parse(&raw).map_err(|e| std::io::Error::new(std::io::ErrorKind::InvalidData, e))
}

/// [`try_get`] that panics on failure.
pub fn get(addr: SocketAddr, path: &str, extra: &[&str]) -> Response {
    try_get(addr, path, extra).unwrap_or_else(|e| panic!("GET http://{addr}{path}: {e}"))
}

/// Parses a whole response read until the peer closed.
fn parse(raw: &[u8]) -> Result<Response, String> {
    let mut headers = [httparse::EMPTY_HEADER; 64];
    let mut r = httparse::Response::new(&mut headers);
    let head = match r.parse(raw).map_err(|e| e.to_string())? {
        httparse::Status::Complete(n) => n,
        httparse::Status::Partial => return Err(format!("incomplete head ({} bytes)", raw.len())),
    };
    let status = r.code.ok_or("no status")?;
    let headers: Vec<(String, String)> = r
        .headers
        .iter()
        .map(|h| {
            (
                h.name.to_string(),
                String::from_utf8_lossy(h.value).into_owned(),
            )
        })
        .collect();
    let rest = &raw[head..];
    let find = |name: &str| {
        headers
            .iter()
            .find(|(n, _)| n.eq_ignore_ascii_case(name))
            .map(|(_, v)| v.clone())
    };
    let body = if status == 304 || status == 204 {
        Vec::new()
    } else if find("transfer-encoding").is_some_and(|v| v.eq_ignore_ascii_case("chunked")) {
        dechunk(rest)?
    } else if let Some(len) = find("content-length") {
        let len: usize = len.parse().map_err(|e| format!("content-length: {e}"))?;
        if rest.len() != len {
            return Err(format!("content-length {len}, got {} bytes", rest.len()));
        }
        rest.to_vec()
    } else {
        rest.to_vec()
    };
    Ok(Response {
        status,
        headers,
        body,
    })
}

/// Decodes a chunked body (no trailers expected).
fn dechunk(mut rest: &[u8]) -> Result<Vec<u8>, String> {
    let mut body = Vec::new();
    loop {
        let line_end = rest
            .windows(2)
            .position(|w| w == b"\r\n")
            .ok_or("unterminated chunk size")?;
        let size_text = std::str::from_utf8(&rest[..line_end]).map_err(|e| e.to_string())?;
        let size_text = size_text.split(';').next().unwrap_or_default().trim();
        let size = usize::from_str_radix(size_text, 16).map_err(|e| e.to_string())?;
        rest = &rest[line_end + 2..];
        if size == 0 {
            return Ok(body);
        }
        if rest.len() < size + 2 {
            return Err("truncated chunk".into());
        }
        body.extend_from_slice(&rest[..size]);
        rest = &rest[size + 2..];
    }
}

/// The value of the Prometheus sample `line_prefix` (`name{labels}`) in `/metrics` text,
/// 0 when absent (the server omits zero request counters).
pub fn metric(metrics_text: &str, line_prefix: &str) -> u64 {
    metrics_text
        .lines()
        .find_map(|line| {
            let value = line.strip_prefix(line_prefix)?.strip_prefix(' ')?;
            value.trim().parse().ok()
        })
        .unwrap_or(0)
}

/// Builds the bundled 1025 x 1025 SRTM crop at 2 m RMS into `output` (what the end-to-end
/// tests serve).
pub fn build_bundled_korea(output: &Path) {
    use quincunx_repo_tools::build::{self, BuildArgs};
    build::run(&BuildArgs {
        rms_m: Some(2.0),
        overwrite: true,
        ..BuildArgs::new(workspace_root().join("data/korea_srtm3_1025.json"), output)
    })
    .unwrap();
}

/// Copies the repository file of `repo` to `www/name`, creating `www`: a file for a static
/// host to serve.
pub fn put_file(repo: &Path, www: &Path, name: &str) {
    std::fs::create_dir_all(www).unwrap();
    std::fs::copy(repo.join("repository.pack"), www.join(name)).unwrap();
}
