//! The thin quincunx server: hands out repositories' immutable blobs by diamond centre.
//!
//! It never decodes a blob (this crate does not depend on the codec; CI checks it): a
//! request is parsed, its id validated with `quincunx-diamond` (through
//! `quincunx_store::answer::IdSpace`), and the blob's bytes come from the in-memory hot
//! cache or the repository file; packages are framed from stored blobs
//! (`quincunx_store::answer`), never decoded. Blob URLs carry the repository's content
//! hash, so responses are immutable and any HTTP cache or CDN can sit in front.
//! The API is documented in `docs/http-api.md`.
//!
//! - [`config`]: TOML + flags + environment.
//! - [`Server`]: bind, then [`Server::run`] until a shutdown future completes; connections
//!   are HTTP/1.1 (keep-alive, pipelining with aggregated flushes) or HTTP/2 (cleartext
//!   prior knowledge, or by ALPN over TLS with `--tls-cert`/`--tls-key`), with connection,
//!   header, stream and time limits.
//! - [`router`]: the routes, usable in memory (`oneshot`) in tests.

pub mod config;
mod error;
mod listener;
pub mod metrics;
mod routes;
mod state;
mod tls;

use std::future::Future;
use std::net::SocketAddr;
use std::time::Duration;

pub use config::{RepoConfig, ServeArgs, ServerConfig, TlsConfig};
pub use error::ApiError;
pub use routes::router;
pub use state::AppState;

/// Why the server could not start.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ServeError {
    /// The configuration is invalid.
    #[error("configuration: {0}")]
    Config(String),
    /// A repository could not be opened.
    #[error("repository {name:?}: {source}")]
    Store {
        /// Its name.
        name: String,
        /// Cause.
        source: quincunx_store::StoreError,
    },
    /// The TLS certificate or key is unreadable, not PEM, or they do not match.
    #[error("TLS: {0}")]
    Tls(String),
    /// A socket or file operation failed.
    #[error("{context}: {source}")]
    Io {
        /// What was being done.
        context: String,
        /// Cause.
        source: std::io::Error,
    },
}

/// A bound, ready server.
pub struct Server {
    listener: tokio::net::TcpListener,
    tls: Option<tokio_rustls::TlsAcceptor>,
    state: AppState,
    config: ServerConfig,
}

impl Server {
    /// Opens the repositories and binds the listening socket.
    pub async fn bind(config: ServerConfig) -> Result<Server, ServeError> {
        config.check()?;
        let tls = config.tls.as_ref().map(tls::acceptor).transpose()?;
        let state = AppState::open(&config)?;
        let listener = listener::bind(config.addr).map_err(|source| ServeError::Io {
            context: format!("binding {}", config.addr),
            source,
        })?;
        Ok(Server {
            listener,
            tls,
            state,
            config,
        })
    }

    /// The address actually bound (useful with port 0).
    pub fn local_addr(&self) -> Result<SocketAddr, ServeError> {
        self.listener.local_addr().map_err(|source| ServeError::Io {
            context: "reading the bound address".into(),
            source,
        })
    }

    /// `https` when the server terminates TLS, else `http`.
    pub fn scheme(&self) -> &'static str {
        if self.tls.is_some() { "https" } else { "http" }
    }

    /// The shared state (metrics, repositories).
    pub fn state(&self) -> &AppState {
        &self.state
    }

    /// Serves until `shutdown` completes, then drains gracefully.
    pub async fn run(self, shutdown: impl Future<Output = ()> + Send + 'static) {
        let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
        tokio::spawn(async move {
            shutdown.await;
            let _ = stop_tx.send(true);
        });
        let summary = tokio::spawn(summaries(self.state.clone()));
        let workers = match self.config.workers {
            0 => config::cores(),
            n => n,
        };
        // `Server::bind` checked the configuration.
        let per_ip = match listener::PerIp::new(&self.config.limits) {
            Ok(p) => std::sync::Arc::new(p),
            Err(e) => return tracing::error!("{e}"),
        };
        let shared = std::sync::Arc::new(listener::Shared {
            app: router(self.state.clone()),
            state: self.state.clone(),
            permits: std::sync::Arc::new(tokio::sync::Semaphore::new(
                self.config.limits.max_connections,
            )),
            limits: self.config.limits.clone(),
            per_ip,
            registry: std::sync::Arc::default(),
            shutdown: stop_rx,
            tls: self.tls,
        });
        listener::serve(self.listener, workers, shared).await;
        summary.abort();
        tracing::info!(
            requests = self.state.metrics.requests_total(),
            "server stopped"
        );
    }
}

/// One INFO line every 10 s while requests arrive.
async fn summaries(state: AppState) {
    use std::sync::atomic::Ordering::Relaxed;
    let period = Duration::from_secs(10);
    let mut last = (0, 0, 0);
    loop {
        tokio::time::sleep(period).await;
        let m = &state.metrics;
        let now = (
            m.requests_total(),
            m.cache_hits.load(Relaxed),
            m.cache_misses.load(Relaxed),
        );
        let requests = now.0 - last.0;
        if requests > 0 {
            let lookups = (now.1 - last.1) + (now.2 - last.2);
            tracing::info!(
                requests,
                rps = requests as f64 / period.as_secs_f64(),
                cache_hit_ratio = if lookups > 0 {
                    (now.1 - last.1) as f64 / lookups as f64
                } else {
                    1.0
                },
                connections_open = m.connections_open.load(Relaxed),
                server_errors = m.server_errors_total(),
                "serving"
            );
        }
        last = now;
    }
}

/// Runs `quincunx serve` / `quincunx-server`: builds the runtime, serves until Ctrl-C or
/// SIGTERM. `on_ready` is called with the bound address and the scheme (`http` or
/// `https`) once the server accepts.
pub fn run_cli(
    args: &ServeArgs,
    on_ready: impl FnOnce(SocketAddr, &'static str),
) -> Result<(), ServeError> {
    let config = ServerConfig::from_args(args)?;
    raise_descriptor_limit(config.limits.max_connections);
    // This thread is the first worker; `Server::run` starts the others.
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .map_err(|source| ServeError::Io {
            context: "starting the runtime".into(),
            source,
        })?;
    runtime.block_on(async move {
        let server = Server::bind(config).await?;
        on_ready(server.local_addr()?, server.scheme());
        server.run(shutdown_signal()).await;
        Ok(())
    })
}

/// Raises the open-file soft limit towards the hard limit so `max_connections` sockets fit.
fn raise_descriptor_limit(max_connections: usize) {
    let want = max_connections as u64 + 256;
    match rlimit::increase_nofile_limit(want) {
        Ok(got) if got < want => tracing::warn!(
            "open-file limit is {got}: fewer than max_connections = {max_connections} clients fit"
        ),
        Ok(_) => {}
        Err(e) => tracing::warn!("could not raise the open-file limit: {e}"),
    }
}

/// Completes on Ctrl-C or SIGTERM.
pub async fn shutdown_signal() {
    let ctrl_c = tokio::signal::ctrl_c();
    #[cfg(unix)]
    {
        let mut term =
            match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
                Ok(term) => term,
                Err(_) => {
                    let _ = ctrl_c.await;
                    return;
                }
            };
        tokio::select! {
            _ = ctrl_c => {}
            _ = term.recv() => {}
        }
    }
    #[cfg(not(unix))]
    let _ = ctrl_c.await;
    tracing::info!("shutting down: draining connections");
}
