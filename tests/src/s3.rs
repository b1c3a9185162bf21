//! An S3-protocol server (`s3s` with its file-system backend, `s3s-fs`) over a real TCP
//! socket, requests signed with one key pair (SigV4, headers or a presigned query): the
//! bucket end of `tests/s3.rs` and of the `s3` source of `benches/hosting/hosting.sh`.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};

use hyper_util::rt::{TokioExecutor, TokioIo};
use hyper_util::server::conn::auto::Builder as ConnBuilder;
use object_store::ObjectStore;
use object_store::aws::{AmazonS3, AmazonS3Builder};
use s3s::auth::SimpleAuth;
use s3s::service::S3ServiceBuilder;
use tokio::sync::oneshot;

/// The key pair the server accepts.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Keys {
    /// `AWS_ACCESS_KEY_ID`.
    pub access_key: String,
    /// `AWS_SECRET_ACCESS_KEY`.
    pub secret_key: String,
}

/// A running server; dropping it stops it.
pub struct S3Server {
    /// Where it listens.
    pub addr: SocketAddr,
    /// The folder of its buckets (one sub-folder each).
    pub root: PathBuf,
    stop: Option<oneshot::Sender<()>>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl S3Server {
    /// Serves the buckets under `root` (created, with the folders of `buckets`) on
    /// `addr` (port 0: any free one), accepting requests signed with `keys` only.
    pub fn start(
        root: &Path,
        buckets: &[&str],
        keys: &Keys,
        addr: SocketAddr,
    ) -> std::io::Result<S3Server> {
        for b in buckets {
            std::fs::create_dir_all(root.join(b))?;
        }
        let fs =
            s3s_fs::FileSystem::new(root).map_err(|e| std::io::Error::other(format!("{e:?}")))?;
        let service = {
            let mut b = S3ServiceBuilder::new(fs);
            b.set_auth(SimpleAuth::from_single(
                keys.access_key.clone(),
                keys.secret_key.clone(),
            ));
            b.build()
        };
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .enable_all()
            .build()?;
        let listener = runtime.block_on(tokio::net::TcpListener::bind(addr))?;
        let addr = listener.local_addr()?;
        let (stop, mut stopped) = oneshot::channel();
        let thread = std::thread::Builder::new()
            .name("s3-server".into())
            .spawn(move || {
                runtime.block_on(async move {
                    let http = ConnBuilder::new(TokioExecutor::new());
                    loop {
                        let socket = tokio::select! {
                            accepted = listener.accept() => match accepted {
                                Ok((socket, _)) => socket,
                                Err(_) => continue,
                            },
                            _ = &mut stopped => break,
                        };
                        let _ = socket.set_nodelay(true);
                        let conn = http
                            .serve_connection(TokioIo::new(socket), service.clone())
                            .into_owned();
                        tokio::spawn(async move {
                            let _ = conn.await;
                        });
                    }
                });
                runtime.shutdown_background();
            })?;
        Ok(S3Server {
            addr,
            root: root.to_path_buf(),
            stop: Some(stop),
            thread: Some(thread),
        })
    }

    /// `http://addr`, the endpoint (`AWS_ENDPOINT_URL`).
    pub fn endpoint(&self) -> String {
        format!("http://{}", self.addr)
    }

    /// An `object_store` client of `bucket` on this server, signing with `keys`.
    pub fn client(&self, bucket: &str, keys: &Keys) -> object_store::Result<AmazonS3> {
        // object_store's reqwest has no bundled TLS provider: the client's (graviola).
        let _ =
            rustls::crypto::CryptoProvider::install_default(rustls_graviola::default_provider());
        AmazonS3Builder::new()
            .with_endpoint(self.endpoint())
            .with_allow_http(true)
            .with_region("us-east-1")
            .with_bucket_name(bucket)
            .with_access_key_id(&keys.access_key)
            .with_secret_access_key(&keys.secret_key)
            .build()
    }

    /// Uploads `bytes` as `bucket/key` with a signed `PUT` (so the server keeps its
    /// `ETag`); blocks.
    pub fn put(&self, keys: &Keys, bucket: &str, key: &str, bytes: Vec<u8>) -> anyhow::Result<()> {
        let store = self.client(bucket, keys)?;
        let path = object_store::path::Path::parse(key)?;
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()?;
        runtime.block_on(store.put_opts(&path, bytes.into(), Default::default()))?;
        Ok(())
    }
}

impl S3Server {
    /// A presigned `GET` URL of `bucket/key` (SigV4 in the query, valid for `expires`).
    pub fn presigned_url(
        &self,
        keys: &Keys,
        bucket: &str,
        key: &str,
        expires: std::time::Duration,
    ) -> anyhow::Result<String> {
        use object_store::signer::Signer;
        let store = self.client(bucket, keys)?;
        let path = object_store::path::Path::parse(key)?;
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()?;
        let url = runtime.block_on(store.signed_url(http::Method::GET, &path, expires))?;
        Ok(url.to_string())
    }
}

impl Drop for S3Server {
    fn drop(&mut self) {
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}
