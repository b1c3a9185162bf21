//! The end-to-end tests: one module per file of this folder, in one test binary (one
//! link of the whole workspace instead of one per file). Run one file's tests with its
//! module as the filter, e.g. `cargo test --release --test e2e -- web::`.

mod common;

mod buckets;
mod colour;
mod dependencies;
mod docker_files;
mod https;
mod image_error;
mod nginx_cache;
mod packages;
mod planet;
mod range_proxy;
mod range_reads;
mod render_images;
mod s3;
mod session;
mod web;
mod web_ranges;
