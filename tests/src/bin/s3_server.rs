//! An S3-protocol server with signed requests, for `benches/hosting/hosting.sh`:
//! `quincunx-s3-server ROOT ADDR BUCKET ACCESS_KEY SECRET_KEY [KEY=FILE ...]` serves the
//! buckets under `ROOT` on `ADDR`, uploads each `FILE` as `BUCKET/KEY` (a signed PUT),
//! prints `ready` and runs until killed.

use std::net::SocketAddr;
use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use quincunx_e2e::s3::{Keys, S3Server};

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [root, addr, bucket, access_key, secret_key, uploads @ ..] = &args[..] else {
        bail!("usage: quincunx-s3-server ROOT ADDR BUCKET ACCESS_KEY SECRET_KEY [KEY=FILE ...]");
    };
    let keys = Keys {
        access_key: access_key.clone(),
        secret_key: secret_key.clone(),
    };
    let addr: SocketAddr = addr.parse().with_context(|| format!("address {addr:?}"))?;
    let server = S3Server::start(&PathBuf::from(root), &[bucket], &keys, addr)
        .with_context(|| format!("serving {root} on {addr}"))?;
    for upload in uploads {
        let Some((key, file)) = upload.split_once('=') else {
            bail!("{upload:?}: KEY=FILE");
        };
        let bytes = std::fs::read(file).with_context(|| format!("reading {file}"))?;
        server
            .put(&keys, bucket, key, bytes)
            .with_context(|| format!("uploading {file} as {bucket}/{key}"))?;
    }
    println!("ready {}", server.endpoint());
    loop {
        std::thread::park();
    }
}
