//! Responses are untrusted: the pipelined HTTP/1.1 client (`quincunx_client::fetch`, also
//! used by `quincunx loadtest`) must split any byte stream into responses or return `Err`, never
//! panic, never buffer past its limits. The first byte picks how the stream is chunked.
#![no_main]

use libfuzzer_sys::fuzz_target;
use quincunx_client::fetch::http1::{Limits, ResponseDecoder};

fuzz_target!(|data: &[u8]| {
    let Some((&chunk, stream)) = data.split_first() else {
        return;
    };
    let limits = Limits {
        max_head_bytes: 4096,
        max_body_bytes: 1 << 16,
    };
    let mut decoder = ResponseDecoder::new(limits);
    for piece in stream.chunks(usize::from(chunk).max(1)) {
        if decoder.extend(piece).is_err() {
            return;
        }
        loop {
            match decoder.decode() {
                Ok(Some(response)) => {
                    assert!(response.body.len() <= limits.max_body_bytes);
                    assert!(response.status < 1000);
                }
                Ok(None) => break,
                Err(_) => return,
            }
        }
        assert!(decoder.buffered() <= limits.max_head_bytes + limits.max_body_bytes + piece.len());
    }
});
