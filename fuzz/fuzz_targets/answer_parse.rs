//! Package parsing (`quincunx_store::answer::parse`) of arbitrary bytes never panics, and
//! what it returns lies inside the input: the parts are subslices in order, and parsing a
//! carried child's package again behaves the same (recursively, as a client unpacks).
//!
//! Input layout: byte 0 says whether the bytes are parsed as a package or a bare blob;
//! the rest is the answer.

#![no_main]

use libfuzzer_sys::fuzz_target;
use quincunx_store::answer;

fn check(bytes: &[u8], packaged: bool, depth: usize) {
    let Ok(parsed) = answer::parse(bytes, packaged) else {
        return;
    };
    assert!(!parsed.blob.is_empty() && parsed.blob.len() <= bytes.len());
    assert!(parsed.children.len() <= 4);
    let mut last = None;
    for &(i, child) in &parsed.children {
        assert!(i < 4 && last.is_none_or(|l| l < i));
        last = Some(i);
        assert!(child.len() < bytes.len());
        if depth < 8 {
            check(child, true, depth + 1);
        }
    }
}

fuzz_target!(|data: &[u8]| {
    let Some((&mode, rest)) = data.split_first() else {
        return;
    };
    check(rest, mode & 1 == 1, 0);
});
