//! Server configuration: a TOML file, overridden by command-line flags and `QUINCUNX_*`
//! environment variables (flags win over the environment, both over the file).

use std::net::{IpAddr, SocketAddr};
use std::path::{Path, PathBuf};
use std::time::Duration;

use serde::Deserialize;

use crate::ServeError;

/// Everything the server needs, with defaults suitable for the internet.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ServerConfig {
    /// Address to listen on.
    pub addr: SocketAddr,
    /// Repositories to serve, by name.
    #[serde(rename = "repo")]
    pub repos: Vec<RepoConfig>,
    /// Bytes of blobs kept in the in-memory hot cache in front of the repository files.
    pub cache_bytes: u64,
    /// Worker threads, each with its own listener and event loop (0 = one per core; at
    /// most [`max_workers`]).
    pub workers: usize,
    /// Connection and request limits.
    pub limits: Limits,
    /// Cross-origin resource sharing.
    pub cors: Cors,
    /// TLS: serve `https://` (HTTP/2 and HTTP/1.1 by ALPN) with this certificate and key
    /// instead of cleartext HTTP.
    pub tls: Option<TlsConfig>,
}

/// The certificate and key of an `https://` server (`[tls]` in the configuration file).
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TlsConfig {
    /// PEM file of the certificate chain, the server's own certificate first.
    pub cert: PathBuf,
    /// PEM file of its private key (PKCS#8, PKCS#1 or SEC1).
    pub key: PathBuf,
}

/// One repository to serve.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RepoConfig {
    /// Name in URLs: ASCII letters, digits, `-`, `_`, `.` (not leading).
    pub name: String,
    /// The repository directory (built by `quincunx build`).
    pub path: PathBuf,
}

/// Limits that keep one client (or many) from exhausting the server.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Limits {
    /// Open connections at most; more are answered `503` and closed at once.
    pub max_connections: usize,
    /// Open connections per client address at most (IPv6: per /64), 0 for no limit; more
    /// are answered `429` and closed at once. Loopback is not exempt.
    pub max_connections_per_ip: usize,
    /// Client addresses (`10.0.0.5`) or networks (`10.0.0.0/8`, `fd00::/8`) exempt from
    /// `max_connections_per_ip`, such as a reverse proxy in front of the server.
    pub per_ip_exempt: Vec<String>,
    /// Bytes of a request head (request line + headers) at most; larger heads get `431`.
    /// HTTP/1 reads at most this many bytes ahead of the request being answered, which
    /// bounds the pipelined requests buffered per connection.
    pub max_header_bytes: usize,
    /// Header fields per request at most.
    pub max_headers: usize,
    /// HTTP/2 streams in flight per connection at most.
    pub max_concurrent_streams: u32,
    /// Seconds a client has to send a complete request (slow-loris defence): a new
    /// connection's first request head (HTTP/2: preface, SETTINGS and a complete HEADERS
    /// block) counts from the accept, later heads from their first byte. Empty lines do
    /// not restart it; time the server spends blocked writing to the client does not
    /// count. See `docs/http-api.md`, "Slow clients".
    pub header_timeout_s: f64,
    /// Seconds a response may stay blocked without any of it moving (a client that stopped
    /// reading, or an HTTP/2 stream that stopped making progress) before the connection
    /// is closed.
    pub write_timeout_s: f64,
    /// Seconds without any bytes moving in either direction before a connection is closed
    /// (idle keep-alive connections, and clients that stop reading their responses).
    pub idle_timeout_s: f64,
    /// Seconds graceful shutdown waits for in-flight requests before closing the rest.
    pub shutdown_grace_s: f64,
}

/// Which origins may read responses from scripts.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Cors {
    /// Allowed origins: `["*"]` (any, the default: blobs are public), a list of exact
    /// origins (echoed back with `Vary: Origin`), or empty to send no CORS headers.
    pub allow_origins: Vec<String>,
}

impl Default for ServerConfig {
    fn default() -> Self {
        ServerConfig {
            addr: SocketAddr::from(([127, 0, 0, 1], 8080)),
            repos: Vec::new(),
            cache_bytes: 256 << 20,
            workers: 0,
            limits: Limits::default(),
            cors: Cors::default(),
            tls: None,
        }
    }
}

impl Default for Limits {
    fn default() -> Self {
        Limits {
            max_connections: 16_384,
            max_connections_per_ip: 256,
            per_ip_exempt: Vec::new(),
            max_header_bytes: 16 << 10,
            max_headers: 64,
            max_concurrent_streams: 128,
            header_timeout_s: 10.0,
            write_timeout_s: 30.0,
            idle_timeout_s: 120.0,
            shutdown_grace_s: 10.0,
        }
    }
}

impl Default for Cors {
    fn default() -> Self {
        Cors {
            allow_origins: vec!["*".to_string()],
        }
    }
}

