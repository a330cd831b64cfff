//! The operations side of the gRPC transport over loopback: the status service (once and
//! watched), health through a run's end, reflection, Prometheus metrics, the bearer token on
//! every service but health, TLS, and the per-actor message rate limit.

use crate::common;

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::{Duration, Instant};

use common::{batch_item, episode, link_options, run_config, runtime};

use hac_learner::{Learner, LearnerOptions, RejectReason};
use hac_proto::{ActorRole, Registration, pb};
use hac_serve::grpc::{ServerOptions, serve};
use hac_serve::metrics::learner_metrics;
use hac_transport::grpc::{
    ActorNodeStatus, GrpcLink, GrpcLinkOptions, Health, STATUS_SERVICE, ServerSecurity,
    StatusSource, reject_reason, serve_status,
};
use hac_transport::metrics::serve_metrics;
use hac_transport::security::{BearerToken, ClientTls, ServerTls, Token, endpoint};
use hac_transport::{ActorLink, IngestSink, LinkError};
use tokio::io::{AsyncReadExt as _, AsyncWriteExt as _};
use tokio::sync::oneshot;
use tonic::Code;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::Channel;
use tonic_health::pb::health_check_response::ServingStatus;
use tonic_health::pb::{HealthCheckRequest, health_client::HealthClient};
use tonic_reflection::pb::v1::ServerReflectionRequest;
use tonic_reflection::pb::v1::server_reflection_client::ServerReflectionClient;
use tonic_reflection::pb::v1::server_reflection_request::MessageRequest;
use tonic_reflection::pb::v1::server_reflection_response::MessageResponse;

const WAIT: Duration = Duration::from_secs(20);

fn start_learner(options: impl FnOnce(&mut LearnerOptions)) -> Arc<Learner> {
    let run = run_config();
    let mut learner_options = LearnerOptions::for_run(&run);
    options(&mut learner_options);
    Arc::new(Learner::start(run, learner_options).unwrap())
}

/// A learner server on an ephemeral loopback port.
struct Server {
    addr: SocketAddr,
    stop: oneshot::Sender<()>,
    done: tokio::task::JoinHandle<Result<(), tonic::transport::Error>>,
}

impl Server {
    async fn start(learner: Arc<Learner>, security: ServerSecurity) -> Self {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        let (stop, stopped) = oneshot::channel::<()>();
        let options = ServerOptions {
            drain_timeout: Duration::from_secs(2),
            security,
            ..ServerOptions::default()
        };
        let done = tokio::spawn(serve(learner, listener, options, async {
            let _ = stopped.await;
        }));
        Self { addr, stop, done }
    }

    async fn stop(self) {
        let _ = self.stop.send(());
        tokio::time::timeout(WAIT, self.done)
            .await
            .expect("the server drains in time")
            .unwrap()
            .unwrap();
    }
}

type Authed = InterceptedService<Channel, BearerToken>;

async fn channel(url: &str, tls: Option<&ClientTls>, token: Option<&Token>) -> Authed {
    let channel = endpoint(url, tls).unwrap().connect().await.unwrap();
    InterceptedService::new(channel, BearerToken(token.cloned()))
}

fn registration(actor_id: &str) -> Registration {
    Registration {
        actor_id: actor_id.into(),
        role: ActorRole::Trainer,
        hostname: "test".into(),
        transports: vec!["grpc".into()],
    }
}

async fn health(channel: Authed, service: &str) -> Result<ServingStatus, tonic::Status> {
    let response = HealthClient::new(channel)
        .check(HealthCheckRequest {
            service: service.into(),
        })
        .await?;
    Ok(ServingStatus::try_from(response.into_inner().status).unwrap())
}

async fn list_services(channel: Authed) -> Result<Vec<String>, tonic::Status> {
    let request = ServerReflectionRequest {
        host: String::new(),
        message_request: Some(MessageRequest::ListServices(String::new())),
    };
    let mut responses = ServerReflectionClient::new(channel)
        .server_reflection_info(tokio_stream::iter([request]))
        .await?
        .into_inner();
    let response = responses.message().await?.expect("one answer");
    let Some(MessageResponse::ListServicesResponse(list)) = response.message_response else {
        panic!("a service list, got {response:?}");
    };
    let mut names: Vec<String> = list.service.into_iter().map(|s| s.name).collect();
    names.sort();
    Ok(names)
}

