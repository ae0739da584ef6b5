//! Generates the gRPC server and client code of `proto/mpiflow/v1/mpiflow.proto` (tonic + prost)
//! and its file descriptor set (for gRPC reflection), with the vendored `protoc`. A tensor's
//! `data` is a `bytes::Bytes` (a sample's buffers become it without a copy, and a client decodes
//! it as a view of the received message), and the service's codec is `service::codec::WireCodec`.

use std::path::PathBuf;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    println!("cargo:rerun-if-changed=proto");
    println!("cargo:rerun-if-changed=build.rs");
    let protoc = protoc_bin_vendored::protoc_bin_path()?;
    // build scripts run single-threaded: setting the variable here is sound
    std::env::set_var("PROTOC", protoc);
    let out = PathBuf::from(std::env::var("OUT_DIR")?);
    tonic_prost_build::configure()
        .file_descriptor_set_path(out.join("mpiflow_descriptor.bin"))
        .bytes(".mpiflow.v1.Tensor.data")
        .codec_path("crate::service::codec::WireCodec")
        // the sample streams (StreamSamples, GetSamples) are answered in front of the generated
        // service (`service::server::routes`): its trait gets default methods, so no handler
        // stands for them
        .generate_default_stubs(true)
        .compile_protos(&["proto/mpiflow/v1/mpiflow.proto"], &["proto"])?;
    Ok(())
}