impl Limits {
    /// [`Limits::header_timeout_s`] as a duration.
    pub fn header_timeout(&self) -> Duration {
        Duration::from_secs_f64(self.header_timeout_s)
    }
    /// [`Limits::write_timeout_s`] as a duration.
    pub fn write_timeout(&self) -> Duration {
        Duration::from_secs_f64(self.write_timeout_s)
    }
    /// [`Limits::per_ip_exempt`] parsed.
    pub fn exempt_networks(&self) -> Result<Vec<IpNet>, ServeError> {
        self.per_ip_exempt.iter().map(|s| IpNet::parse(s)).collect()
    }
    /// [`Limits::idle_timeout_s`] as a duration.
    pub fn idle_timeout(&self) -> Duration {
        Duration::from_secs_f64(self.idle_timeout_s)
    }
    /// [`Limits::shutdown_grace_s`] as a duration.
    pub fn shutdown_grace(&self) -> Duration {
        Duration::from_secs_f64(self.shutdown_grace_s)
    }
}

/// Command-line flags of `quincunx serve` (and of the `quincunx-server` binary).
#[derive(Clone, Debug, Default, clap::Args)]
pub struct ServeArgs {
    /// TOML configuration file (see docs/http-api.md); flags override it.
    #[arg(long, env = "QUINCUNX_CONFIG")]
    pub config: Option<PathBuf>,
    /// Address to listen on, e.g. 127.0.0.1:8080 or 0.0.0.0:80.
    #[arg(long, env = "QUINCUNX_ADDR")]
    pub addr: Option<SocketAddr>,
    /// A repository to serve, as NAME=PATH (repeatable; adds to the configuration file's).
    #[arg(long = "repo", value_name = "NAME=PATH", value_parser = parse_repo)]
    pub repos: Vec<RepoConfig>,
    /// Hot cache size in MiB.
    #[arg(long, env = "QUINCUNX_CACHE_MB")]
    pub cache_mb: Option<u64>,
    /// Open connections at most.
    #[arg(long, env = "QUINCUNX_MAX_CONNECTIONS")]
    pub max_connections: Option<usize>,
    /// Open connections per client address at most (0 = no limit).
    #[arg(long, env = "QUINCUNX_MAX_CONNECTIONS_PER_IP")]
    pub max_connections_per_ip: Option<usize>,
    /// Seconds a blocked response may make no progress before the connection is closed.
    #[arg(long, env = "QUINCUNX_WRITE_TIMEOUT_S")]
    pub write_timeout_s: Option<f64>,
    /// Idle connection timeout in seconds.
    #[arg(long, env = "QUINCUNX_IDLE_TIMEOUT_S")]
    pub idle_timeout_s: Option<f64>,
    /// Request-head timeout in seconds.
    #[arg(long, env = "QUINCUNX_HEADER_TIMEOUT_S")]
    pub header_timeout_s: Option<f64>,
    /// Allowed CORS origins, comma separated (`*` for any, empty for none).
    #[arg(long, env = "QUINCUNX_CORS")]
    pub cors: Option<String>,
    /// Worker threads, each with its own listener and event loop (default: one per core;
    /// at most 4 per core and 1024).
    #[arg(long, env = "QUINCUNX_THREADS")]
    pub threads: Option<usize>,
    /// Serve https:// with this PEM certificate chain (with --tls-key).
    #[arg(long, env = "QUINCUNX_TLS_CERT", requires = "tls_key")]
    pub tls_cert: Option<PathBuf>,
    /// The PEM private key of --tls-cert.
    #[arg(long, env = "QUINCUNX_TLS_KEY", requires = "tls_cert")]
    pub tls_key: Option<PathBuf>,
}

fn parse_repo(s: &str) -> Result<RepoConfig, String> {
    let (name, path) = s
        .split_once('=')
        .ok_or_else(|| format!("expected NAME=PATH, got {s:?}"))?;
    Ok(RepoConfig {
        name: name.to_string(),
        path: PathBuf::from(path),
    })
}

impl ServerConfig {
    /// Parses a TOML configuration.
    pub fn from_toml(text: &str, origin: &Path) -> Result<ServerConfig, ServeError> {
        toml::from_str(text).map_err(|e| ServeError::Config(format!("{}: {e}", origin.display())))
    }

