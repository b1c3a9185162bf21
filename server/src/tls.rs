//! TLS termination: the certificate and key of [`crate::config::TlsConfig`] loaded into a
//! rustls server configuration (graviola's crypto, like the client) that offers HTTP/2 and
//! HTTP/1.1 by ALPN, so browsers get HTTP/2.

use std::path::Path;
use std::sync::Arc;

use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, PrivateKeyDer};

use crate::ServeError;
use crate::config::TlsConfig;

fn tls_error(msg: String) -> ServeError {
    ServeError::Tls(msg)
}

fn read(path: &Path, what: &str) -> Result<Vec<u8>, ServeError> {
    std::fs::read(path)
        .map_err(|e| tls_error(format!("reading the {what} {}: {e}", path.display())))
}

/// The acceptor for `config`: certificate chain and key read and checked to match.
pub(crate) fn acceptor(config: &TlsConfig) -> Result<tokio_rustls::TlsAcceptor, ServeError> {
    let cert_pem = read(&config.cert, "certificate")?;
    let key_pem = read(&config.key, "key")?;
    let certs = CertificateDer::pem_slice_iter(&cert_pem)
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| tls_error(format!("{}: {e}", config.cert.display())))?;
    if certs.is_empty() {
        return Err(tls_error(format!(
            "{} holds no PEM certificate",
            config.cert.display()
        )));
    }
    let key = PrivateKeyDer::from_pem_slice(&key_pem).map_err(|e| {
        tls_error(format!(
            "{} holds no usable PEM private key: {e}",
            config.key.display()
        ))
    })?;
    if let Some(why) = quincunx_meta::crypto::tls_cpu_unsupported() {
        return Err(tls_error(why));
    }
    let provider = Arc::new(rustls_graviola::default_provider());
    let mut server = rustls::ServerConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .map_err(|e| tls_error(e.to_string()))?
        .with_no_client_auth()
        .with_single_cert(certs, key)
        .map_err(|e| match e {
            rustls::Error::InconsistentKeys(_) => tls_error(format!(
                "the key in {} does not match the certificate in {}",
                config.key.display(),
                config.cert.display()
            )),
            e => tls_error(format!(
                "certificate {} with key {}: {e}",
                config.cert.display(),
                config.key.display()
            )),
        })?;
    server.alpn_protocols = vec![b"h2".to_vec(), b"http/1.1".to_vec()];
    Ok(tokio_rustls::TlsAcceptor::from(Arc::new(server)))
}
