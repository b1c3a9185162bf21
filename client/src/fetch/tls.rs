//! TLS for `https://` servers: rustls with graviola's pure-Rust crypto (no C compiler for
//! any target), the system's trusted roots plus any CA given in [`ConnectOptions`], and
//! certificate errors that name their cause. There is never a fallback to plain HTTP: an
//! `https://` URL either gets a verified TLS connection or an error.
//!
//! The pipelined transport and the metadata request offer ALPN `http/1.1`; the HTTP/2
//! transport offers `h2` and `http/1.1`, so it speaks HTTP/2 where the server offers it.

use std::io;
use std::net::SocketAddr;
use std::pin::Pin;
use std::sync::{Arc, OnceLock};
use std::task::{Context, Poll};

use rustls::crypto::CryptoProvider;
use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, ServerName};
use rustls::{CertificateError, ClientConfig, RootCertStore};
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::TcpStream;

/// How to reach a server, beyond what its URL says.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct ConnectOptions {
    /// PEM certificates of certificate authorities trusted besides the system's (a
    /// private or test CA), for `https://` URLs.
    pub ca_cert_pem: Option<Vec<u8>>,
    /// Connect to this address instead of the URL host's (an emulated link or a proxy in
    /// front of the server); the `Host` header and the name the certificate must carry
    /// still come from the URL.
    pub connect_to: Option<SocketAddr>,
    /// Settings of a bucket URL (`s3://`, `gs://`, `az://`; feature `object-store`).
    pub bucket: BucketOptions,
}

/// `object_store` settings of a bucket (`aws_access_key_id`, `aws_endpoint`,
/// `google_service_account`, ...), applied over the environment's `AWS_*`, `GOOGLE_*` and
/// `AZURE_*` variables. Shown without values (they hold secrets).
#[derive(Clone, Default, PartialEq, Eq)]
pub struct BucketOptions(pub Vec<(String, String)>);

impl std::fmt::Debug for BucketOptions {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_list()
            .entries(self.0.iter().map(|(k, _)| k))
            .finish()
    }
}

/// The crypto provider of every TLS connection (client and server).
pub fn provider() -> Arc<CryptoProvider> {
    static PROVIDER: OnceLock<Arc<CryptoProvider>> = OnceLock::new();
    Arc::clone(PROVIDER.get_or_init(|| Arc::new(rustls_graviola::default_provider())))
}

/// A client configuration with no trusted roots, for an HTTP client that builds one even
/// when it speaks only cleartext (reqwest): it can verify nothing, so it never carries a
/// connection.
pub fn cleartext_placeholder() -> Result<ClientConfig, TlsError> {
    Ok(ClientConfig::builder_with_provider(provider())
        .with_safe_default_protocol_versions()
        .map_err(|e| TlsError::Config(e.to_string()))?
        .with_root_certificates(RootCertStore::empty())
        .with_no_client_auth())
}

/// The system's trusted roots, loaded once per process.
fn system_roots() -> &'static [CertificateDer<'static>] {
    static ROOTS: OnceLock<Vec<CertificateDer<'static>>> = OnceLock::new();
    ROOTS.get_or_init(|| {
        let found = rustls_native_certs::load_native_certs();
        for e in &found.errors {
            tracing::debug!("system certificate store: {e}");
        }
        found.certs
    })
}

/// Why TLS could not be set up or a handshake failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum TlsError {
    /// The extra CA file is not PEM certificates.
    #[error("CA certificate: {0}")]
    CaCert(String),
    /// The URL's host is not a valid TLS server name.
    #[error("{0:?} is not a valid TLS server name")]
    ServerName(String),
    /// rustls refused the configuration.
    #[error("TLS configuration: {0}")]
    Config(String),
}

/// The TLS side of an `https://` endpoint: the name its certificate must carry and the
/// client configurations (ALPN `http/1.1`, and `h2` then `http/1.1`).
#[derive(Clone)]
pub struct TlsClient {
    /// The name the server's certificate must be valid for (the URL's host).
    pub server_name: ServerName<'static>,
    http1: Arc<ClientConfig>,
    h2: Arc<ClientConfig>,
}

