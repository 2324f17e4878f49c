//! Compiles `evermap/fleet/v1/*.proto` with protox (pure Rust, no system `protoc`) and generates the prost
//! messages and tonic services, plus the encoded file descriptor set that gRPC reflection serves.

use std::path::PathBuf;

use prost::Message as _;

const PROTOS: [&str; 7] = [
    "evermap/fleet/v1/common.proto",
    "evermap/fleet/v1/agent_service.proto",
    "evermap/fleet/v1/map_service.proto",
    "evermap/fleet/v1/site_log.proto",
    "evermap/fleet/v1/site_checkpoint.proto",
    "evermap/fleet/v1/site_summary.proto",
    "evermap/fleet/v1/zenoh_link.proto",
];

fn main() -> Result<(), Box<dyn std::error::Error>> {
    for proto in PROTOS {
        println!("cargo:rerun-if-changed={proto}");
    }
    let descriptors = protox::compile(PROTOS, ["."])?;
    let out_dir = PathBuf::from(std::env::var("OUT_DIR")?);
    std::fs::write(
        out_dir.join("evermap_fleet_v1_descriptor.bin"),
        descriptors.encode_to_vec(),
    )?;
    tonic_prost_build::configure()
        .build_client(true)
        .build_server(true)
        .compile_fds(descriptors)?;
    Ok(())
}
