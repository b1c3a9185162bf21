//! Measures sled's space overhead for a repository's blobs under different write
//! strategies (used to choose how `RepositoryBuilder` writes; see
//! `docs/repository-format.md`). Usage: `cargo run --release -p quincunx-store --example
//! sled_space -- <repo>`; prints one JSON line per strategy.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use quincunx_store::{Repository, dir_size};

fn main() {
    let path = std::env::args().nth(1).expect("usage: sled_space <repo>");
    let repo = Repository::open(&path).unwrap();
    let blobs: Vec<(Vec<u8>, Vec<u8>)> = repo
        .blobs()
        .map(|kv| {
            let (k, v) = kv.unwrap();
            (k.to_vec(), v.to_vec())
        })
        .collect();
    let payload: usize = blobs.iter().map(|(k, v)| k.len() + v.len()).sum();
    let values: usize = blobs.iter().map(|(_, v)| v.len()).sum();
    for (page, seg) in [(4096usize, 512usize << 10), (65536, 512 << 10), (4096, 64 << 10), (65536, 64 << 10), (65536, 8 << 10)] {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("db");
        {
            let db = sled::Config::new().path(&p).mode(sled::Mode::LowSpace).segment_size(seg).open().unwrap();
            let t = db.open_tree("pages").unwrap();
            let mut b = sled::Batch::default();
            let mut cur: Vec<u8> = Vec::new();
            let mut first: Option<Vec<u8>> = None;
            for (k, v) in &blobs {
                if first.is_none() {
                    first = Some(k.clone());
                }
                cur.push(k.len() as u8);
                cur.extend_from_slice(k);
                cur.extend_from_slice(&(v.len() as u32).to_le_bytes());
                cur.extend_from_slice(v);
                if cur.len() >= page {
                    t.insert(first.take().unwrap(), std::mem::take(&mut cur)).unwrap();
                }
            }
            if let Some(f) = first {
                t.insert(f, cur).unwrap();
            }
            drop(b);
            db.flush().unwrap();
        }
        {
            let _db = sled::Config::new().path(&p).segment_size(seg).open().unwrap();
        }
        let reopened = dir_size(&p).unwrap();
        for e in std::fs::read_dir(&p).unwrap() {
            let e = e.unwrap();
            eprintln!("  {:?} {}", e.file_name(), e.metadata().unwrap().len());
            if e.file_type().unwrap().is_dir() {
                for f in std::fs::read_dir(e.path()).unwrap() {
                    let f = f.unwrap();
                    eprintln!("    {:?} {}", f.file_name(), f.metadata().unwrap().len());
                }
            }
        }
        println!(
            "{{\"strategy\":\"pages_{page}_seg{seg}\",\"disk_bytes_after_reopen\":{reopened},\"overhead\":{:.3}}}",
            reopened as f64 / values as f64
        );
    }
    for (name, segment, batch, mode) in [
        ("insert_lowspace_512k", 512 << 10, false, sled::Mode::LowSpace),
        ("batch_lowspace_512k", 512 << 10, true, sled::Mode::LowSpace),
        ("batch_lowspace_64k", 64 << 10, true, sled::Mode::LowSpace),
        ("batch_throughput_512k", 512 << 10, true, sled::Mode::HighThroughput),
    ] {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("db");
        {
            let db = sled::Config::new()
                .path(&p)
                .mode(mode)
                .segment_size(segment)
                .open()
                .unwrap();
            let t = db.open_tree("blobs").unwrap();
            if batch {
                let mut b = sled::Batch::default();
                for (k, v) in &blobs {
                    b.insert(k.as_slice(), v.as_slice());
                }
                t.apply_batch(b).unwrap();
            } else {
                for (k, v) in &blobs {
                    t.insert(k.as_slice(), v.as_slice()).unwrap();
                }
            }
            db.flush().unwrap();
        }
        let written = dir_size(&p).unwrap();
        {
            let db = sled::Config::new().path(&p).segment_size(segment).open().unwrap();
            assert_eq!(db.open_tree("blobs").unwrap().len(), blobs.len());
        }
        let reopened = dir_size(&p).unwrap();
        println!(
            "{{\"strategy\":\"{name}\",\"blobs\":{},\"value_bytes\":{values},\"key_and_value_bytes\":{payload},\"disk_bytes\":{written},\"disk_bytes_after_reopen\":{reopened},\"overhead\":{:.3}}}",
            blobs.len(),
            reopened as f64 / values as f64
        );
    }
}
