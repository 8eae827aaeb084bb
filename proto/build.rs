//! Compiles the .proto files with protox (pure Rust, no system protoc) and exports the descriptor
//! set for server reflection.
//!
//! Two passes: the messages and clients with tonic-prost's codec, then the servers alone (into
//! `servers/`, over the messages of the first pass) with [`RequestCodec`](../src/codec.rs), so that
//! a malformed request is the client's error while a client still treats a malformed reply as ours.

use std::path::PathBuf;

use prost::Message;

const PROTOS: [&str; 7] = [
    "proto/spoofwatch/v1/common.proto",
    "proto/spoofwatch/v1/detection.proto",
    "proto/spoofwatch/v1/models.proto",
    "proto/spoofwatch/v1/datasets.proto",
    "proto/spoofwatch/v1/training.proto",
    "proto/spoofwatch/v1/alarms.proto",
    "proto/google/longrunning/operations.proto",
];

fn main() -> Result<(), Box<dyn std::error::Error>> {
    println!("cargo:rerun-if-changed=proto");
    let descriptors = protox::compile(PROTOS, ["proto"])?;
    let out_dir = PathBuf::from(std::env::var("OUT_DIR")?);
    std::fs::write(
        out_dir.join("spoofwatch_descriptor.bin"),
        descriptors.encode_to_vec(),
    )?;
    tonic_prost_build::configure()
        .build_server(false)
        // google.rpc.Status is tonic-types' own message, so rich error details interoperate.
        .extern_path(".google.rpc.Status", "::tonic_types::Status")
        .compile_fds(descriptors.clone())?;

    // The services only: every message is the first pass's.
    let mut services = descriptors;
    for file in &mut services.file {
        file.message_type.clear();
        file.enum_type.clear();
    }
    let servers_dir = out_dir.join("servers");
    std::fs::create_dir_all(&servers_dir)?;
    tonic_prost_build::configure()
        .build_client(false)
        .codec_path("crate::codec::RequestCodec")
        .out_dir(servers_dir)
        .extern_path(".spoofwatch.v1", "crate::spoofwatch::v1")
        .extern_path(".google.longrunning", "crate::google::longrunning")
        .extern_path(".google.rpc.Status", "::tonic_types::Status")
        .compile_fds(services)?;
    Ok(())
}
