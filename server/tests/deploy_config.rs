//! The shipped deployment config must parse and validate, so `deploy/` never drifts from the code.

#[test]
fn deploy_server_toml_is_valid() {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../deploy/server.toml");
    let text = std::fs::read_to_string(path).expect("deploy/server.toml exists");
    let config = server::ServerConfig::from_toml(&text).expect("deploy/server.toml parses");
    config.validate().expect("deploy/server.toml is valid");
    assert_eq!(config.sites.len(), 1);
    assert_eq!(config.sites[0].robots.len(), 2);
}