    /// The file (if any) with the flags applied, checked.
    pub fn from_args(args: &ServeArgs) -> Result<ServerConfig, ServeError> {
        let mut config = match &args.config {
            Some(path) => {
                let text = std::fs::read_to_string(path).map_err(|source| ServeError::Io {
                    context: format!("reading {}", path.display()),
                    source,
                })?;
                ServerConfig::from_toml(&text, path)?
            }
            None => ServerConfig::default(),
        };
        if let Some(addr) = args.addr {
            config.addr = addr;
        }
        config.repos.extend(args.repos.iter().cloned());
        if let Some(mb) = args.cache_mb {
            config.cache_bytes = mb << 20;
        }
        if let Some(n) = args.threads {
            config.workers = n;
        }
        if let Some(n) = args.max_connections {
            config.limits.max_connections = n;
        }
        if let Some(n) = args.max_connections_per_ip {
            config.limits.max_connections_per_ip = n;
        }
        if let Some(s) = args.write_timeout_s {
            config.limits.write_timeout_s = s;
        }
        if let Some(s) = args.idle_timeout_s {
            config.limits.idle_timeout_s = s;
        }
        if let Some(s) = args.header_timeout_s {
            config.limits.header_timeout_s = s;
        }
        match (&args.tls_cert, &args.tls_key) {
            (Some(cert), Some(key)) => {
                config.tls = Some(TlsConfig {
                    cert: cert.clone(),
                    key: key.clone(),
                });
            }
            (None, None) => {}
            _ => {
                return Err(ServeError::Config(
                    "--tls-cert and --tls-key go together".into(),
                ));
            }
        }
        if let Some(cors) = &args.cors {
            config.cors.allow_origins = cors
                .split(',')
                .map(str::trim)
                .filter(|s| !s.is_empty())
                .map(String::from)
                .collect();
        }
        config.check()?;
        Ok(config)
    }

    /// Rejects configurations the server cannot honour.
    pub fn check(&self) -> Result<(), ServeError> {
        let bad = |what: String| Err(ServeError::Config(what));
        if self.repos.is_empty() {
            return bad("no repositories to serve (pass --repo NAME=PATH)".into());
        }
        for (i, repo) in self.repos.iter().enumerate() {
            if !quincunx_store::is_valid_name(&repo.name) {
                return bad(format!(
                    "repository name {:?} must be ASCII letters, digits, '-', '_' or '.' (not leading)",
                    repo.name
                ));
            }
            if self.repos[..i].iter().any(|r| r.name == repo.name) {
                return bad(format!("repository name {:?} is given twice", repo.name));
            }
        }
        let most = max_workers();
        if self.workers > most {
            return bad(format!(
                "workers (--threads) = {} is more than {most}: at most 4 per core ({} cores \
                 here) and never more than {MAX_WORKERS}; 0 means one per core",
                self.workers,
                cores()
            ));
        }
        let l = &self.limits;
        l.exempt_networks()?;
        if l.max_connections == 0 {
            return bad("limits.max_connections must be at least 1".into());
        }
        if !(1024..=1 << 20).contains(&l.max_header_bytes) {
            return bad("limits.max_header_bytes must be in 1024..=1048576".into());
        }
        if l.max_headers == 0 || l.max_concurrent_streams == 0 {
            return bad("limits.max_headers and max_concurrent_streams must be positive".into());
        }
        for (name, s) in [
            ("header_timeout_s", l.header_timeout_s),
            ("write_timeout_s", l.write_timeout_s),
            ("idle_timeout_s", l.idle_timeout_s),
            ("shutdown_grace_s", l.shutdown_grace_s),
        ] {
            if !(s.is_finite() && s > 0.0 && s < 1e7) {
                return bad(format!(
                    "limits.{name} must be a positive number of seconds"
                ));
            }
        }
        Ok(())
    }
}

/// Worker threads at most, whatever the core count.
pub const MAX_WORKERS: usize = 1024;

/// Cores available to this process (1 if unknown).
pub fn cores() -> usize {
    std::thread::available_parallelism().map_or(1, usize::from)
}

/// The most worker threads a configuration may ask for: 4 per core, at most
/// [`MAX_WORKERS`]. More only adds threads that contend for the same cores.
pub fn max_workers() -> usize {
    (4 * cores()).min(MAX_WORKERS)
}

/// An address or network (`addr/prefix`), for [`Limits::per_ip_exempt`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct IpNet {
    addr: IpAddr,
    prefix: u8,
}

impl IpNet {
    /// Parses `10.0.0.5`, `10.0.0.0/8`, `::1` or `fd00::/8`.
    pub fn parse(s: &str) -> Result<IpNet, ServeError> {
        let bad = || {
            ServeError::Config(format!(
                "limits.per_ip_exempt: {s:?} is not an address or addr/prefix"
            ))
        };
        let (addr, prefix) = match s.split_once('/') {
            Some((a, p)) => (a, Some(p)),
            None => (s, None),
        };
        let addr: IpAddr = addr.trim().parse().map_err(|_| bad())?;
        let max = if addr.is_ipv4() { 32 } else { 128 };
        let prefix = match prefix {
            Some(p) => p.trim().parse::<u8>().map_err(|_| bad())?,
            None => max,
        };
        if prefix > max {
            return Err(bad());
        }
        Ok(IpNet { addr, prefix })
    }