fn learner_of(status: pb::NodeStatus) -> pb::LearnerStatus {
    match status.node {
        Some(pb::node_status::Node::Learner(l)) => l,
        other => panic!("a learner status, got {other:?}"),
    }
}

#[test]
fn status_reports_what_was_ingested_and_a_watch_streams_it() {
    let runtime = runtime();
    let learner = start_learner(|_| {});
    let server = runtime.block_on(Server::start(learner.clone(), ServerSecurity::default()));
    let url = format!("http://{}", server.addr);
    let mut link = GrpcLink::connect(&url, link_options()).unwrap();
    link.register(&registration("trainer-0")).unwrap();
    for _ in 0..3 {
        link.send(batch_item(&learner, 0, 64)).unwrap();
        link.send(batch_item(&learner, 1, 16)).unwrap();
        link.send(episode()).unwrap();
    }
    link.flush(WAIT).unwrap();

    runtime.block_on(async {
        let mut client = pb::status_client::StatusClient::new(channel(&url, None, None).await);
        let status = learner_of(
            client
                .get_status(pb::GetStatusRequest::default())
                .await
                .unwrap()
                .into_inner(),
        );
        assert_eq!(status.state, "serving");
        assert_eq!((status.env.as_str(), status.levels), ("mountain-car", 2));
        assert_eq!(status.algo, "hac");
        assert_eq!((status.batches, status.episodes), (6, 3));
        assert_eq!(status.transitions, 3 * (64 + 16));
        assert_eq!(status.env_steps, 30);
        assert!(status.transitions_per_second > 0.0, "{status:?}");
        assert_eq!(status.level_status.len(), 2);
        for (level, l) in status.level_status.iter().enumerate() {
            assert_eq!(l.level as usize, level);
            assert_eq!(l.shard_sizes.len(), 2, "two shards");
            assert_eq!(l.shard_sizes.iter().sum::<u64>(), l.replay_size);
            assert_eq!(l.replay_size, [192, 48][level]);
            assert!(l.replay_size <= l.replay_capacity);
        }
        assert_eq!(status.rejected.len(), RejectReason::ALL.len());
        assert!(status.rejected.iter().all(|r| r.count == 0));
        let [actor] = status.actors.as_slice() else {
            panic!("one actor: {:?}", status.actors);
        };
        assert_eq!(actor.actor_id, "trainer-0");
        assert_eq!(
            (actor.role.as_str(), actor.transport.as_str()),
            ("trainer", "grpc")
        );
        assert_eq!((actor.episodes, actor.env_steps), (3, 30));
        assert_eq!(
            actor.weights_lag,
            status.weights_version - actor.weights_version
        );

        // A watch: snapshots at the interval asked for, counters never going back.
        let mut watch = client
            .watch_status(pb::WatchStatusRequest {
                interval_ms: 100,
                max_evaluations: 0,
            })
            .await
            .unwrap()
            .into_inner();
        let mut last_version = 0;
        for _ in 0..3 {
            let snapshot = tokio::time::timeout(WAIT, watch.message())
                .await
                .unwrap()
                .unwrap()
                .unwrap();
            let s = learner_of(snapshot);
            assert!(s.weights_version >= last_version);
            assert_eq!(s.transitions, status.transitions);
            last_version = s.weights_version;
        }
        // The server's shutdown ends the watch.
        server.stop().await;
        let end = tokio::time::timeout(WAIT, watch.message()).await.unwrap();
        assert!(!matches!(end, Ok(Some(_))), "{end:?}");
    });
    drop(link);
}

