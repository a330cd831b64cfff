//! Operating a distributed run with the real `hac` binary over loopback: status that adds up
//! during a run (and `hac status` printing it), Prometheus metrics, health through start-up and
//! drain (SIGTERM), reflection, and a run behind a bearer token and TLS that keeps strangers out.

use std::io::{BufRead as _, BufReader, Read as _};
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdout, Command};
use std::time::{Duration, Instant};

use hac_proto::pb;
use hac_transport::security::{BearerToken, ClientTls, Token, endpoint};
use serde_json::Value;
use tonic::Code;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::Channel;
use tonic_health::pb::health_check_response::ServingStatus;
use tonic_health::pb::{HealthCheckRequest, health_client::HealthClient};
use tonic_reflection::pb::v1::ServerReflectionRequest;
use tonic_reflection::pb::v1::server_reflection_client::ServerReflectionClient;
use tonic_reflection::pb::v1::server_reflection_request::MessageRequest;
use tonic_reflection::pb::v1::server_reflection_response::MessageResponse;

use crate::common;

use common::{Processes, all_logs, hac, hac_output, hac_output_env};

const DEADLINE: Duration = Duration::from_secs(180);

fn scratch(name: &str) -> PathBuf {
    common::scratch("hac-ops-test", name)
}

impl Processes {
    fn get(&mut self, name: &str) -> &mut Child {
        &mut self.0.iter_mut().find(|(n, _)| n == name).unwrap().1
    }
}

/// The next stdout line of `child`, which must start with `prefix`; the rest of it.
fn announced(stdout: &mut BufReader<ChildStdout>, prefix: &str, logs: &Path) -> String {
    let mut line = String::new();
    stdout.read_line(&mut line).unwrap();
    line.trim()
        .strip_prefix(prefix)
        .unwrap_or_else(|| {
            panic!(
                "expected `{prefix}<addr>`, got {line:?}\n{}",
                all_logs(logs)
            )
        })
        .to_string()
}

fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap()
}

type Authed = InterceptedService<Channel, BearerToken>;

async fn channel(url: &str, tls: Option<&ClientTls>, token: Option<&Token>) -> Authed {
    let channel = endpoint(url, tls).unwrap().connect().await.unwrap();
    InterceptedService::new(channel, BearerToken(token.cloned()))
}

