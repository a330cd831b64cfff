//! What every hac gRPC server carries besides its own service: the standard health service
//! ([`Health`]), server reflection (v1 and v1alpha), the token check ([`AuthLayer`]) and TLS
//! ([`router`], [`serve_router`]: the learner's server in `hac-serve` is built on them too);
//! and [`serve_status`], the small server of an actor daemon (status, health, reflection).

use std::future::Future;
use std::sync::Arc;
use std::time::Duration;

use tokio::net::TcpListener;
use tokio::sync::watch;
use tonic::transport::server::{Router, TcpIncoming};
use tonic_health::ServingStatus;
use tonic_health::pb::health_server::HealthServer;
use tonic_health::server::{HealthReporter, HealthService};
use tower::layer::util::{Identity, Stack};

use super::malformed::RefuseUndecodable;
use super::status::{StatusGrpc, StatusSource};
use crate::security::{AuthLayer, ServerTls, Token};

/// The learner service's name (health, reflection).
pub const LEARNER_SERVICE: &str = "hac.v1.Learner";
/// The status service's name (health, reflection).
pub const STATUS_SERVICE: &str = "hac.v1.Status";
const HEALTH_SERVICE: &str = "grpc.health.v1.Health";
const REFLECTION_SERVICES: [&str; 2] = [
    "grpc.reflection.v1.ServerReflection",
    "grpc.reflection.v1alpha.ServerReflection",
];

/// Who may talk to a server, and over what.
#[derive(Debug, Clone, Default)]
pub struct ServerSecurity {
    /// Required on every RPC but health, when set.
    pub token: Option<Token>,
    /// TLS on every connection, when set.
    pub tls: Option<ServerTls>,
}

/// The `grpc.health.v1.Health` statuses of one server: the whole server (`""`) and its main
/// service move together, `NOT_SERVING` from creation until [`set_serving`](Self::set_serving).
/// Cheap to clone; every clone reports to the same service.
#[derive(Debug, Clone)]
pub struct Health {
    reporter: HealthReporter,
    names: Vec<&'static str>,
}

impl Health {
    /// Statuses for `""` and `service`, both `NOT_SERVING`.
    pub async fn new(service: &'static str) -> Self {
        let health = Self {
            reporter: HealthReporter::new(),
            names: vec!["", service],
        };
        health.set_serving(false).await;
        health
    }

    /// `SERVING` (ready) or `NOT_SERVING` (starting, draining).
    pub async fn set_serving(&self, serving: bool) {
        let status = if serving {
            ServingStatus::Serving
        } else {
            ServingStatus::NotServing
        };
        for name in &self.names {
            self.reporter.set_service_status(name, status).await;
        }
    }

    fn service(&self) -> HealthServer<HealthService> {
        HealthServer::new(HealthService::from_health_reporter(self.reporter.clone()))
    }
}

/// A server with `security` applied (TLS if configured, and the token check, which calls
/// `on_refused` for each request it refuses) and health (reported by `health`) and reflection
/// (advertising `services`, health and reflection) added; the caller adds its own services.
pub fn router(
    security: &ServerSecurity,
    on_refused: Option<Arc<dyn Fn() + Send + Sync>>,
    health: &Health,
    services: &[&str],
) -> Result<Router<Stack<AuthLayer, Identity>>, tonic::transport::Error> {
    let mut builder = tonic::transport::Server::builder();
    if let Some(tls) = &security.tls {
        builder = builder.tls_config(tls.config())?;
    }
    let mut auth = AuthLayer::new(security.token.clone());
    if let Some(f) = on_refused {
        auth = auth.on_refused(move || f());
    }
    let (v1, v1alpha) = reflection(services);
    Ok(builder
        .layer(auth)
        .add_service(health.service())
        .add_service(v1)
        .add_service(v1alpha))
}

/// Serves `router` on `listener` until `shutdown` completes; then stops accepting connections
/// and waits up to `drain_timeout` for the open ones to close.
pub async fn serve_router(
    router: Router<Stack<AuthLayer, Identity>>,
    listener: TcpListener,
    drain_timeout: Duration,
    shutdown: impl Future<Output = ()>,
) -> Result<(), tonic::transport::Error> {
    let (drain_tx, mut drain_rx) = watch::channel(false);
    let signal = async move {
        shutdown.await;
        drain_tx.send_replace(true);
    };
    let incoming = TcpIncoming::from(listener).with_nodelay(Some(true));
    let server = router.serve_with_incoming_shutdown(incoming, signal);
    let drained = async move {
        // The sender lives in the server future, which this races with: an error here means
        // that future is gone, and the select has already finished.
        if drain_rx.wait_for(|&draining| draining).await.is_ok() {
            tokio::time::sleep(drain_timeout).await;
        } else {
            std::future::pending::<()>().await;
        }
    };
    tokio::select! {
        result = server => result,
        () = drained => {
            tracing::warn!(timeout = ?drain_timeout, "connections still open after the drain timeout");
            Ok(())
        }
    }
}

/// The reflection services (v1 and v1alpha) advertising `services` plus health and reflection,
/// able to describe every hac, health and reflection message.
pub(crate) fn reflection(
    services: &[&str],
) -> (
    tonic_reflection::server::v1::ServerReflectionServer<
        impl tonic_reflection::server::v1::ServerReflection,
    >,
    tonic_reflection::server::v1alpha::ServerReflectionServer<
        impl tonic_reflection::server::v1alpha::ServerReflection,
    >,
) {
    let configure = || {
        let mut builder = tonic_reflection::server::Builder::configure()
            .register_encoded_file_descriptor_set(hac_proto::FILE_DESCRIPTOR_SET)
            .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
            .register_encoded_file_descriptor_set(tonic_reflection::pb::v1::FILE_DESCRIPTOR_SET)
            .register_encoded_file_descriptor_set(
                tonic_reflection::pb::v1alpha::FILE_DESCRIPTOR_SET,
            );
        let names = services
            .iter()
            .copied()
            .chain([HEALTH_SERVICE])
            .chain(REFLECTION_SERVICES);
        for name in names {
            builder = builder.with_service_name(name);
        }
        builder
    };
    // The descriptor sets are compiled in; failing to read them is a build defect.
    let v1 = configure()
        .build_v1()
        .expect("the compiled descriptor sets are valid");
    let v1alpha = configure()
        .build_v1alpha()
        .expect("the compiled descriptor sets are valid");
    (v1, v1alpha)
}

/// Serves `source` as `hac.v1.Status`, with health (reported by `health`, which the caller
/// moves between serving and not) and reflection, on `listener` until `shutdown` completes;
/// then reports `NOT_SERVING`, ends the watch streams, stops accepting and waits up to
/// `drain_timeout` for connections to close. An actor daemon's own status endpoint.
pub async fn serve_status(
    source: Arc<dyn StatusSource>,
    listener: TcpListener,
    security: &ServerSecurity,
    health: Health,
    drain_timeout: Duration,
    shutdown: impl Future<Output = ()>,
) -> Result<(), tonic::transport::Error> {
    let (closing_tx, closing) = watch::channel(false);
    let status = StatusGrpc::new(source, closing);
    let router = router(security, None, &health, &[STATUS_SERVICE])?
        .add_service(RefuseUndecodable::new(status.into_service(), None));
    let signal = async move {
        shutdown.await;
        health.set_serving(false).await;
        closing_tx.send_replace(true);
    };
    serve_router(router, listener, drain_timeout, signal).await
}
