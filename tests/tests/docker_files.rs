//! The shipped container files agree with the server: `docker/server.toml` is a valid
//! configuration, and it serves from the `/data` volume on the port the image exposes.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use crate::common;

use quincunx_server::ServerConfig;

#[test]
fn shipped_server_config_is_valid_and_serves_the_data_volume_on_8080() {
    let path = common::workspace_root().join("docker/server.toml");
    let text = std::fs::read_to_string(&path).unwrap();
    let config = ServerConfig::from_toml(&text, &path).unwrap();
    config.check().unwrap();
    assert_eq!(config.addr.port(), 8080);
    assert!(
        config.addr.ip().is_unspecified(),
        "replicas listen on all interfaces"
    );
    assert!(!config.repos.is_empty());
    for repo in &config.repos {
        assert!(repo.path.starts_with("/data"), "{}", repo.path.display());
    }
}

#[test]
fn dockerfile_exposes_the_configured_port_and_checks_health_with_the_shipped_script() {
    let dockerfile =
        std::fs::read_to_string(common::workspace_root().join("docker/Dockerfile")).unwrap();
    assert!(dockerfile.lines().any(|l| l.trim() == "EXPOSE 8080"));
    assert!(dockerfile.contains("docker/healthcheck.sh"));
    assert!(dockerfile.contains("/etc/quincunx/server.toml"));
}
