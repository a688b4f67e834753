//! The wire between dronerace's processes: the rollout and weights transports (iceoryx2 on one
//! machine, gRPC across machines, memory within one process) with their admission checks and
//! limits, TLS and tokens, track and message conversion, the gRPC adapters of the task
//! controller (`task_grpc`, `task_client`), the learner (`grpc_link`) and a served policy
//! (`pilot_grpc`), health and reflection, and the transports' benchmark. The messages and
//! services themselves are the `proto` crate's, generated from `proto/dronerace/v1`.

pub mod bench;
pub mod board;
pub mod budget;
pub mod chunking;
pub mod convert;
pub mod grpc_link;
pub mod link;
pub mod listener;
pub mod memory;
pub mod pilot_grpc;
pub mod refusal;
pub mod security;
pub mod shm;
pub mod task_client;
pub mod task_grpc;

pub use link::{ActorLink, Admission, Delivery, LearnerLink, LearnerStatus, LinkError, Received, Refusal, Transport, WeightsUpdate};
pub use security::{NetworkConfig, Security, SecurityError};

/// Fully-qualified names of the discovery services every dronerace server offers beside its own.
pub const DISCOVERY_SERVICES: [&str; 3] =
    ["grpc.health.v1.Health", "grpc.reflection.v1.ServerReflection", "grpc.reflection.v1alpha.ServerReflection"];

/// `server` with gRPC health (each of `serving` reported SERVING) and server reflection in
/// both versions — v1, and v1alpha, which grpcio-reflection and older grpcurl speak — each
/// listing exactly what this server serves: `serving` and the discovery services. Reflection
/// answers only requests that pass `token` (it describes the whole API); health answers
/// anyone, as probes carry no token. Add the server's own services to the returned router.
#[allow(clippy::expect_used, reason = "the compiled-in descriptor sets are valid")]
pub async fn with_discovery(
    mut server: tonic::transport::Server,
    serving: &[&str],
    token: security::TokenCheck,
) -> tonic::transport::server::Router {
    let (reporter, health) = tonic_health::server::health_reporter();
    for name in serving {
        reporter.set_service_status(*name, tonic_health::ServingStatus::Serving).await;
    }
    let builder = || {
        let mut b = tonic_reflection::server::Builder::configure()
            .register_encoded_file_descriptor_set(proto::FILE_DESCRIPTOR_SET)
            .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
            .register_encoded_file_descriptor_set(tonic_reflection::pb::v1::FILE_DESCRIPTOR_SET)
            .register_encoded_file_descriptor_set(tonic_reflection::pb::v1alpha::FILE_DESCRIPTOR_SET)
            .include_reflection_service(false);
        for name in serving.iter().chain(&DISCOVERY_SERVICES) {
            b = b.with_service_name(*name);
        }
        b
    };
    let v1 = builder().build_v1().expect("the compiled-in descriptor sets are valid");
    let v1alpha = builder().build_v1alpha().expect("the compiled-in descriptor sets are valid");
    use tonic::service::interceptor::InterceptedService;
    server.add_service(health).add_service(InterceptedService::new(v1, token.clone())).add_service(InterceptedService::new(v1alpha, token))
}

/// Serves gRPC health alone, in plaintext, on `listener` (each of `serving` SERVING) until
/// `shutdown`: for probes that cannot speak TLS — Kubernetes' native gRPC probes — beside a
/// server that only speaks TLS. It tells whoever asks that the process is up, nothing more.
pub async fn serve_health(
    listener: tokio::net::TcpListener,
    serving: &[&str],
    shutdown: impl std::future::Future<Output = ()>,
) -> Result<(), tonic::transport::Error> {
    let (reporter, health) = tonic_health::server::health_reporter();
    for name in serving {
        reporter.set_service_status(*name, tonic_health::ServingStatus::Serving).await;
    }
    tonic::transport::Server::builder()
        .timeout(security::REQUEST_TIMEOUT)
        .max_concurrent_streams(security::STREAMS_PER_CONNECTION)
        .add_service(health)
        .serve_with_incoming_shutdown(listener::incoming(listener), shutdown)
        .await
}

#[cfg(test)]
mod tests {
    use super::*;
    use tokio_stream::StreamExt;

