//! The `quincunx` command line.
mod input;
fn main() {}
