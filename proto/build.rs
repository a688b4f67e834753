//! Generates the dronerace.v1 messages and services with a vendored protoc (no system install).

fn main() -> Result<(), Box<dyn std::error::Error>> {
    // SAFETY: build scripts are single-threaded; PROTOC is read by prost-build below.
    unsafe { std::env::set_var("PROTOC", protoc_bin_vendored::protoc_bin_path()?) };
    let out = std::path::PathBuf::from(std::env::var("OUT_DIR")?);
    tonic_prost_build::configure()
        .file_descriptor_set_path(out.join("dronerace_descriptor.bin"))
        .bytes(".dronerace.v1.RolloutPart.data")
        .bytes(".dronerace.v1.WeightsPart.data")
        .compile_protos(&["proto/dronerace/v1/dronerace.proto"], &["proto"])?;
    println!("cargo:rerun-if-changed=proto");
    Ok(())
}
