//! `dronerace.v1`: the gRPC messages and services of every dronerace process, generated from
//! `proto/dronerace/v1/dronerace.proto` with a vendored protoc. What travels in them and how is
//! the `transport` crate's.

/// Generated messages, clients and servers of package `dronerace.v1`.
#[allow(missing_docs, clippy::all)]
pub mod v1 {
    tonic::include_proto!("dronerace.v1");
}

/// Encoded file descriptors, for gRPC reflection.
pub const FILE_DESCRIPTOR_SET: &[u8] = tonic::include_file_descriptor_set!("dronerace_descriptor");