    /// Whether `ip` is in the network (IPv4-mapped IPv6 addresses count as IPv4).
    pub fn contains(&self, ip: IpAddr) -> bool {
        let ip = canonical_ip(ip);
        match (self.addr, ip) {
            (IpAddr::V4(net), IpAddr::V4(ip)) => {
                let mask = u32::MAX
                    .checked_shl(32 - u32::from(self.prefix))
                    .unwrap_or(0);
                u32::from(net) & mask == u32::from(ip) & mask
            }
            (IpAddr::V6(net), IpAddr::V6(ip)) => {
                let mask = u128::MAX
                    .checked_shl(128 - u32::from(self.prefix))
                    .unwrap_or(0);
                u128::from(net) & mask == u128::from(ip) & mask
            }
            _ => false,
        }
    }
}

/// `ip` with IPv4-mapped IPv6 addresses (`::ffff:a.b.c.d`) turned into IPv4.
pub fn canonical_ip(ip: IpAddr) -> IpAddr {
    match ip {
        IpAddr::V6(v6) => v6.to_ipv4_mapped().map_or(ip, IpAddr::V4),
        v4 => v4,
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use super::*;

    #[test]
    fn toml_file_is_read_and_flags_override_it() {
        let text = r#"
            addr = "0.0.0.0:9000"
            cache_bytes = 1000
            [limits]
            max_connections = 7
            [cors]
            allow_origins = ["https://a.example"]
            [[repo]]
            name = "earth"
            path = "/srv/earth"
        "#;
        let config = ServerConfig::from_toml(text, Path::new("x.toml")).unwrap();
        assert_eq!(config.addr.port(), 9000);
        assert_eq!(config.limits.max_connections, 7);
        assert_eq!(config.limits.max_headers, Limits::default().max_headers);
        assert_eq!(config.repos[0].name, "earth");
        assert_eq!(config.cors.allow_origins, ["https://a.example"]);
        config.check().unwrap();
    }

    #[test]
    fn unknown_keys_and_bad_names_are_rejected() {
        assert!(ServerConfig::from_toml("adr = \"1.2.3.4:5\"", Path::new("x")).is_err());
        let args = ServeArgs {
            repos: vec![parse_repo("../etc=/x").unwrap()],
            ..ServeArgs::default()
        };
        assert!(ServerConfig::from_args(&args).is_err());
        let args = ServeArgs {
            repos: vec![parse_repo("a=/x").unwrap(), parse_repo("a=/y").unwrap()],
            ..ServeArgs::default()
        };
        assert!(ServerConfig::from_args(&args).is_err());
        assert!(parse_repo("noequals").is_err());
        assert!(ServerConfig::from_args(&ServeArgs::default()).is_err());
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod limit_tests {
    use super::*;

    #[test]
    fn thread_counts_past_the_bound_are_rejected_with_the_bound_named() {
        let repos = vec![parse_repo("a=/x").unwrap()];
        let args = ServeArgs {
            repos: repos.clone(),
            threads: Some(100_000),
            ..ServeArgs::default()
        };
        let err = ServerConfig::from_args(&args).unwrap_err().to_string();
        assert!(
            err.contains("100000") && err.contains(&max_workers().to_string()),
            "{err}"
        );
        let config = ServerConfig {
            repos: vec![RepoConfig {
                name: "a".into(),
                path: "/x".into(),
            }],
            workers: max_workers(),
            ..ServerConfig::default()
        };
        config.check().unwrap();
        let config = ServerConfig {
            workers: max_workers() + 1,
            ..config
        };
        assert!(config.check().is_err());
    }

    #[test]
    fn exempt_networks_parse_and_match() {
        let net = IpNet::parse("10.0.0.0/8").unwrap();
        assert!(net.contains("10.200.3.4".parse().unwrap()));
        assert!(net.contains("::ffff:10.1.1.1".parse().unwrap()));
        assert!(!net.contains("11.0.0.1".parse().unwrap()));
        let one = IpNet::parse("127.0.0.1").unwrap();
        assert!(one.contains("127.0.0.1".parse().unwrap()));
        assert!(!one.contains("127.0.0.2".parse().unwrap()));
        let v6 = IpNet::parse("fd00::/8").unwrap();
        assert!(v6.contains("fd12::1".parse().unwrap()));
        assert!(!v6.contains("fe80::1".parse().unwrap()));
        assert!(
            IpNet::parse("0.0.0.0/0")
                .unwrap()
                .contains("1.2.3.4".parse().unwrap())
        );
        for bad in ["10.0.0.0/33", "nope", "::/129", "1.2.3.4/x"] {
            assert!(IpNet::parse(bad).is_err(), "{bad}");
        }
    }
}
