//! The metadata record the store's integration tests write (the golden file's).

use quincunx_store::{Attribute, Metadata, NodataPolicy};

/// A planar record: m = 6, N = 32, nine levels, no channels, not yet published.
pub fn metadata() -> Metadata {
    Metadata {
        format_version: 0,
        complete: false,
        content_hash: String::new(),
        domain: quincunx_store::Domain::Planar,
        m: 6,
        n: 32,
        levels: 9,
        attribute: Attribute {
            kind: quincunx_store::AttributeKind::Elevation,
            units: "m".into(),
        },
        extent: [65, 65],
        nodata: NodataPolicy {
            source_count: 0,
            handling: quincunx_store::NodataHandling::None,
        },
        georef: None,
        radius_m: None,
        channels: vec![],
        build: serde_json::json!({"tool": "golden"}),
        level_stats: vec![],
        coverage: None,
        inline_max_bytes: None,
        static_export: false,
    }
}
