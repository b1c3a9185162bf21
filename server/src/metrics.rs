//! Prometheus metrics: lock-free counters updated on every request and connection,
//! rendered in the text exposition format by `GET /metrics`.

use std::fmt::Write as _;
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::time::Duration;

/// What a request asked for (a metric label).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Route {
    /// A blob by diamond centre.
    Blob,
    /// A repository's metadata.
    Metadata,
    /// The repository list.
    List,
    /// `/healthz`.
    Health,
    /// `/metrics`.
    Metrics,
    /// Web demo files.
    Static,
    /// Anything else (404s, CORS preflights).
    Other,
}

const ROUTES: [(Route, &str); 7] = [
    (Route::Blob, "blob"),
    (Route::Metadata, "metadata"),
    (Route::List, "list"),
    (Route::Health, "health"),
    (Route::Metrics, "metrics"),
    (Route::Static, "static"),
    (Route::Other, "other"),
];

/// Status codes counted separately; anything else is counted as `other`.
const STATUSES: [u16; 9] = [200, 204, 304, 400, 404, 405, 413, 500, 503];

/// Upper bounds (seconds) of the handler latency histogram.
const BUCKETS_S: [f64; 12] = [
    25e-6, 50e-6, 100e-6, 250e-6, 500e-6, 1e-3, 2.5e-3, 5e-3, 10e-3, 25e-3, 100e-3, 1.0,
];

/// The server's counters.
#[derive(Default)]
pub struct Metrics {
    requests: [[AtomicU64; STATUSES.len() + 1]; ROUTES.len()],
    body_bytes: [AtomicU64; ROUTES.len()],
    latency_buckets: [AtomicU64; BUCKETS_S.len() + 1],
    latency_sum_ns: AtomicU64,
    /// Blob lookups answered from the hot cache.
    pub cache_hits: AtomicU64,
    /// Blob lookups that went to the repository file.
    pub cache_misses: AtomicU64,
    /// Connections accepted and served.
    pub connections_accepted: AtomicU64,
    /// Connections refused because `max_connections` were open.
    pub connections_rejected: AtomicU64,
    /// Connections closed because nothing moved for `idle_timeout_s`.
    pub connections_idle_closed: AtomicU64,
    /// Connections closed because no complete request arrived within `header_timeout_s`.
    pub connections_header_timeout: AtomicU64,
    /// Connections refused because their client had `max_connections_per_ip` open.
    pub connections_rejected_per_ip: AtomicU64,
    /// Connections closed because a response made no progress for `write_timeout_s`.
    pub connections_write_timeout: AtomicU64,
    /// Connections closed to make room for a new one on a full server.
    pub connections_evicted: AtomicU64,
    /// Connections closed for sending more empty lines than tolerated before a request.
    pub connections_empty_lines: AtomicU64,
    /// Requests answered 500 because the repository could not be read.
    pub repository_read_errors: AtomicU64,
    /// Connections open now.
    pub connections_open: AtomicU64,
    /// HTTP/2 connections accepted.
    pub connections_h2: AtomicU64,
    /// Write system calls on client sockets (with pipelining, fewer than responses).
    pub socket_writes: AtomicU64,
    /// Bytes written to client sockets.
    pub socket_bytes_written: AtomicU64,
    /// Read system calls on client sockets that returned data.
    pub socket_reads: AtomicU64,
}

fn route_index(route: Route) -> usize {
    ROUTES
        .iter()
        .position(|(r, _)| *r == route)
        .unwrap_or(ROUTES.len() - 1)
}

impl Metrics {
    /// Records one answered request.
    pub fn observe(&self, route: Route, status: u16, body_bytes: u64, took: Duration) {
        let r = route_index(route);
        let s = STATUSES
            .iter()
            .position(|&c| c == status)
            .unwrap_or(STATUSES.len());
        self.requests[r][s].fetch_add(1, Relaxed);
        self.body_bytes[r].fetch_add(body_bytes, Relaxed);
        let secs = took.as_secs_f64();
        let b = BUCKETS_S
            .iter()
            .position(|&ub| secs <= ub)
            .unwrap_or(BUCKETS_S.len());
        self.latency_buckets[b].fetch_add(1, Relaxed);
        self.latency_sum_ns
            .fetch_add(took.as_nanos().min(u64::MAX as u128) as u64, Relaxed);
    }

    /// Requests answered so far (all routes and statuses).
    pub fn requests_total(&self) -> u64 {
        self.requests
            .iter()
            .flatten()
            .map(|c| c.load(Relaxed))
            .sum()
    }

    /// Requests answered with a status of 500 or more.
    pub fn server_errors_total(&self) -> u64 {
        let fivexx: Vec<usize> = STATUSES
            .iter()
            .enumerate()
            .filter(|(_, c)| **c >= 500)
            .map(|(i, _)| i)
            .collect();
        self.requests
            .iter()
            .map(|row| fivexx.iter().map(|&i| row[i].load(Relaxed)).sum::<u64>())
            .sum()
    }