impl std::fmt::Debug for TlsClient {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TlsClient")
            .field("server_name", &self.server_name)
            .finish_non_exhaustive()
    }
}

impl PartialEq for TlsClient {
    fn eq(&self, o: &Self) -> bool {
        self.server_name == o.server_name && Arc::ptr_eq(&self.http1, &o.http1)
    }
}

impl Eq for TlsClient {}

impl TlsClient {
    /// TLS to `host` (a name or an IP address, without port or brackets), trusting the
    /// system's roots and the certificates in `ca_cert_pem`.
    pub fn new(host: &str, ca_cert_pem: Option<&[u8]>) -> Result<TlsClient, TlsError> {
        if let Some(why) = quincunx_meta::crypto::tls_cpu_unsupported() {
            return Err(TlsError::Config(why));
        }
        let server_name = ServerName::try_from(host.to_string())
            .map_err(|_| TlsError::ServerName(host.to_string()))?;
        let mut roots = RootCertStore::empty();
        let (_added, _ignored) = roots.add_parsable_certificates(system_roots().iter().cloned());
        if let Some(pem) = ca_cert_pem {
            let mut n = 0;
            for cert in CertificateDer::pem_slice_iter(pem) {
                let cert = cert.map_err(|e| TlsError::CaCert(e.to_string()))?;
                roots
                    .add(cert)
                    .map_err(|e| TlsError::CaCert(e.to_string()))?;
                n += 1;
            }
            if n == 0 {
                return Err(TlsError::CaCert("no PEM certificate in it".into()));
            }
        }
        let roots = Arc::new(roots);
        let config = |alpn: &[&[u8]]| -> Result<Arc<ClientConfig>, TlsError> {
            let mut c = ClientConfig::builder_with_provider(provider())
                .with_safe_default_protocol_versions()
                .map_err(|e| TlsError::Config(e.to_string()))?
                .with_root_certificates(Arc::clone(&roots))
                .with_no_client_auth();
            c.alpn_protocols = alpn.iter().map(|p| p.to_vec()).collect();
            Ok(Arc::new(c))
        };
        Ok(TlsClient {
            server_name,
            http1: config(&[b"http/1.1"])?,
            h2: config(&[b"h2", b"http/1.1"])?,
        })
    }

    /// The configuration offering only HTTP/1.1 by ALPN.
    pub fn http1_config(&self) -> Arc<ClientConfig> {
        Arc::clone(&self.http1)
    }

    /// The configuration offering HTTP/2, then HTTP/1.1, by ALPN.
    pub fn h2_config(&self) -> Arc<ClientConfig> {
        Arc::clone(&self.h2)
    }

    /// The server name as text (for messages).
    pub fn host(&self) -> String {
        self.server_name.to_str().into_owned()
    }

    /// A TLS handshake over `tcp` offering HTTP/1.1.
    pub(crate) async fn connect(&self, tcp: TcpStream) -> io::Result<Stream> {
        let connector = tokio_rustls::TlsConnector::from(self.http1_config());
        let tls = connector.connect(self.server_name.clone(), tcp).await?;
        Ok(Stream::Tls(Box::new(tls)))
    }
}

/// What a certificate or handshake failure means, naming its cause: an unknown issuer,
/// a wrong host name, an expired (or not yet valid) certificate.
pub fn describe(e: &rustls::Error, host: &str) -> String {
    let cause = match e {
        rustls::Error::InvalidCertificate(c) => match c {
            CertificateError::UnknownIssuer => format!(
                "the certificate of {host} has an unknown issuer (no trusted CA signed it; \
                 give its CA with --ca-cert)"
            ),
            CertificateError::NotValidForName | CertificateError::NotValidForNameContext { .. } => {
                format!("the certificate is not valid for the host name {host} ({c})")
            }
            CertificateError::Expired | CertificateError::ExpiredContext { .. } => {
                format!("the certificate of {host} has expired ({c})")
            }
            CertificateError::NotValidYet | CertificateError::NotValidYetContext { .. } => {
                format!("the certificate of {host} is not valid yet ({c})")
            }
            other => format!("the certificate of {host} is invalid ({other})"),
        },
        other => format!("TLS handshake with {host}: {other}"),
    };
    format!("TLS: {cause}")
}

