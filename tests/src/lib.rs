//! End-to-end tests of the quincunx workspace; the tests live in `tests/`. The library
//! holds what a test and a bench both run: an S3-protocol server ([`s3`]).

pub mod s3;
