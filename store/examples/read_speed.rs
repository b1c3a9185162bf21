//! Measures how fast a repository reads: open time, the median and p99 of 20,000 random
//! `get`s of stored keys (warm page cache), and a full `blobs()` walk. One JSON line per
//! repository.
//!
//! Usage: `cargo run --release -p quincunx-store --example read_speed -- <repo>...`

use std::time::Instant;

use quincunx_store::Repository;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let inputs: Vec<String> = std::env::args().skip(1).collect();
    if inputs.is_empty() {
        return Err("usage: read_speed <repo>...".into());
    }
    for input in &inputs {
        let started = Instant::now();
        let repo = Repository::open(input)?;
        let open_ms = started.elapsed().as_secs_f64() * 1e3;
        let started = Instant::now();
        let mut keys = Vec::new();
        let mut bytes = 0usize;
        for kv in repo.blobs() {
            let (k, v) = kv?;
            bytes += v.len();
            keys.push(k);
        }
        let walk_ms = started.elapsed().as_secs_f64() * 1e3;
        // xorshift: fixed seed, no dependency.
        let mut x = 0x9e37_79b9_7f4a_7c15u64;
        let mut times = Vec::with_capacity(20_000);
        for _ in 0..20_000 {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            let key = &keys[(x % keys.len().max(1) as u64) as usize];
            let t = Instant::now();
            let blob = repo.get(key)?;
            times.push(t.elapsed().as_secs_f64() * 1e6);
            std::hint::black_box(blob);
        }
        times.sort_by(f64::total_cmp);
        println!(
            "{{\"repo\":{input:?},\"blobs\":{},\"blob_bytes\":{bytes},\"file_bytes\":{},\"open_ms\":{open_ms:.3},\"walk_ms\":{walk_ms:.2},\"get_median_us\":{:.3},\"get_p99_us\":{:.3}}}",
            keys.len(),
            repo.size_on_disk()?,
            times[times.len() / 2],
            times[times.len() * 99 / 100],
        );
    }
    Ok(())
}