/// The TLS failure inside an I/O error, described, if it is one.
pub fn tls_cause(e: &io::Error, host: &str) -> Option<String> {
    e.get_ref()
        .and_then(|inner| inner.downcast_ref::<rustls::Error>())
        .map(|t| describe(t, host))
}

/// The TLS failure anywhere in an error's chain of causes, described.
pub fn find_tls_cause(e: &(dyn std::error::Error + 'static), host: &str) -> Option<String> {
    let mut cur = Some(e);
    while let Some(err) = cur {
        if let Some(t) = err.downcast_ref::<rustls::Error>() {
            return Some(describe(t, host));
        }
        if let Some(io) = err.downcast_ref::<io::Error>()
            && let Some(msg) = tls_cause(io, host)
        {
            return Some(msg);
        }
        // An I/O error's `source` skips the error it wraps: look inside.
        if let Some(inner) = err.downcast_ref::<io::Error>().and_then(|io| io.get_ref())
            && let Some(msg) = find_tls_cause(as_error(inner), host)
        {
            return Some(msg);
        }
        cur = err.source();
    }
    // Layers that keep only the text (connectors boxing their errors anew).
    let text = chain_text(e);
    let certificate = |c: CertificateError| describe(&rustls::Error::InvalidCertificate(c), host);
    let (_, rest) = text.split_once("invalid peer certificate: ")?;
    Some(if rest.starts_with("UnknownIssuer") {
        certificate(CertificateError::UnknownIssuer)
    } else if rest.starts_with("NotValidForName") || rest.contains("not valid for name") {
        certificate(CertificateError::NotValidForName)
    } else if rest.starts_with("Expired") || rest.contains("expired") {
        certificate(CertificateError::Expired)
    } else {
        format!("TLS: the certificate of {host} is invalid ({rest})")
    })
}

fn as_error<'a>(
    e: &'a (dyn std::error::Error + Send + Sync + 'static),
) -> &'a (dyn std::error::Error + 'static) {
    e
}

fn chain_text(e: &(dyn std::error::Error + 'static)) -> String {
    let mut text = e.to_string();
    let mut cur = e.source();
    while let Some(err) = cur {
        text.push_str(": ");
        text.push_str(&err.to_string());
        cur = err.source();
    }
    text
}

/// A client connection: plain TCP or TLS over TCP.
#[derive(Debug)]
pub enum Stream {
    /// `http://`.
    Plain(TcpStream),
    /// `https://`.
    Tls(Box<tokio_rustls::client::TlsStream<TcpStream>>),
}

impl Stream {
    /// The protocol the server chose by ALPN (`h2`, `http/1.1`), if any.
    pub fn alpn(&self) -> Option<&[u8]> {
        match self {
            Stream::Plain(_) => None,
            Stream::Tls(t) => t.get_ref().1.alpn_protocol(),
        }
    }
}

impl AsyncRead for Stream {
    fn poll_read(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        match self.get_mut() {
            Stream::Plain(s) => Pin::new(s).poll_read(cx, buf),
            Stream::Tls(s) => Pin::new(s.as_mut()).poll_read(cx, buf),
        }
    }
}

impl AsyncWrite for Stream {
    fn poll_write(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        match self.get_mut() {
            Stream::Plain(s) => Pin::new(s).poll_write(cx, buf),
            Stream::Tls(s) => Pin::new(s.as_mut()).poll_write(cx, buf),
        }
    }

    fn poll_flush(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        match self.get_mut() {
            Stream::Plain(s) => Pin::new(s).poll_flush(cx),
            Stream::Tls(s) => Pin::new(s.as_mut()).poll_flush(cx),
        }
    }

    fn poll_shutdown(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        match self.get_mut() {
            Stream::Plain(s) => Pin::new(s).poll_shutdown(cx),
            Stream::Tls(s) => Pin::new(s.as_mut()).poll_shutdown(cx),
        }
    }
}
