//! `dronerace.v1`: the gRPC messages and services (generated from `proto/dronerace/v1`), and
//! everything both ends of a connection must agree on: track conversion, the rollout/weights
//! transports (iceoryx2 on one machine, gRPC across machines, memory within one process), message limits, TLS and tokens.

pub mod board;
pub mod chunking;
pub mod convert;
pub mod grpc_link;
pub mod memory;
pub mod security;
pub mod shm;
pub mod transport;

/// Generated messages, clients and servers of package `dronerace.v1`.
#[allow(missing_docs, clippy::all)]
pub mod v1 {
    tonic::include_proto!("dronerace.v1");
}

/// Encoded file descriptors, for gRPC reflection.
pub const FILE_DESCRIPTOR_SET: &[u8] = tonic::include_file_descriptor_set!("dronerace_descriptor");

pub use security::{NetworkConfig, Security, SecurityError};
pub use transport::{ActorLink, Admission, Delivery, LearnerLink, LearnerStatus, LinkError, Received, Refusal, WeightsUpdate};

/// gRPC health and reflection services for a server whose own services are `serving`.
#[allow(clippy::expect_used, reason = "the compiled-in descriptor set is valid")]
pub async fn health_and_reflection(
    serving: &[&str],
) -> (
    tonic_health::pb::health_server::HealthServer<impl tonic_health::pb::health_server::Health>,
    tonic_reflection::server::v1::ServerReflectionServer<impl tonic_reflection::server::v1::ServerReflection>,
) {
    let (reporter, health) = tonic_health::server::health_reporter();
    for name in serving {
        reporter.set_service_status(*name, tonic_health::ServingStatus::Serving).await;
    }
    let reflection = tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(FILE_DESCRIPTOR_SET)
        .build_v1()
        .expect("the compiled-in descriptor set is valid");
    (health, reflection)
}
