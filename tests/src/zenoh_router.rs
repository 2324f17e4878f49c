//! A zenoh router in process, for the zenoh integration tests.

/// A zenoh router on `port` (TCP, loopback, no scouting): a `zenohd` in process.
pub async fn zenoh_router(port: u16) -> zenoh::Session {
    let mut config = zenoh::Config::default();
    for (key, value) in [
        ("mode", "\"router\"".to_owned()),
        ("listen/endpoints", format!("[\"tcp/127.0.0.1:{port}\"]")),
        ("scouting/multicast/enabled", "false".to_owned()),
        ("scouting/gossip/enabled", "false".to_owned()),
    ] {
        config
            .insert_json5(key, &value)
            .expect("a valid router configuration");
    }
    zenoh::open(config).await.expect("open the zenoh router")
}
