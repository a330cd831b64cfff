//! Compiles `proto/hac/v1/*.proto` (server and client code) into `OUT_DIR` and writes the file
//! descriptor set next to it for gRPC reflection.
//!
//! protoc comes from the `protoc-bin-vendored` crate so that a fresh machine needs no system
//! install; `PROTOC` still overrides it (for a platform the vendored binaries do not cover). The
//! path is handed to prost-build directly rather than through `std::env::set_var`, which is
//! `unsafe` in edition 2024 and the workspace forbids unsafe code.

use std::path::PathBuf;

/// The status messages derive `serde::Serialize`, so that `hac status --json` prints them as
/// they travel.
const SERIALIZED: [&str; 9] = [
    "hac.v1.NodeStatus",
    "hac.v1.NodeStatus.node",
    "hac.v1.LearnerStatus",
    "hac.v1.LevelStatus",
    "hac.v1.RejectCount",
    "hac.v1.RegisteredActor",
    "hac.v1.EvaluationPoint",
    "hac.v1.ActorStatus",
    "hac.v1.WalStatus",
];

const PROTOS: [&str; 3] = [
    "hac/v1/transitions.proto",
    "hac/v1/learner.proto",
    "hac/v1/status.proto",
];

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let manifest_dir =
        PathBuf::from(std::env::var_os("CARGO_MANIFEST_DIR").ok_or("no CARGO_MANIFEST_DIR")?);
    let out_dir = PathBuf::from(std::env::var_os("OUT_DIR").ok_or("no OUT_DIR")?);
    let proto_root = manifest_dir.join("../../proto");
    let protos: Vec<PathBuf> = PROTOS.iter().map(|p| proto_root.join(p)).collect();

    let protoc = match std::env::var_os("PROTOC") {
        Some(path) => PathBuf::from(path),
        None => protoc_bin_vendored::protoc_bin_path()?,
    };
    let mut config = tonic_prost_build::Config::new();
    config.protoc_executable(protoc);

    let mut builder = tonic_prost_build::configure();
    for path in SERIALIZED {
        builder = builder.type_attribute(path, "#[derive(serde::Serialize)]");
    }
    builder
        .type_attribute(
            "hac.v1.NodeStatus.node",
            "#[serde(rename_all = \"snake_case\")]",
        )
        // `{"learner": {...}}` rather than `{"node": {"learner": {...}}}`.
        .field_attribute("hac.v1.NodeStatus.node", "#[serde(flatten)]")
        .build_server(true)
        .build_client(true)
        .file_descriptor_set_path(out_dir.join("hac_v1_descriptor.bin"))
        .compile_with_config(config, &protos, std::slice::from_ref(&proto_root))?;

    println!("cargo:rerun-if-env-changed=PROTOC");
    for proto in &protos {
        println!("cargo:rerun-if-changed={}", proto.display());
    }
    Ok(())
}
