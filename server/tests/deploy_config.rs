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

/// The router's access control knows every robot of the deployed server (by its certificate's CN
/// `<site>/<robot id>`) and the server itself; the file is a valid zenoh configuration.
#[test]
fn deploy_router_config_lets_every_deployed_robot_reach_its_site() {
    let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/../deploy");
    let router = format!("{dir}/zenohd.json5");
    zenoh::Config::from_file(&router).expect("deploy/zenohd.json5 is a zenoh configuration");
    let text = std::fs::read_to_string(&router).expect("deploy/zenohd.json5 exists");
    assert!(text.contains("\"evermap-server\""));
    let server = std::fs::read_to_string(format!("{dir}/server.toml")).expect("server.toml");
    let config = server::ServerConfig::from_toml(&server).expect("server.toml parses");
    for site in &config.sites {
        assert!(
            text.contains(&format!("\"evermap/{}/api\"", site.id)),
            "{}",
            site.id
        );
        for robot in &site.robots {
            let cn = format!("\"{}/{}\"", site.id, robot.id);
            assert!(
                text.contains(&cn),
                "no access for {cn} in deploy/zenohd.json5"
            );
        }
    }
}
