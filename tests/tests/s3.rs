//! Repository files in a private bucket, read through `object_store` with signed requests
//! from a real S3-protocol server (`s3s` on `s3s-fs`) over a TCP socket
//! (`docs/hosting.md`, "Private buckets"):
//! - a session streams `s3://` crack-free at every frame, and every blob read that way is
//!   the stored one; the server refuses unsigned requests;
//! - wrong credentials and a missing key are clear errors at open;
//! - an object replaced mid-session is `FetchError::Changed`, never a mix of two builds;
//! - a presigned `https://…?X-Amz-…` URL reads the file with the plain transport (the
//!   query goes with every request; a forged signature is refused).
#![allow(clippy::unwrap_used, clippy::expect_used)]

use crate::common;

use std::path::Path;
use std::time::Duration;

use common::pack_reads::{
    assert_clean, assert_reads_stored, build, fetch_all, fly_checked_with, raw_fetcher, stored,
};
use quincunx_client::fetch::tls::{BucketOptions, ConnectOptions};
use quincunx_client::fetch::{FetchError, Fetched, Key, Remote};
use quincunx_e2e::s3::{Keys, S3Server};
use quincunx_repo_tools::build::BuildArgs;

const BUCKET: &str = "terrain";

fn keys() -> Keys {
    Keys {
        access_key: "quincunx-test".into(),
        secret_key: "a-secret-of-forty-characters-0123456789".into(),
    }
}

/// A server with one bucket, `root/buckets` its folder.
fn server(root: &Path) -> S3Server {
    S3Server::start(
        &root.join("buckets"),
        &[BUCKET],
        &keys(),
        "127.0.0.1:0".parse().unwrap(),
    )
    .unwrap()
}

/// The settings that reach `server`'s bucket with `keys`: what `AWS_ACCESS_KEY_ID`,
/// `AWS_SECRET_ACCESS_KEY`, `AWS_ENDPOINT_URL`, `AWS_ALLOW_HTTP` and `AWS_REGION` give.
fn reach(server: &S3Server, keys: &Keys) -> ConnectOptions {
    let pairs = [
        ("aws_access_key_id", keys.access_key.clone()),
        ("aws_secret_access_key", keys.secret_key.clone()),
        ("aws_endpoint_url", server.endpoint()),
        ("aws_allow_http", "true".into()),
        ("aws_region", "us-east-1".into()),
    ];
    ConnectOptions {
        bucket: BucketOptions(pairs.map(|(k, v)| (k.to_string(), v)).to_vec()),
        ..ConnectOptions::default()
    }
}

fn open(url: &str, name: &str, connect: &ConnectOptions) -> Result<Remote, FetchError> {
    Remote::open_with(url, name, Duration::from_secs(10), connect).map(|(r, _)| r)
}

fn upload(server: &S3Server, key: &str, repo: &Path) {
    let bytes = std::fs::read(repo.join("repository.pack")).unwrap();
    server.put(&keys(), BUCKET, key, bytes).unwrap();
}

#[test]
fn a_private_bucket_streams_crack_free_with_signed_requests_and_blobs_read_back_exactly() {
    let dir = tempfile::tempdir().unwrap();
    let korea = dir.path().join("korea");
    common::build_bundled_korea(&korea);
    let server = server(dir.path());
    upload(&server, "maps/korea.pack", &korea);
    let connect = reach(&server, &keys());
    let url = format!("s3://{BUCKET}/maps");

    let flight = fly_checked_with(&url, "korea.pack", None, connect.clone());
    assert_clean("korea from s3://", &flight);
    println!(
        "s3: korea: {} requests, {} bytes fetched, 0 cracks",
        flight.requests, flight.bytes_fetched
    );

    // Every blob read through the bucket is the stored one, every other diamond a leaf.
    let want = stored(&korea);
    let remote = open(&url, "korea.pack", &connect).unwrap();
    let pack = remote.pack.clone().unwrap();
    assert_eq!(pack.open_requests, 1, "korea opens in one read");
    assert_eq!(pack.path, "s3://terrain/maps/korea.pack");
    assert!(pack.etag.is_some(), "S3 gives an ETag");
    let stats = assert_reads_stored(remote, &want);
    assert_eq!(stats.errors.total(), 0, "{stats:?}");

    // The bucket is private: an unsigned request is refused.
    let unsigned = common::get(
        server.addr,
        "/terrain/maps/korea.pack",
        &["Range: bytes=0-99"],
    );
    assert_eq!(
        unsigned.status,
        403,
        "{}",
        String::from_utf8_lossy(&unsigned.body)
    );
}