    /// The services a reflection client of either version lists.
    async fn listed(addr: std::net::SocketAddr) -> (Vec<String>, Vec<String>) {
        use tonic_reflection::pb::{v1, v1alpha};
        let channel = tonic::transport::Endpoint::from_shared(format!("http://{addr}")).unwrap().connect().await.unwrap();
        let mut client = v1::server_reflection_client::ServerReflectionClient::new(channel.clone());
        let request = v1::ServerReflectionRequest {
            host: String::new(),
            message_request: Some(v1::server_reflection_request::MessageRequest::ListServices(String::new())),
        };
        let mut stream = client.server_reflection_info(tokio_stream::iter([request])).await.unwrap().into_inner();
        let Some(v1::server_reflection_response::MessageResponse::ListServicesResponse(list)) =
            stream.next().await.unwrap().unwrap().message_response
        else {
            panic!("v1: not a service list")
        };
        let v1_names = list.service.into_iter().map(|s| s.name).collect();
        let mut client = v1alpha::server_reflection_client::ServerReflectionClient::new(channel);
        let request = v1alpha::ServerReflectionRequest {
            host: String::new(),
            message_request: Some(v1alpha::server_reflection_request::MessageRequest::ListServices(String::new())),
        };
        let mut stream = client.server_reflection_info(tokio_stream::iter([request])).await.unwrap().into_inner();
        let Some(v1alpha::server_reflection_response::MessageResponse::ListServicesResponse(list)) =
            stream.next().await.unwrap().unwrap().message_response
        else {
            panic!("v1alpha: not a service list")
        };
        (v1_names, list.service.into_iter().map(|s| s.name).collect())
    }

    /// Reflection describes the whole API: behind a token it answers only with the token,
    /// while health still answers a probe that carries none.
    #[tokio::test]
    async fn reflection_needs_the_token_and_health_does_not() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("token"), "s3cret\n").unwrap();
        let config = NetworkConfig { token_file: Some(dir.path().join("token")), ..NetworkConfig::default() };
        let security = Security::load(&config).unwrap();
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        let router = with_discovery(security.server().unwrap(), &["dronerace.v1.TaskController"], security.token_check()).await;
        tokio::spawn(router.serve_with_incoming(listener::incoming(listener)));
        let channel = tonic::transport::Endpoint::from_shared(format!("http://{addr}")).unwrap().connect().await.unwrap();
        let health = tonic_health::pb::health_client::HealthClient::new(channel.clone())
            .check(tonic_health::pb::HealthCheckRequest { service: "dronerace.v1.TaskController".into() })
            .await
            .unwrap();
        assert_eq!(health.into_inner().status, tonic_health::pb::health_check_response::ServingStatus::Serving as i32);
        use tonic_reflection::pb::v1;
        let list = || v1::ServerReflectionRequest {
            host: String::new(),
            message_request: Some(v1::server_reflection_request::MessageRequest::ListServices(String::new())),
        };
        let mut client = v1::server_reflection_client::ServerReflectionClient::new(channel.clone());
        let refused = client.server_reflection_info(tokio_stream::iter([list()])).await.unwrap_err();
        assert_eq!(refused.code(), tonic::Code::Unauthenticated, "{refused:?}");
        let mut request = tonic::Request::new(tokio_stream::iter([list()]));
        request.metadata_mut().insert("authorization", "Bearer s3cret".parse().unwrap());
        let mut answers = client.server_reflection_info(request).await.unwrap().into_inner();
        assert!(answers.next().await.unwrap().is_ok(), "with the token, reflection answers");
    }

    #[tokio::test]
    async fn both_reflection_versions_list_exactly_what_the_server_serves() {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        let router =
            with_discovery(tonic::transport::Server::builder(), &["dronerace.v1.TaskController"], Security::default().token_check()).await;
        tokio::spawn(router.serve_with_incoming(tokio_stream::wrappers::TcpListenerStream::new(listener)));
        let (v1, v1alpha) = listed(addr).await;
        let mut expected: Vec<String> = ["dronerace.v1.TaskController"].iter().chain(&DISCOVERY_SERVICES).map(|s| s.to_string()).collect();
        expected.sort();
        for (version, mut names) in [("v1", v1), ("v1alpha", v1alpha)] {
            names.sort();
            assert_eq!(names, expected, "reflection {version}");
        }
    }
}
