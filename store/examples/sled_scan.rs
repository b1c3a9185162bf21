//! Scratch: parameter scan (removed before hand-off).
#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use quincunx_store::dir_size;
use std::path::Path;

fn alloc_size(p: &Path) -> u64 {
    use std::os::unix::fs::MetadataExt;
    let mut t = 0;
    for e in std::fs::read_dir(p).unwrap() {
        let e = e.unwrap();
        let m = e.metadata().unwrap();
        if m.is_dir() {
            t += alloc_size(&e.path());
        } else {
            t += m.blocks() * 512;
        }
    }
    t
}

fn nfiles(p: &Path) -> usize {
    let mut t = 0;
    for e in std::fs::read_dir(p).unwrap() {
        let e = e.unwrap();
        if e.metadata().unwrap().is_dir() {
            t += nfiles(&e.path());
        } else {
            t += 1;
        }
    }
    t
}

fn main() {
    let path = std::env::args().nth(1).unwrap();
    let seg_conf = String::from_utf8_lossy(&std::fs::read(Path::new(&path).join("conf")).unwrap()).into_owned();
    let seg: usize = seg_conf
        .lines()
        .find_map(|l| l.strip_prefix("segment_size: "))
        .unwrap()
        .parse()
        .unwrap();
    let blobs: Vec<(Vec<u8>, Vec<u8>)> = {
        let db = sled::Config::new().path(&path).segment_size(seg).open().unwrap();
        let t = db.open_tree("blobs").unwrap();
        t.iter()
            .map(|kv| {
                let (k, v) = kv.unwrap();
                (k.to_vec(), v.to_vec())
            })
            .collect()
    };
    let values: usize = blobs.iter().map(|(_, v)| v.len()).sum();
    eprintln!("blobs {} values {values}", blobs.len());
    let pages: Vec<usize> = std::env::args()
        .nth(2)
        .unwrap()
        .split(',')
        .map(|s| s.parse().unwrap())
        .collect();
    let segs: Vec<usize> = std::env::args()
        .nth(3)
        .unwrap()
        .split(',')
        .map(|s| s.parse().unwrap())
        .collect();
    let batch = std::env::args().nth(4).as_deref() == Some("batch");
    let flush_none = std::env::args().nth(5).as_deref() == Some("noflush");
    for &page in &pages {
        // page 0 = one blob per key
        let items: Vec<(Vec<u8>, Vec<u8>)> = if page == 0 {
            blobs.clone()
        } else {
            let mut out = Vec::new();
            let mut cur: Vec<u8> = Vec::new();
            let mut first: Option<Vec<u8>> = None;
            for (k, v) in &blobs {
                if first.is_none() {
                    first = Some(k.clone());
                }
                cur.push(k.len() as u8);
                cur.extend_from_slice(k);
                cur.extend_from_slice(&(v.len() as u16).to_le_bytes());
                cur.extend_from_slice(v);
                if cur.len() >= page {
                    out.push((first.take().unwrap(), std::mem::take(&mut cur)));
                }
            }
            if let Some(f) = first {
                out.push((f, cur));
            }
            out
        };
        for &seg in &segs {
            let dir = tempfile::tempdir().unwrap();
            let p = dir.path().join("db");
            let cfg = || {
                let c = sled::Config::new()
                    .path(&p)
                    .mode(sled::Mode::LowSpace)
                    .segment_size(seg);
                if flush_none { c.flush_every_ms(None) } else { c }
            };
            {
                let db = cfg().open().unwrap();
                let t = db.open_tree("blobs").unwrap();
                if batch {
                    let mut b = sled::Batch::default();
                    for (k, v) in &items {
                        b.insert(k.as_slice(), v.as_slice());
                    }
                    t.apply_batch(b).unwrap();
                } else {
                    for (k, v) in &items {
                        t.insert(k.as_slice(), v.as_slice()).unwrap();
                    }
                }
                db.insert("metadata", vec![7u8; 3000]).unwrap();
                let fill: usize = std::env::var("FILL").ok().map(|s| s.parse().unwrap()).unwrap_or(0);
                if fill > 0 {
                    let scratch = db.open_tree("~roll").unwrap();
                    for i in 0..fill {
                        scratch.insert("k", &(i as u64).to_le_bytes()).unwrap();
                    }
                    drop(scratch);
                    db.drop_tree("~roll").unwrap();
                }
                db.flush().unwrap();
            }
            let written = dir_size(&p).unwrap();
            if std::env::var("LIST").is_ok() { eprintln!("after write"); list(&p); }
            let mut reopen = vec![];
            for _ in 0..3 {
                let db = sled::Config::new().path(&p).mode(sled::Mode::LowSpace).segment_size(seg).flush_every_ms(None).open().unwrap();
                let t = db.open_tree("blobs").unwrap();
                let n = t.iter().count();
                assert_eq!(n, items.len());
                drop(t);
                drop(db);
                reopen.push(dir_size(&p).unwrap());
            }
            if std::env::var("LIST").is_ok() { eprintln!("after reopen"); list(&p); }
            println!(
                "page {page:6} seg {seg:7} items {:5} written {written:8} reopened {:?} ratio {:.3} alloc {} files {}",
                items.len(),
                reopen,
                reopen[0] as f64 / values as f64,
                alloc_size(&p),
                nfiles(&p)
            );
        }
    }
}
#[allow(dead_code)]
fn list(p: &Path) {
    for e in std::fs::read_dir(p).unwrap() {
        let e = e.unwrap();
        if e.file_type().unwrap().is_dir() {
            for f in std::fs::read_dir(e.path()).unwrap() {
                let f = f.unwrap();
                eprintln!("    blobs/{:?} {}", f.file_name(), f.metadata().unwrap().len());
            }
        } else {
            eprintln!("  {:?} {}", e.file_name(), e.metadata().unwrap().len());
        }
    }
}