#[test]
fn health_is_serving_until_the_run_finishes_and_reflection_lists_the_services() {
    let runtime = runtime();
    let learner = start_learner(|_| {});
    runtime.block_on(async {
        let server = Server::start(learner.clone(), ServerSecurity::default()).await;
        let url = format!("http://{}", server.addr);
        for service in ["", "hac.v1.Learner"] {
            assert_eq!(
                health(channel(&url, None, None).await, service)
                    .await
                    .unwrap(),
                ServingStatus::Serving
            );
        }
        let unknown = health(channel(&url, None, None).await, "hac.v1.Other").await;
        assert_eq!(unknown.unwrap_err().code(), Code::NotFound);
        assert_eq!(
            list_services(channel(&url, None, None).await)
                .await
                .unwrap(),
            [
                "grpc.health.v1.Health",
                "grpc.reflection.v1.ServerReflection",
                "grpc.reflection.v1alpha.ServerReflection",
                "hac.v1.Learner",
                "hac.v1.Status",
            ]
        );

        // The run ends: the learner only serves its final weights now.
        learner.finish("test");
        let started = Instant::now();
        loop {
            let status = health(channel(&url, None, None).await, "").await.unwrap();
            if status == ServingStatus::NotServing {
                break;
            }
            assert!(started.elapsed() < WAIT, "still {status:?}");
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        assert_eq!(
            health(channel(&url, None, None).await, "hac.v1.Learner")
                .await
                .unwrap(),
            ServingStatus::NotServing
        );
        let mut client = pb::status_client::StatusClient::new(channel(&url, None, None).await);
        let status = learner_of(
            client
                .get_status(pb::GetStatusRequest::default())
                .await
                .unwrap()
                .into_inner(),
        );
        assert_eq!(status.state, "draining");
        server.stop().await;
    });
}

#[test]
fn health_is_not_serving_while_a_level_fails_and_status_says_why() {
    // A learning rate of 1e30: every update explodes and is undone; after ten in a row the
    // learner is unhealthy (never publishing what the updates made).
    let mut run = run_config();
    run.agent.actor_lr = 1e30;
    run.agent.critic_lr = 1e30;
    run.agent.batch_size = 8;
    let options = LearnerOptions::for_run(&run);
    let learner = Arc::new(Learner::start(run, options).unwrap());
    let runtime = runtime();
    runtime.block_on(async {
        let server = Server::start(learner.clone(), ServerSecurity::default()).await;
        let url = format!("http://{}", server.addr);
        assert_eq!(
            health(channel(&url, None, None).await, "").await.unwrap(),
            ServingStatus::Serving
        );
        let incarnation = learner.register(registration("a")).unwrap().incarnation;
        let mut sequence = 0;
        let started = Instant::now();
        loop {
            for item in [
                batch_item(&learner, 0, 8),
                batch_item(&learner, 1, 8),
                episode(),
            ] {
                sequence += 1;
                learner
                    .ingest(&hac_proto::IngestMessage {
                        actor_id: "a".into(),
                        incarnation,
                        sequence,
                        item,
                    })
                    .unwrap();
            }
            if health(channel(&url, None, None).await, "hac.v1.Learner")
                .await
                .unwrap()
                == ServingStatus::NotServing
            {
                break;
            }
            assert!(started.elapsed() < WAIT, "still serving");
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        let mut client = pb::status_client::StatusClient::new(channel(&url, None, None).await);
        let status = learner_of(
            client
                .get_status(pb::GetStatusRequest::default())
                .await
                .unwrap()
                .into_inner(),
        );
        assert_eq!(status.state, "unhealthy");
        assert!(
            status.trouble.contains("diverged and were undone"),
            "{}",
            status.trouble
        );
        assert!(
            status
                .level_status
                .iter()
                .any(|l| l.diverged_in_a_row >= 10)
        );
        learner.finish("test");
        server.stop().await;
    });
}

/// Every RPC of every service but health, without the token and with a wrong one.
async fn assert_every_rpc_refused(url: &str, tls: Option<&ClientTls>, token: Option<&Token>) {
    let check = |what: &str, result: Result<(), tonic::Status>| {
        let status = result.expect_err(what);
        assert_eq!(status.code(), Code::Unauthenticated, "{what}: {status:?}");
        assert_eq!(
            reject_reason(&status),
            Some(RejectReason::Unauthenticated),
            "{what}"
        );
    };
    let mut learner = pb::learner_client::LearnerClient::new(channel(url, tls, token).await);
    check(
        "register",
        learner
            .register(pb::RegisterRequest::from(registration("intruder")))
            .await
            .map(drop),
    );
    check(
        "ingest",
        learner
            .ingest(tokio_stream::iter(Vec::<pb::IngestRequest>::new()))
            .await
            .map(drop),
    );
    check(
        "watch weights",
        learner
            .watch_weights(pb::WatchWeightsRequest::default())
            .await
            .map(drop),
    );
    check(
        "report evaluation",
        learner
            .report_evaluation(pb::EvaluationReport::default())
            .await
            .map(drop),
    );
    let mut status = pb::status_client::StatusClient::new(channel(url, tls, token).await);
    check(
        "get status",
        status
            .get_status(pb::GetStatusRequest::default())
            .await
            .map(drop),
    );
    check(
        "watch status",
        status
            .watch_status(pb::WatchStatusRequest::default())
            .await
            .map(drop),
    );
    check(
        "reflection",
        list_services(channel(url, tls, token).await)
            .await
            .map(drop),
    );
    // Health needs no token.
    assert_eq!(
        health(channel(url, tls, token).await, "").await.unwrap(),
        ServingStatus::Serving
    );
}

/// A CA, and a certificate it signed for `localhost` and 127.0.0.1 with its key (PEM).
fn test_pki() -> (String, String, String) {
    let mut ca_params = rcgen::CertificateParams::new(Vec::<String>::new()).unwrap();
    ca_params.is_ca = rcgen::IsCa::Ca(rcgen::BasicConstraints::Unconstrained);
    ca_params
        .distinguished_name
        .push(rcgen::DnType::CommonName, "hac test CA");
    let ca = rcgen::CertifiedIssuer::self_signed(ca_params, rcgen::KeyPair::generate().unwrap())
        .unwrap();
    let key = rcgen::KeyPair::generate().unwrap();
    let cert = rcgen::CertificateParams::new(vec!["localhost".into(), "127.0.0.1".into()])
        .unwrap()
        .signed_by(&key, &ca)
        .unwrap();
    (ca.pem(), cert.pem(), key.serialize_pem())
}

#[test]
fn a_token_guards_every_service_but_health_over_tls() {
    let runtime = runtime();
    let learner = start_learner(|_| {});
    let token = Token::new("the-right-token").unwrap();
    let (ca, cert, key) = test_pki();
    let tls = ServerTls::new(cert.into_bytes(), key.into_bytes()).unwrap();
    let server = runtime.block_on(Server::start(
        learner.clone(),
        ServerSecurity {
            token: Some(token.clone()),
            tls: Some(tls),
        },
    ));
    let client_tls = ClientTls::new(ca.clone().into_bytes(), None).unwrap();
    let url = format!("https://{}", server.addr);
    let wrong = Token::new("a-wrong-token").unwrap();
    runtime.block_on(async {
        assert_every_rpc_refused(&url, Some(&client_tls), None).await;
        assert_every_rpc_refused(&url, Some(&client_tls), Some(&wrong)).await;
    });
    // 7 refused RPCs, twice; health went through.
    let refused = |learner: &Learner| {
        learner
            .status()
            .rejected
            .iter()
            .find(|(r, _)| *r == RejectReason::Unauthenticated)
            .map(|&(_, n)| n)
    };
    assert_eq!(refused(&learner), Some(14));

    // A link with the wrong token gives up at once: retrying cannot help.
    let options = GrpcLinkOptions {
        token: Some(wrong),
        tls: Some(client_tls.clone()),
        ..link_options()
    };
    let mut intruder = GrpcLink::connect(&url, options).unwrap();
    match intruder.register(&registration("intruder")) {
        Err(LinkError::Refused(message)) => assert!(message.contains("token"), "{message}"),
        other => panic!("expected a refusal, got {other:?}"),
    }
    // Plain http to a TLS server gets nowhere either.
    let plain = GrpcLink::connect(
        &format!("http://{}", server.addr),
        GrpcLinkOptions {
            token: Some(token.clone()),
            give_up_after: Duration::from_millis(300),
            ..link_options()
        },
    );
    assert!(matches!(
        plain.unwrap().register(&registration("plain")),
        Err(LinkError::Unavailable(_))
    ));

    // The right token over TLS (with the certificate's name checked against the CA): stored.
    let options = GrpcLinkOptions {
        token: Some(token.clone()),
        tls: Some(ClientTls::new(ca.into_bytes(), Some("localhost".into())).unwrap()),
        ..link_options()
    };
    let mut link = GrpcLink::connect(&server.addr.to_string(), options).unwrap();
    link.register(&registration("trainer-0")).unwrap();
    link.send(batch_item(&learner, 0, 8)).unwrap();
    link.send(episode()).unwrap();
    link.flush(WAIT).unwrap();
    let status = learner.status();
    assert_eq!((status.batches, status.episodes), (1, 1));
    let stats = link.stats().expect("a grpc link keeps stats");
    assert_eq!((stats.incarnation(), stats.unacked()), (1, 0));
    runtime.block_on(async {
        let mut client = pb::status_client::StatusClient::new(
            channel(&url, Some(&client_tls), Some(&token)).await,
        );
        let status = learner_of(
            client
                .get_status(pb::GetStatusRequest::default())
                .await
                .unwrap()
                .into_inner(),
        );
        assert_eq!(status.batches, 1);
    });
    drop(link);
    drop(intruder);
    runtime.block_on(server.stop());
}

#[test]
fn the_actor_rate_limit_holds_messages_back_without_refusing_any() {
    let runtime = runtime();
    let rate = 20.0;
    let learner = start_learner(|o| o.max_actor_messages_per_second = Some(rate));
    let server = runtime.block_on(Server::start(learner.clone(), ServerSecurity::default()));
    let mut link = GrpcLink::connect(&format!("http://{}", server.addr), link_options()).unwrap();
    link.register(&registration("fast")).unwrap();
    let started = Instant::now();
    let messages = 40;
    for _ in 0..messages {
        link.send(batch_item(&learner, 0, 4)).unwrap();
    }
    link.flush(WAIT).unwrap();
    let elapsed = started.elapsed();
    let status = learner.status();
    assert_eq!(status.batches, messages);
    assert!(status.rejected.iter().all(|&(_, n)| n == 0), "{status:?}");
    // A burst of `rate` goes at once, the rest at `rate` per second (or slower, on a slow
    // machine, which then needs less holding back).
    let held = messages - rate as u64;
    let min_elapsed = Duration::from_secs_f64((held - 1) as f64 / rate);
    assert!(elapsed >= min_elapsed, "{elapsed:?}");
    assert!(
        status.throttled > 0 && status.throttled <= held,
        "{}",
        status.throttled
    );
    assert!(status.throttled_for > Duration::ZERO);
    drop(link);
    runtime.block_on(server.stop());
}

async fn http_get(addr: SocketAddr, path: &str) -> (String, String) {
    let mut stream = tokio::net::TcpStream::connect(addr).await.unwrap();
    let request = format!("GET {path} HTTP/1.1\r\nHost: test\r\nConnection: close\r\n\r\n");
    stream.write_all(request.as_bytes()).await.unwrap();
    let mut response = String::new();
    stream.read_to_string(&mut response).await.unwrap();
    let (head, body) = response.split_once("\r\n\r\n").unwrap();
    (head.to_string(), body.to_string())
}

/// The value of the sample `series` (name and labels exactly as exposed).
fn sample(text: &str, series: &str) -> f64 {
    text.lines()
        .find_map(|line| line.strip_prefix(series)?.strip_prefix(' '))
        .unwrap_or_else(|| panic!("{series} in\n{text}"))
        .parse()
        .unwrap()
}

#[test]
fn prometheus_metrics_are_scraped_over_http() {
    let runtime = runtime();
    let learner = start_learner(|_| {});
    let server = runtime.block_on(Server::start(learner.clone(), ServerSecurity::default()));
    let mut link = GrpcLink::connect(&format!("http://{}", server.addr), link_options()).unwrap();
    link.register(&registration("trainer-0")).unwrap();
    link.send(batch_item(&learner, 0, 8)).unwrap();
    link.send(batch_item(&learner, 1, 2)).unwrap();
    link.send(episode()).unwrap();
    link.flush(WAIT).unwrap();

    runtime.block_on(async {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        let (stop, stopped) = oneshot::channel::<()>();
        let source = learner.clone();
        let metrics = tokio::spawn(serve_metrics(
            listener,
            Arc::new(move || learner_metrics(&source)),
            async {
                let _ = stopped.await;
            },
        ));
        let (head, text) = http_get(addr, "/metrics").await;
        assert!(head.starts_with("HTTP/1.1 200"), "{head}");
        assert!(
            head.to_lowercase()
                .contains("content-type: text/plain; version=0.0.4"),
            "{head}"
        );
        assert_eq!(
            sample(&text, "hac_learner_transitions_ingested_total"),
            10.0
        );
        assert_eq!(sample(&text, "hac_learner_episodes_ingested_total"), 1.0);
        assert_eq!(sample(&text, "hac_learner_batches_ingested_total"), 2.0);
        let shards: f64 = (0..2)
            .map(|shard| {
                sample(
                    &text,
                    &format!("hac_learner_replay_size{{level=\"0\",shard=\"{shard}\"}}"),
                )
            })
            .sum();
        assert_eq!(shards, 8.0);
        assert_eq!(
            sample(
                &text,
                "hac_learner_rejected_total{reason=\"unauthenticated\"}"
            ),
            0.0
        );
        assert_eq!(sample(&text, "hac_learner_updates_total{level=\"1\"}"), 0.0);
        assert!(sample(&text, "hac_learner_weights_version") >= 1.0);
        assert_eq!(
            sample(
                &text,
                "hac_learner_actor_episodes_total{actor=\"trainer-0\",role=\"trainer\"}"
            ),
            1.0
        );
        for family in [
            "# TYPE hac_learner_transitions_ingested_total counter",
            "# TYPE hac_learner_replay_size gauge",
            "# TYPE hac_learner_updates_total counter",
            "# TYPE hac_learner_rejected_total counter",
            "# HELP hac_learner_weights_version ",
        ] {
            assert!(text.contains(family), "{family}");
        }
        let (head, _) = http_get(addr, "/other").await;
        assert!(head.starts_with("HTTP/1.1 404"), "{head}");
        let _ = stop.send(());
        tokio::time::timeout(WAIT, metrics)
            .await
            .unwrap()
            .unwrap()
            .unwrap();
    });
    drop(link);
    runtime.block_on(server.stop());
}

/// A fixed actor view, for the actor-side status server.
struct FixedActor;

impl StatusSource for FixedActor {
    fn node_status(&self, _: usize) -> pb::NodeStatus {
        (&ActorNodeStatus {
            actor_id: "a-0".into(),
            role: "trainer",
            state: "running",
            episodes: 5,
            ..ActorNodeStatus::default()
        })
            .into()
    }
}

#[test]
fn an_actor_status_server_reports_health_as_told_and_guards_status_with_the_token() {
    let runtime = runtime();
    let token = Token::new("actor-token").unwrap();
    runtime.block_on(async {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let url = format!("http://{}", listener.local_addr().unwrap());
        let health_handle = Health::new(STATUS_SERVICE).await;
        let (stop, stopped) = oneshot::channel::<()>();
        let security = ServerSecurity {
            token: Some(token.clone()),
            tls: None,
        };
        let server = tokio::spawn({
            let health_handle = health_handle.clone();
            async move {
                serve_status(
                    Arc::new(FixedActor),
                    listener,
                    &security,
                    health_handle,
                    Duration::from_secs(1),
                    async {
                        let _ = stopped.await;
                    },
                )
                .await
            }
        });
        // Not ready until told.
        for service in ["", "hac.v1.Status"] {
            assert_eq!(
                health(channel(&url, None, None).await, service)
                    .await
                    .unwrap(),
                ServingStatus::NotServing
            );
        }
        health_handle.set_serving(true).await;
        assert_eq!(
            health(channel(&url, None, None).await, "hac.v1.Status")
                .await
                .unwrap(),
            ServingStatus::Serving
        );
        let mut anonymous = pb::status_client::StatusClient::new(channel(&url, None, None).await);
        let refused = anonymous
            .get_status(pb::GetStatusRequest::default())
            .await
            .unwrap_err();
        assert_eq!(refused.code(), Code::Unauthenticated);
        let mut client =
            pb::status_client::StatusClient::new(channel(&url, None, Some(&token)).await);
        let status = client
            .get_status(pb::GetStatusRequest::default())
            .await
            .unwrap()
            .into_inner();
        let Some(pb::node_status::Node::Actor(actor)) = status.node else {
            panic!("an actor status");
        };
        assert_eq!((actor.actor_id.as_str(), actor.episodes), ("a-0", 5));
        assert_eq!(
            list_services(channel(&url, None, Some(&token)).await)
                .await
                .unwrap(),
            [
                "grpc.health.v1.Health",
                "grpc.reflection.v1.ServerReflection",
                "grpc.reflection.v1alpha.ServerReflection",
                "hac.v1.Status",
            ]
        );
        let _ = stop.send(());
        tokio::time::timeout(WAIT, server)
            .await
            .unwrap()
            .unwrap()
            .unwrap();
    });
}
