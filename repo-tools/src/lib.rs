//! The library behind the `quincunx` command line: input readers, the mapping between
//! codec output and repositories, planet resampling, and the commands themselves.
//!
//! Invariants: nothing here panics on bad input (files, repositories, options); every
//! failure is an `anyhow` error naming the file or option, and the binary exits with 1.

/// `println!` that ends the process quietly when stdout is closed (`quincunx info | head`)
/// instead of panicking on the broken pipe.
#[macro_export]
macro_rules! outln {
    ($($arg:tt)*) => {{
        use std::io::Write as _;
        if let Err(e) = writeln!(std::io::stdout(), $($arg)*) {
            if e.kind() == std::io::ErrorKind::BrokenPipe {
                std::process::exit(0);
            }
        }
    }};
}

pub mod args;
pub mod bounds;
pub mod build;
pub mod demo;
pub mod export;
pub mod fly;
#[cfg(feature = "render")]
mod fly_render;
pub mod info;
pub mod input;
pub mod layout;
pub mod loadtest;
pub mod mosaic;
pub mod planet;
#[cfg(feature = "charts")]
pub mod plot;
pub mod preview;
pub mod progress;
pub mod query;
#[cfg(feature = "render")]
pub mod render;
pub mod rows;
pub mod shard;
#[cfg(feature = "render")]
pub mod trade;
pub mod verify;
#[cfg(feature = "render")]
pub mod view;
