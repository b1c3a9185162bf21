//! End-to-end tests of the quincunx workspace; everything lives in `tests/`. This library
//! is empty: it only gives the package a target so the integration tests have a home.