    /// The Prometheus text exposition of every counter.
    pub fn render(&self, cache_bytes: u64, cache_entries: usize) -> String {
        let mut out = String::with_capacity(4096);
        out.push_str(
            "# HELP quincunx_http_requests_total Requests answered, by route and status.\n",
        );
        out.push_str("# TYPE quincunx_http_requests_total counter\n");
        for (r, (_, route)) in ROUTES.iter().enumerate() {
            for (s, counter) in self.requests[r].iter().enumerate() {
                let n = counter.load(Relaxed);
                if n == 0 {
                    continue;
                }
                let status = STATUSES
                    .get(s)
                    .map_or_else(|| "other".to_string(), |c| c.to_string());
                let _ = writeln!(
                    out,
                    "quincunx_http_requests_total{{route=\"{route}\",status=\"{status}\"}} {n}"
                );
            }
        }
        out.push_str("# HELP quincunx_http_response_body_bytes_total Body bytes sent, by route.\n");
        out.push_str("# TYPE quincunx_http_response_body_bytes_total counter\n");
        for (r, (_, route)) in ROUTES.iter().enumerate() {
            let _ = writeln!(
                out,
                "quincunx_http_response_body_bytes_total{{route=\"{route}\"}} {}",
                self.body_bytes[r].load(Relaxed)
            );
        }
        out.push_str(
            "# HELP quincunx_http_handler_seconds Time from routing a request to its response head.\n",
        );
        out.push_str("# TYPE quincunx_http_handler_seconds histogram\n");
        let mut cumulative = 0;
        for (i, count) in self.latency_buckets.iter().enumerate() {
            cumulative += count.load(Relaxed);
            let le = BUCKETS_S
                .get(i)
                .map_or_else(|| "+Inf".to_string(), |ub| format!("{ub}"));
            let _ = writeln!(
                out,
                "quincunx_http_handler_seconds_bucket{{le=\"{le}\"}} {cumulative}"
            );
        }
        let _ = writeln!(
            out,
            "quincunx_http_handler_seconds_sum {}\nquincunx_http_handler_seconds_count {cumulative}",
            self.latency_sum_ns.load(Relaxed) as f64 * 1e-9
        );
        let counters = [
            (
                "quincunx_cache_hits_total",
                "Blob lookups answered from the hot cache.",
                &self.cache_hits,
            ),
            (
                "quincunx_cache_misses_total",
                "Blob lookups that read the repository.",
                &self.cache_misses,
            ),
            (
                "quincunx_connections_accepted_total",
                "Connections accepted.",
                &self.connections_accepted,
            ),
            (
                "quincunx_connections_rejected_total",
                "Connections refused at max_connections (503).",
                &self.connections_rejected,
            ),
            (
                "quincunx_connections_idle_closed_total",
                "Connections closed after idle_timeout_s.",
                &self.connections_idle_closed,
            ),
            (
                "quincunx_connections_header_timeout_total",
                "Connections closed for sending no complete request in header_timeout_s.",
                &self.connections_header_timeout,
            ),
            (
                "quincunx_connections_rejected_per_ip_total",
                "Connections refused at max_connections_per_ip (429).",
                &self.connections_rejected_per_ip,
            ),
            (
                "quincunx_connections_write_timeout_total",
                "Connections closed after a response made no progress for write_timeout_s.",
                &self.connections_write_timeout,
            ),
            (
                "quincunx_connections_evicted_total",
                "Connections closed to make room on a full server (least useful first).",
                &self.connections_evicted,
            ),
            (
                "quincunx_connections_empty_lines_total",
                "Connections closed for too many empty lines before a request line.",
                &self.connections_empty_lines,
            ),
            (
                "quincunx_repository_read_errors_total",
                "Blob or package reads that failed (answered 500; each blob logged once).",
                &self.repository_read_errors,
            ),
            (
                "quincunx_connections_h2_total",
                "HTTP/2 connections accepted.",
                &self.connections_h2,
            ),
            (
                "quincunx_socket_writes_total",
                "Write system calls on client sockets.",
                &self.socket_writes,
            ),
            (
                "quincunx_socket_written_bytes_total",
                "Bytes written to client sockets.",
                &self.socket_bytes_written,
            ),
            (
                "quincunx_socket_reads_total",
                "Read system calls on client sockets that returned data.",
                &self.socket_reads,
            ),
        ];
        for (name, help, counter) in counters {
            let _ = writeln!(
                out,
                "# HELP {name} {help}\n# TYPE {name} counter\n{name} {}",
                counter.load(Relaxed)
            );
        }
        let gauges = [
            (
                "quincunx_connections_open",
                "Connections open now.",
                self.connections_open.load(Relaxed),
            ),
            (
                "quincunx_cache_bytes",
                "Bytes of blobs in the hot cache.",
                cache_bytes,
            ),
            (
                "quincunx_cache_entries",
                "Blobs in the hot cache.",
                cache_entries as u64,
            ),
        ];
        for (name, help, value) in gauges {
            let _ = writeln!(
                out,
                "# HELP {name} {help}\n# TYPE {name} gauge\n{name} {value}"
            );
        }
        out
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use super::*;

    #[test]
    fn observations_show_up_in_the_exposition() {
        let m = Metrics::default();
        m.observe(Route::Blob, 200, 120, Duration::from_micros(30));
        m.observe(Route::Blob, 200, 80, Duration::from_micros(30));
        m.observe(Route::Blob, 418, 0, Duration::from_secs(3));
        m.observe(Route::Other, 503, 0, Duration::from_micros(1));
        let text = m.render(10, 1);
        assert!(text.contains("quincunx_http_requests_total{route=\"blob\",status=\"200\"} 2"));
        assert!(text.contains("quincunx_http_requests_total{route=\"blob\",status=\"other\"} 1"));
        assert!(text.contains("quincunx_http_response_body_bytes_total{route=\"blob\"} 200"));
        assert!(text.contains("quincunx_http_handler_seconds_bucket{le=\"0.00005\"} 3"));
        assert!(text.contains("quincunx_http_handler_seconds_bucket{le=\"+Inf\"} 4"));
        assert_eq!(m.requests_total(), 4);
        assert_eq!(m.server_errors_total(), 1);
    }
}