async fn health(channel: Authed, service: &str) -> ServingStatus {
    let response = HealthClient::new(channel)
        .check(HealthCheckRequest {
            service: service.into(),
        })
        .await
        .unwrap();
    ServingStatus::try_from(response.into_inner().status).unwrap()
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

/// `hac status <args> --json`, parsed.
fn status_json(args: &[&str], env: &[(&str, &str)]) -> Value {
    let mut all = vec!["status"];
    all.extend_from_slice(args);
    all.push("--json");
    let out = hac_output_env(&all, env);
    assert!(
        out.status.success(),
        "hac {all:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8(out.stdout).unwrap();
    assert_eq!(text.lines().count(), 1, "one JSON object:\n{text}");
    serde_json::from_str(&text).unwrap()
}

fn u(value: &Value) -> u64 {
    value
        .as_u64()
        .unwrap_or_else(|| panic!("a count, got {value}"))
}

fn f(value: &Value) -> f64 {
    value
        .as_f64()
        .unwrap_or_else(|| panic!("a number, got {value}"))
}

/// A metrics scrape over plain HTTP/1.1.
fn scrape(addr: &str) -> String {
    use std::io::Write as _;
    let mut stream = std::net::TcpStream::connect(addr).unwrap();
    stream
        .set_read_timeout(Some(Duration::from_secs(20)))
        .unwrap();
    stream
        .write_all(b"GET /metrics HTTP/1.1\r\nHost: test\r\nConnection: close\r\n\r\n")
        .unwrap();
    let mut response = String::new();
    stream.read_to_string(&mut response).unwrap();
    let (head, body) = response.split_once("\r\n\r\n").unwrap();
    assert!(head.starts_with("HTTP/1.1 200"), "{head}");
    body.to_string()
}

fn sample(text: &str, series: &str) -> f64 {
    text.lines()
        .find_map(|line| line.strip_prefix(series)?.strip_prefix(' '))
        .unwrap_or_else(|| panic!("{series} in\n{text}"))
        .parse()
        .unwrap()
}

/// Checks what must add up in a learner status, whenever it is taken.
fn check_coherent(s: &Value) {
    let levels = s["level_status"].as_array().unwrap();
    assert_eq!(levels.len(), 2, "{s}");
    let mut inserted = 0;
    for level in levels {
        let shards: u64 = level["shard_sizes"].as_array().unwrap().iter().map(u).sum();
        assert_eq!(level["shard_sizes"].as_array().unwrap().len(), 2, "{level}");
        assert_eq!(shards, u(&level["replay_size"]), "{level}");
        assert!(
            u(&level["replay_size"]) <= u(&level["replay_capacity"]),
            "{level}"
        );
        assert!(
            u(&level["transitions_inserted"]) >= u(&level["replay_size"]),
            "{level}"
        );
        inserted += u(&level["transitions_inserted"]);
    }
    // Every transition stored went into exactly one level's replay.
    assert_eq!(inserted, u(&s["transitions"]), "{s}");
    assert!(u(&s["successes"]) <= u(&s["episodes"]), "{s}");
    for actor in s["actors"].as_array().unwrap() {
        assert_eq!(
            u(&actor["weights_lag"]),
            u(&s["weights_version"]) - u(&actor["weights_version"]),
            "{actor}"
        );
    }
}

#[test]
fn a_real_run_reports_coherent_status_metrics_health_and_reflection_then_drains_on_sigterm() {
    let dir = scratch("run");
    let out = dir.join("out");
    let mut processes = Processes(Vec::new());
    let mut learner = hac(
        &[
            "learner",
            "--env",
            "mountain-car",
            "--levels",
            "2",
            "--episodes",
            "100000",
            "--replay-shards",
            "2",
            "--set",
            "test_episodes=5",
            "--listen",
            "127.0.0.1:0",
            "--metrics-listen",
            "127.0.0.1:0",
            "--grace-period",
            "5",
            "--out",
            out.to_str().unwrap(),
        ],
        &dir,
        "learner",
    );
    let mut stdout = BufReader::new(learner.stdout.take().unwrap());
    let addr = announced(&mut stdout, "listening on ", &dir);
    let learner_metrics = announced(&mut stdout, "metrics on ", &dir);
    processes.0.push(("learner".into(), learner));
    let url = format!("http://{addr}");

    let rt = runtime();
    // Serving as soon as it listens: start-up is over by then.
    for service in ["", "hac.v1.Learner"] {
        assert_eq!(
            rt.block_on(async { health(channel(&url, None, None).await, service).await }),
            ServingStatus::Serving
        );
    }

    let mut trainer = hac(
        &[
            "actor",
            "--learner",
            &url,
            "--id",
            "trainer-0",
            "--status-listen",
            "127.0.0.1:0",
            "--metrics-listen",
            "127.0.0.1:0",
        ],
        &dir,
        "trainer-0",
    );
    let mut trainer_stdout = BufReader::new(trainer.stdout.take().unwrap());
    let trainer_status = announced(&mut trainer_stdout, "status on ", &dir);
    let trainer_metrics = announced(&mut trainer_stdout, "metrics on ", &dir);
    processes.0.push(("trainer-0".into(), trainer));
    processes.0.push((
        "eval-0".into(),
        hac(
            &[
                "actor",
                "--learner",
                &url,
                "--id",
                "eval-0",
                "--role",
                "evaluator",
                "--eval-every",
                "5",
            ],
            &dir,
            "eval-0",
        ),
    ));

    // Mid-run: both actors known, updates done, an evaluation on the curve.
    let started = Instant::now();
    let first = loop {
        let s = status_json(&["--learner", &addr], &[]);
        let s = s["learner"].clone();
        let updates = u(&s["level_status"][0]["updates"]);
        if s["actors"].as_array().unwrap().len() == 2
            && updates > 0
            && u(&s["evaluations_total"]) > 0
            && u(&s["episodes"]) >= 10
        {
            break s;
        }
        assert!(
            started.elapsed() < DEADLINE,
            "the run never got going: {s}\n{}",
            all_logs(&dir)
        );
        std::thread::sleep(Duration::from_millis(500));
    };
    check_coherent(&first);
    assert_eq!(first["state"], "serving");
    assert_eq!(first["env"], "mountain-car");
    for rate in [
        "transitions_per_second",
        "episodes_per_second",
        "env_steps_per_second",
        "updates_per_second",
    ] {
        assert!(f(&first[rate]) > 0.0, "{rate}: {first}");
    }
    let trainer_seen = first["actors"]
        .as_array()
        .unwrap()
        .iter()
        .find(|a| a["actor_id"] == "trainer-0")
        .unwrap()
        .clone();
    assert_eq!(trainer_seen["transport"], "grpc");
    assert_eq!(trainer_seen["role"], "trainer");
    assert!(u(&trainer_seen["episodes"]) > 0);
    assert!(!first["evaluations"].as_array().unwrap().is_empty());

    // Later: counters and versions only grow, and it all still adds up.
    std::thread::sleep(Duration::from_millis(1500));
    let second = status_json(&["--learner", &addr], &[])["learner"].clone();
    check_coherent(&second);
    for key in [
        "weights_version",
        "episodes",
        "transitions",
        "env_steps",
        "messages",
    ] {
        assert!(
            u(&second[key]) >= u(&first[key]),
            "{key}: {first} then {second}"
        );
    }
    for level in 0..2 {
        assert!(
            u(&second["level_status"][level]["updates"])
                >= u(&first["level_status"][level]["updates"])
        );
    }

    // The table.
    let table = hac_output(&["status", "--learner", &addr]);
    assert!(table.status.success());
    let table = String::from_utf8(table.stdout).unwrap();
    for expected in [
        "learner  serving  env mountain-car  levels 2",
        "level  updates",
        "trainer-0",
        "eval-0",
        "rejected: none",
        "evaluations (last",
    ] {
        assert!(table.contains(expected), "{expected:?} in\n{table}");
    }

    // The actor's own status, health and reflection.
    let actor = status_json(&["--actor", &trainer_status], &[])["actor"].clone();
    assert_eq!(actor["actor_id"], "trainer-0");
    assert_eq!(actor["state"], "running");
    assert_eq!(
        (actor["role"].as_str(), actor["transport"].as_str()),
        (Some("trainer"), Some("grpc"))
    );
    // Incarnations are numbered across actors in registration order, and the trainer and the
    // evaluator start together: the trainer's is whichever the learner gave it.
    assert!(
        u(&actor["episodes"]) > 0 && u(&actor["incarnation"]) == u(&trainer_seen["incarnation"]),
        "{actor}\nlearner's view: {trainer_seen}"
    );
    let actor_table = hac_output(&["status", "--actor", &trainer_status]);
    let actor_table = String::from_utf8(actor_table.stdout).unwrap();
    assert!(
        actor_table.contains("actor trainer-0  running  role trainer"),
        "{actor_table}"
    );
    let actor_url = format!("http://{trainer_status}");
    rt.block_on(async {
        for service in ["", "hac.v1.Status"] {
            assert_eq!(
                health(channel(&actor_url, None, None).await, service).await,
                ServingStatus::Serving
            );
        }
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
        assert_eq!(
            list_services(channel(&actor_url, None, None).await)
                .await
                .unwrap(),
            [
                "grpc.health.v1.Health",
                "grpc.reflection.v1.ServerReflection",
                "grpc.reflection.v1alpha.ServerReflection",
                "hac.v1.Status",
            ]
        );
    });

    // Metrics of both, consistent with the status taken before the scrape.
    let text = scrape(&learner_metrics);
    assert!(
        sample(&text, "hac_learner_transitions_ingested_total") >= u(&second["transitions"]) as f64
    );
    assert!(sample(&text, "hac_learner_weights_version") >= u(&second["weights_version"]) as f64);
    assert!(sample(&text, "hac_learner_updates_total{level=\"0\"}") > 0.0);
    let replay: f64 = (0..2)
        .map(|shard| {
            sample(
                &text,
                &format!("hac_learner_replay_size{{level=\"0\",shard=\"{shard}\"}}"),
            )
        })
        .sum();
    assert!(replay > 0.0);
    assert_eq!(sample(&text, "hac_learner_actors{role=\"trainer\"}"), 1.0);
    assert!(text.contains("# TYPE hac_learner_rejected_total counter"));
    let text = scrape(&trainer_metrics);
    assert!(sample(&text, "hac_actor_episodes_total") >= u(&actor["episodes"]) as f64);
    assert_eq!(sample(&text, "hac_actor_ready"), 1.0);
    assert!(sample(&text, "hac_actor_weights_version") >= 1.0);

    // A live watch while the learner drains.
    let mut watcher = hac(
        &[
            "status",
            "--learner",
            &addr,
            "--watch",
            "--json",
            "--interval",
            "0.2",
        ],
        &dir,
        "watch",
    );
    let (first_line_tx, first_line) = std::sync::mpsc::channel();
    let watched = {
        // Read as it comes, so that the watcher never blocks on a full pipe.
        let stdout = BufReader::new(watcher.stdout.take().unwrap());
        std::thread::spawn(move || {
            let mut lines = Vec::new();
            for line in stdout.lines() {
                let line = line.unwrap();
                if lines.is_empty() {
                    let _ = first_line_tx.send(line.clone());
                }
                lines.push(line);
            }
            lines
        })
    };
    processes.0.push(("watch".into(), watcher));
    let line = first_line
        .recv_timeout(Duration::from_secs(60))
        .expect("a first snapshot from the watch");
    let snapshot: Value = serde_json::from_str(&line).unwrap();
    assert!(u(&snapshot["learner"]["episodes"]) >= u(&second["episodes"]));

    // SIGTERM: health turns NOT_SERVING at once while the learner still serves the final
    // weights for the grace period, then everyone exits cleanly and the run is saved.
    let pid = processes.get("learner").id();
    let killed = Command::new("kill")
        .args(["-TERM", &pid.to_string()])
        .status()
        .unwrap();
    assert!(killed.success());
    let started = Instant::now();
    rt.block_on(async {
        loop {
            let status = health(channel(&url, None, None).await, "").await;
            if status == ServingStatus::NotServing {
                break;
            }
            assert!(
                started.elapsed() < Duration::from_secs(5),
                "still {status:?}"
            );
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        assert_eq!(
            health(channel(&url, None, None).await, "hac.v1.Learner").await,
            ServingStatus::NotServing
        );
    });
    let draining = status_json(&["--learner", &addr], &[])["learner"].clone();
    assert_eq!(draining["state"], "draining");

    processes.all_succeed(&dir, DEADLINE);
    // The watch printed a snapshot per interval until the learner shut it down.
    let lines = watched.join().unwrap();
    assert!(lines.len() >= 2, "{lines:?}");
    let mut last_episodes = 0;
    for line in &lines {
        let snapshot: Value = serde_json::from_str(line).unwrap();
        let episodes = u(&snapshot["learner"]["episodes"]);
        assert!(episodes >= last_episodes, "{line}");
        last_episodes = episodes;
    }
    let summary: Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    assert!(
        u(&summary["episodes_ingested"]) >= u(&second["episodes"]),
        "{summary}"
    );
    let log = std::fs::read_to_string(dir.join("learner.log")).unwrap();
    assert!(log.contains("signal received"), "{log}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// A CA, and a certificate it signed for `localhost` with its key (PEM), written to `dir`.
fn write_pki(dir: &Path) -> (PathBuf, PathBuf, PathBuf) {
    let mut ca_params = rcgen::CertificateParams::new(Vec::<String>::new()).unwrap();
    ca_params.is_ca = rcgen::IsCa::Ca(rcgen::BasicConstraints::Unconstrained);
    ca_params
        .distinguished_name
        .push(rcgen::DnType::CommonName, "hac test CA");
    let ca = rcgen::CertifiedIssuer::self_signed(ca_params, rcgen::KeyPair::generate().unwrap())
        .unwrap();
    let key = rcgen::KeyPair::generate().unwrap();
    let cert = rcgen::CertificateParams::new(vec!["localhost".to_string()])
        .unwrap()
        .signed_by(&key, &ca)
        .unwrap();
    let paths = (
        dir.join("ca.pem"),
        dir.join("cert.pem"),
        dir.join("key.pem"),
    );
    std::fs::write(&paths.0, ca.pem()).unwrap();
    std::fs::write(&paths.1, cert.pem()).unwrap();
    std::fs::write(&paths.2, key.serialize_pem()).unwrap();
    paths
}

/// Every RPC of every service but health, without the token or with `token`: UNAUTHENTICATED;
/// health answers. Returns the number of refused calls.
async fn every_rpc_is_refused(url: &str, tls: &ClientTls, token: Option<&Token>) -> u64 {
    let mut refused = 0;
    let mut check = |what: &str, result: Result<(), tonic::Status>| {
        let status = result.expect_err(what);
        assert_eq!(status.code(), Code::Unauthenticated, "{what}: {status:?}");
        refused += 1;
    };
    let mut learner = pb::learner_client::LearnerClient::new(channel(url, Some(tls), token).await);
    check(
        "register",
        learner
            .register(pb::RegisterRequest {
                actor_id: "intruder".into(),
                role: pb::ActorRole::Trainer.into(),
                ..pb::RegisterRequest::default()
            })
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
    let mut status = pb::status_client::StatusClient::new(channel(url, Some(tls), token).await);
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
        list_services(channel(url, Some(tls), token).await)
            .await
            .map(drop),
    );
    assert_eq!(
        health(channel(url, Some(tls), token).await, "").await,
        ServingStatus::Serving
    );
    refused
}

#[test]
fn a_run_behind_a_token_and_tls_keeps_strangers_out() {
    let dir = scratch("secure");
    let out = dir.join("out");
    let (ca, cert, key) = write_pki(&dir);
    let token_file = dir.join("token");
    std::fs::write(&token_file, "s3cret-0123456789\n").unwrap();
    let (ca_s, token_s) = (ca.to_str().unwrap(), token_file.to_str().unwrap());
    let mut processes = Processes(Vec::new());
    let mut learner = hac(
        &[
            "--log-format",
            "json",
            "learner",
            "--env",
            "mountain-car",
            "--levels",
            "2",
            "--episodes",
            "30",
            "--set",
            "test_episodes=5",
            "--listen",
            "127.0.0.1:0",
            "--token-file",
            token_s,
            "--tls-cert",
            cert.to_str().unwrap(),
            "--tls-key",
            key.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ],
        &dir,
        "learner",
    );
    let mut stdout = BufReader::new(learner.stdout.take().unwrap());
    let addr = announced(&mut stdout, "listening on ", &dir);
    processes.0.push(("learner".into(), learner));
    let url = format!("https://{addr}");

    // Strangers: no token, a wrong token.
    let tls = ClientTls::from_file(&ca, Some("localhost".into())).unwrap();
    let wrong = Token::new("not-the-token").unwrap();
    let mut refused = runtime().block_on(async {
        every_rpc_is_refused(&url, &tls, None).await
            + every_rpc_is_refused(&url, &tls, Some(&wrong)).await
    });
    let tls_flags = ["--tls-ca", ca_s, "--tls-domain", "localhost"];
    let mut args = vec!["status", "--learner", &url];
    args.extend_from_slice(&tls_flags);
    let anonymous = hac_output(&args);
    assert!(!anonymous.status.success());
    let stderr = String::from_utf8_lossy(&anonymous.stderr);
    assert!(stderr.contains("Unauthenticated"), "{stderr}");
    refused += 1;
    // Without TLS nothing gets through at all.
    let plain = hac_output_env(
        &[
            "status",
            "--learner",
            &format!("http://{addr}"),
            "--timeout",
            "5",
        ],
        &[("HAC_TOKEN", "s3cret-0123456789")],
    );
    assert!(!plain.status.success());
    // An actor with the wrong token stops at once, refused.
    let mut intruder_args = vec!["actor", "--learner", &url, "--id", "intruder"];
    intruder_args.extend_from_slice(&tls_flags);
    let intruder = hac_output_env(&intruder_args, &[("HAC_TOKEN", "not-the-token")]);
    assert!(!intruder.status.success());
    let stderr = String::from_utf8_lossy(&intruder.stderr);
    assert!(
        stderr.contains("refused") && stderr.contains("token"),
        "{stderr}"
    );
    refused += 1;

    // The operator's view, with the token from the environment.
    let mut args = vec!["--learner", url.as_str()];
    args.extend_from_slice(&tls_flags);
    let s = status_json(&args, &[("HAC_TOKEN", "s3cret-0123456789")]);
    let unauthenticated = s["learner"]["rejected"]
        .as_array()
        .unwrap()
        .iter()
        .find(|r| r["reason"] == "unauthenticated")
        .map(|r| u(&r["count"]));
    assert_eq!(unauthenticated, Some(refused), "{s}");

    // The run itself, over TLS with the token from a file.
    for (name, extra) in [
        ("eval-0", &["--role", "evaluator", "--eval-every", "10"][..]),
        ("trainer-0", &[][..]),
        ("trainer-1", &[][..]),
    ] {
        let mut args = vec![
            "actor",
            "--learner",
            &url,
            "--id",
            name,
            "--token-file",
            token_s,
        ];
        args.extend_from_slice(&tls_flags);
        args.extend_from_slice(extra);
        processes.0.push((name.into(), hac(&args, &dir, name)));
    }
    processes.all_succeed(&dir, DEADLINE);
    let summary: Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    assert!(u(&summary["episodes_ingested"]) >= 30, "{summary}");
    assert!(u(&summary["rounds"]) >= 1, "{summary}");
    assert_eq!(
        u(&summary["rejected"]["unauthenticated"]),
        refused,
        "{summary}"
    );
    // Structured logs: one JSON object per line, values in fields.
    let log = std::fs::read_to_string(dir.join("learner.log")).unwrap();
    let events: Vec<Value> = log
        .lines()
        .map(|line| serde_json::from_str(line).unwrap_or_else(|e| panic!("{e}: {line}")))
        .collect();
    // Each kind of refusal in full once per 10 s interval, not once per request (at least 7 of
    // each kind came within seconds; the counts above have them all).
    for token in ["(missing token)", "(wrong token)"] {
        let lines = events
            .iter()
            .filter(|e| {
                e["level"] == "WARN"
                    && e["fields"]["message"] == "input refused"
                    && e["fields"]["reason"] == "unauthenticated"
                    && e["fields"]["actor"] == token
            })
            .count();
        assert!((1..=3).contains(&lines), "{lines} lines for {token}\n{log}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}