#[test]
fn wrong_credentials_and_missing_keys_are_clear_errors() {
    let dir = tempfile::tempdir().unwrap();
    let korea = dir.path().join("korea");
    common::build_bundled_korea(&korea);
    let server = server(dir.path());
    upload(&server, "korea.pack", &korea);
    let url = format!("s3://{BUCKET}");

    let wrong = Keys {
        secret_key: "not-the-secret".into(),
        ..keys()
    };
    let err = open(&url, "korea.pack", &reach(&server, &wrong)).unwrap_err();
    let msg = err.to_string();
    assert!(matches!(err, FetchError::Metadata(_)), "{err:?}");
    assert!(msg.contains("403") && msg.contains("credentials"), "{msg}");
    assert!(msg.contains("s3://terrain/korea.pack"), "{msg}");
    let unknown = Keys {
        access_key: "nobody".into(),
        ..keys()
    };
    let err = open(&url, "korea.pack", &reach(&server, &unknown)).unwrap_err();
    assert!(err.to_string().contains("403"), "{err}");

    let connect = reach(&server, &keys());
    let err = open(&url, "nothing.pack", &connect).unwrap_err();
    let msg = err.to_string();
    assert!(
        msg.contains("404") && msg.contains("s3://terrain/nothing.pack"),
        "{msg}"
    );
    let err = open("s3://no-such-bucket", "korea.pack", &connect).unwrap_err();
    assert!(err.to_string().contains("404"), "{err}");
    // A bucket holds files, not a server's repositories.
    let err = open(&url, "korea", &connect).unwrap_err();
    assert!(matches!(err, FetchError::BadUrl(_)), "{err:?}");
    // And the right credentials open it.
    open(&url, "korea.pack", &connect).unwrap();
}

#[test]
fn an_object_replaced_mid_session_is_changed_never_a_mix_of_two_builds() {
    let dir = tempfile::tempdir().unwrap();
    let (old, new) = (dir.path().join("old"), dir.path().join("new"));
    common::build_bundled_korea(&old);
    build(&new, "korea_srtm3_1025.json", |a| BuildArgs {
        rms_m: Some(8.0),
        ..a
    });
    let server = server(dir.path());
    upload(&server, "korea.pack", &old);
    let connect = reach(&server, &keys());
    let remote = open(&format!("s3://{BUCKET}"), "korea.pack", &connect).unwrap();
    let fetcher = raw_fetcher(remote);
    let want = stored(&old);
    let keys_wanted: Vec<Key> = want.keys().copied().collect();
    let (first, rest) = keys_wanted.split_at(keys_wanted.len() / 4);
    let got = fetch_all(&fetcher, first, Duration::from_secs(30));
    assert!(got.values().all(|r| matches!(r, Fetched::Data(_))));
    upload(&server, "korea.pack", &new);
    let got = fetch_all(&fetcher, rest, Duration::from_secs(30));
    assert_eq!(got.len(), rest.len());
    let mut changed = 0;
    for (k, r) in &got {
        match r {
            Fetched::Data(v) => assert_eq!(&v[..], &want[k][..], "a blob of the new build"),
            Fetched::Failed(FetchError::Changed(msg)) => {
                assert!(msg.contains("s3://terrain/korea.pack changed"), "{msg}");
                changed += 1;
            }
            other => panic!("{k:?}: {other:?}"),
        }
    }
    assert!(changed > 0, "no request saw the new object");
}

#[test]
fn a_presigned_url_reads_the_file_with_the_plain_transport() {
    let dir = tempfile::tempdir().unwrap();
    let korea = dir.path().join("korea");
    common::build_bundled_korea(&korea);
    let server = server(dir.path());
    upload(&server, "maps/korea.pack", &korea);
    let url = server
        .presigned_url(&keys(), BUCKET, "maps/korea.pack", Duration::from_secs(600))
        .unwrap();
    assert!(url.contains("X-Amz-Signature="), "{url}");

    // The URL names the file itself; or its folder, with the query.
    let (folder, query) = url.split_once('?').unwrap();
    let folder = folder.strip_suffix("/korea.pack").unwrap();
    for base in [url.clone(), format!("{folder}?{query}")] {
        let (remote, _) = Remote::open(&base, "korea.pack", Duration::from_secs(10)).unwrap();
        assert_reads_stored(remote, &stored(&korea));
    }

    // Without the query, or with a forged signature, the server refuses.
    let err = Remote::open(folder, "korea.pack", Duration::from_secs(10)).unwrap_err();
    assert!(err.to_string().contains("status 403"), "{err}");
    // Same length, one digit changed.
    let at = url.find("X-Amz-Signature=").unwrap() + "X-Amz-Signature=".len();
    let digit = if &url[at..=at] == "0" { "1" } else { "0" };
    let forged = format!("{}{digit}{}", &url[..at], &url[at + 1..]);
    let err = Remote::open(&forged, "korea.pack", Duration::from_secs(10)).unwrap_err();
    assert!(err.to_string().contains("status 403"), "{err}");
}
