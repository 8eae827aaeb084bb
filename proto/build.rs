//! Compiles the .proto files with protox (pure Rust, no system protoc) and exports the descriptor
//! set for server reflection.

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
        // google.rpc.Status is tonic-types' own message, so rich error details interoperate.
        .extern_path(".google.rpc.Status", "::tonic_types::Status")
        .compile_fds(descriptors)?;
    Ok(())
}
