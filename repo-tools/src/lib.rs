//! The library behind the `quincunx` command line: input readers, the mapping between
//! codec output and repositories, planet resampling, and the commands themselves.
//!
//! Invariants: nothing here panics on bad input (files, repositories, options); every
//! failure is an `anyhow` error naming the file or option, and the binary exits with 1.

pub mod build;
pub mod export;
pub mod info;
pub mod input;
pub mod layout;
pub mod planet;
pub mod progress;
pub mod query;
pub mod verify;
