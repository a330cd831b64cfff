//! Prometheus metrics: the text exposition format ([`Exposition`]), a minimal HTTP/1 server for
//! `GET /metrics` ([`serve_metrics`]), and what the learner and an actor daemon expose
//! ([`learner_metrics`], [`actor_metrics`]).
//!
//! Names follow the Prometheus conventions: a `hac_learner_` or `hac_actor_` prefix, base units
//! in the name (`_seconds`, `_bytes`; transitions, episodes and steps are counts), counters end in
//! `_total`, and every family has HELP and TYPE lines. Rates are left to PromQL (`rate(...)`), so
//! only totals and gauges are exposed. A scrape renders a fresh snapshot; nothing is kept between
//! scrapes.

use std::convert::Infallible;
use std::fmt::Write as _;
use std::future::Future;
use std::sync::Arc;
use std::time::Duration;

use hac_learner::Learner;
use http::{Method, Request, Response, StatusCode, header};
use http_body_util::Full;
use hyper::body::{Bytes, Incoming};
use hyper::server::conn::http1;
use hyper::service::service_fn;
use hyper_util::rt::{TokioIo, TokioTimer};
use tokio::net::TcpListener;

use crate::grpc::{ActorNodeStatus, role_name};

/// The content type of the text exposition format.
pub const CONTENT_TYPE: &str = "text/plain; version=0.0.4; charset=utf-8";
/// The path metrics are served on.
pub const PATH: &str = "/metrics";
/// Longest wait for a request's headers before the connection is closed.
const HEADER_TIMEOUT: Duration = Duration::from_secs(10);

/// A metric family's type.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kind {
    Counter,
    Gauge,
}

/// A document in the Prometheus text exposition format, built family by family.
#[derive(Debug, Default)]
pub struct Exposition {
    text: String,
}

impl Exposition {
    pub fn new() -> Self {
        Self::default()
    }

    /// Starts the family `name` (HELP and TYPE lines); add its samples with
    /// [`sample`](Self::sample).
    pub fn family(&mut self, name: &str, kind: Kind, help: &str) -> &mut Self {
        let kind = match kind {
            Kind::Counter => "counter",
            Kind::Gauge => "gauge",
        };
        let help = help.replace('\\', "\\\\").replace('\n', "\\n");
        let _ = writeln!(self.text, "# HELP {name} {help}");
        let _ = writeln!(self.text, "# TYPE {name} {kind}");
        self
    }

    /// One sample of the current family.
    pub fn sample(&mut self, name: &str, labels: &[(&str, &str)], value: f64) -> &mut Self {
        self.text.push_str(name);
        if !labels.is_empty() {
            self.text.push('{');
            for (i, (label, value)) in labels.iter().enumerate() {
                if i > 0 {
                    self.text.push(',');
                }
                let value = value
                    .replace('\\', "\\\\")
                    .replace('"', "\\\"")
                    .replace('\n', "\\n");
                let _ = write!(self.text, "{label}=\"{value}\"");
            }
            self.text.push('}');
        }
        self.text.push(' ');
        if value.is_nan() {
            self.text.push_str("NaN");
        } else if value.is_infinite() {
            self.text
                .push_str(if value > 0.0 { "+Inf" } else { "-Inf" });
        } else {
            let _ = write!(self.text, "{value}");
        }
        self.text.push('\n');
        self
    }

    /// A family with a single unlabelled sample.
    pub fn single(&mut self, name: &str, kind: Kind, help: &str, value: f64) -> &mut Self {
        self.family(name, kind, help).sample(name, &[], value)
    }

    pub fn finish(self) -> String {
        self.text
    }
}

/// Serves `GET /metrics` (and `HEAD`) with whatever `render` returns, on `listener`, until
/// `shutdown` completes; then stops accepting (scrapes in progress finish on their own). Other
/// paths get 404, other methods 405.
pub async fn serve_metrics(
    listener: TcpListener,
    render: Arc<dyn Fn() -> String + Send + Sync>,
    shutdown: impl Future<Output = ()>,
) -> std::io::Result<()> {
    tokio::pin!(shutdown);
    loop {
        let (stream, peer) = tokio::select! {
            () = &mut shutdown => return Ok(()),
            accepted = listener.accept() => match accepted {
                Ok(accepted) => accepted,
                // Out of file descriptors and the like: the next accept may work.
                Err(e) => {
                    tracing::warn!(error = %e, "metrics: accepting a connection failed");
                    tokio::time::sleep(Duration::from_millis(100)).await;
                    continue;
                }
            },
        };
        let render = render.clone();
        tokio::spawn(async move {
            let service = service_fn(move |request| {
                let render = render.clone();
                async move { Ok::<_, Infallible>(respond(&request, render.as_ref())) }
            });
            let connection = http1::Builder::new()
                .timer(TokioTimer::new())
                .header_read_timeout(HEADER_TIMEOUT)
                .serve_connection(TokioIo::new(stream), service);
            if let Err(e) = connection.await {
                tracing::debug!(%peer, error = %e, "metrics connection ended");
            }
        });
    }
}

fn respond(
    request: &Request<Incoming>,
    render: &(dyn Fn() -> String + Send + Sync),
) -> Response<Full<Bytes>> {
    let reply = |status: StatusCode, body: String| {
        Response::builder()
            .status(status)
            .header(header::CONTENT_TYPE, CONTENT_TYPE)
            .body(Full::new(Bytes::from(body)))
            .expect("a valid response")
    };
    if request.uri().path() != PATH {
        return reply(
            StatusCode::NOT_FOUND,
            format!("not found: metrics are at {PATH}\n"),
        );
    }
    match *request.method() {
        Method::GET => reply(StatusCode::OK, render()),
        Method::HEAD => reply(StatusCode::OK, String::new()),
        _ => reply(StatusCode::METHOD_NOT_ALLOWED, "only GET and HEAD\n".into()),
    }
}

/// The learner's metrics now.
pub fn learner_metrics(learner: &Learner) -> String {
    use Kind::{Counter, Gauge};
    let status = learner.status();
    let run = learner.run_config();
    let mut m = Exposition::new();
    let levels = run.levels.to_string();
    m.family(
        "hac_learner_info",
        Gauge,
        "The run this learner serves (always 1).",
    )
    .sample(
        "hac_learner_info",
        &[
            ("env", &run.env),
            ("levels", &levels),
            ("run_config_digest", &status.run_config_digest),
        ],
        1.0,
    );
    m.single(
        "hac_learner_uptime_seconds",
        Gauge,
        "Seconds since the learner started.",
        status.uptime.as_secs_f64(),
    );
    m.single(
        "hac_learner_run_finished",
        Gauge,
        "1 once the run is over (the learner drains), else 0.",
        f64::from(u8::from(status.finished)),
    );
    m.single(
        "hac_learner_weights_version",
        Gauge,
        "The newest weights version published.",
        status.weights_version as f64,
    );
    m.single(
        "hac_learner_episode_budget",
        Gauge,
        "Training episodes the run is budgeted for.",
        run.episodes as f64,
    );
    for (name, help, value) in [
        (
            "hac_learner_ingest_messages_total",
            "Ingest messages that reached the learner core, valid or not.",
            status.messages,
        ),
        (
            "hac_learner_batches_ingested_total",
            "Transition batches stored.",
            status.batches,
        ),
        (
            "hac_learner_transitions_ingested_total",
            "Transitions stored, every level.",
            status.transitions,
        ),
        (
            "hac_learner_episodes_ingested_total",
            "Training episodes ingested.",
            status.episodes,
        ),
        (
            "hac_learner_episode_successes_total",
            "Training episodes ingested that reached their goal.",
            status.successes,
        ),
        (
            "hac_learner_env_steps_total",
            "Primitive environment steps of the training episodes ingested.",
            status.env_steps,
        ),
        (
            "hac_learner_duplicates_total",
            "Resent messages already stored, acknowledged and dropped.",
            status.duplicates,
        ),
        (
            "hac_learner_actor_rate_limit_waits_total",
            "Ingest messages held back by the per-actor message rate limit.",
            status.throttled,
        ),
        (
            "hac_learner_turns_granted_total",
            "Episode turns granted to trainers (--episodes-in-flight).",
            status.turns.granted,
        ),
        (
            "hac_learner_turns_expired_total",
            "Episode turns whose lease ran out before their episode arrived.",
            status.turns.expired,
        ),
    ] {
        m.single(name, Counter, help, value as f64);
    }
    m.single(
        "hac_learner_turns_waiting",
        Gauge,
        "Trainers waiting for an episode turn now.",
        status.turns.waiting as f64,
    );
    m.single(
        "hac_learner_actor_rate_limit_wait_seconds_total",
        Counter,
        "Time ingest streams were held back by the per-actor message rate limit.",
        status.throttled_for.as_secs_f64(),
    );
    m.family(
        "hac_learner_rejected_total",
        Counter,
        "Refused inputs by reason.",
    );
    for &(reason, count) in &status.rejected {
        m.sample(
            "hac_learner_rejected_total",
            &[("reason", reason.name())],
            count as f64,
        );
    }

    let level_names: Vec<String> = (0..status.levels.len()).map(|l| l.to_string()).collect();
    let per_level = |m: &mut Exposition,
                     name: &str,
                     kind: Kind,
                     help: &str,
                     f: &dyn Fn(usize) -> Option<f64>| {
        m.family(name, kind, help);
        for (level, label) in level_names.iter().enumerate() {
            if let Some(value) = f(level) {
                m.sample(name, &[("level", label)], value);
            }
        }
    };
    let levels = &status.levels;
    per_level(
        &mut m,
        "hac_learner_updates_total",
        Counter,
        "Updates done per level.",
        &|l| Some(levels[l].updates as f64),
    );
    m.family(
        "hac_learner_replay_size",
        Gauge,
        "Transitions stored in replay, per level and shard.",
    );
    for (level, l) in levels.iter().enumerate() {
        for (shard, &len) in l.shard_lens.iter().enumerate() {
            m.sample(
                "hac_learner_replay_size",
                &[
                    ("level", &level_names[level]),
                    ("shard", &shard.to_string()),
                ],
                len as f64,
            );
        }
    }
    per_level(
        &mut m,
        "hac_learner_replay_capacity",
        Gauge,
        "Transitions a level's replay holds at most.",
        &|l| Some(levels[l].replay_capacity as f64),
    );
    per_level(
        &mut m,
        "hac_learner_replay_inserted_total",
        Counter,
        "Transitions ever inserted into a level's replay.",
        &|l| Some(levels[l].transitions_inserted as f64),
    );
    per_level(
        &mut m,
        "hac_learner_critic_loss",
        Gauge,
        "The last update's critic loss (absent before the first update).",
        &|l| levels[l].last.map(|u| f64::from(u.critic_loss)),
    );
    per_level(
        &mut m,
        "hac_learner_actor_loss",
        Gauge,
        "The last update's actor loss (absent before the first update).",
        &|l| levels[l].last.map(|u| f64::from(u.actor_loss)),
    );
    per_level(
        &mut m,
        "hac_learner_mean_q",
        Gauge,
        "The last update's mean Q of the sampled batch (absent before the first update).",
        &|l| levels[l].last.map(|u| f64::from(u.mean_q)),
    );
    per_level(
        &mut m,
        "hac_learner_update_deficit",
        Gauge,
        "Updates owed to the episodes ingested (rate limiter).",
        &|l| Some(levels[l].limiter.deficit),
    );
    per_level(
        &mut m,
        "hac_learner_trainer_wait_seconds_total",
        Counter,
        "Time the level's trainer waited for an update to be owed.",
        &|l| Some(levels[l].limiter.trainer_blocked.as_secs_f64()),
    );
    per_level(
        &mut m,
        "hac_learner_ingest_waits_total",
        Counter,
        "Ingest admission checks that found no room (backpressure).",
        &|l| Some(levels[l].limiter.ingest_refused as f64),
    );
    per_level(
        &mut m,
        "hac_learner_diverged_updates_total",
        Counter,
        "Updates undone because they diverged (non-finite or exploding loss or weights).",
        &|l| Some(levels[l].diverged_updates as f64),
    );
    per_level(
        &mut m,
        "hac_learner_ingest_wait_seconds_total",
        Counter,
        "Time ingest waited for room (backpressure).",
        &|l| Some(levels[l].limiter.ingest_blocked.as_secs_f64()),
    );

    m.family("hac_learner_actors", Gauge, "Registered actors by role.");
    for role in [
        hac_proto::ActorRole::Trainer,
        hac_proto::ActorRole::Evaluator,
    ] {
        let n = status.actors.iter().filter(|a| a.role == role).count();
        m.sample("hac_learner_actors", &[("role", role_name(role))], n as f64);
    }
    type ActorField = fn(&hac_learner::RegisteredActor) -> f64;
    let actor_families: [(&str, Kind, &str, ActorField); 6] = [
        (
            "hac_learner_actor_episodes_total",
            Counter,
            "Training episodes ingested from an actor's current incarnation.",
            |a| a.episodes as f64,
        ),
        (
            "hac_learner_actor_env_steps_total",
            Counter,
            "Environment steps ingested from an actor's current incarnation.",
            |a| a.env_steps as f64,
        ),
        (
            "hac_learner_actor_transitions_total",
            Counter,
            "Transitions stored from an actor's current incarnation.",
            |a| a.transitions as f64,
        ),
        (
            "hac_learner_actor_last_seen_seconds",
            Gauge,
            "Seconds since the learner last heard from an actor.",
            |a| a.last_seen_ago.as_secs_f64(),
        ),
        (
            "hac_learner_actor_weights_lag",
            Gauge,
            "Weights versions an actor is behind the newest.",
            |a| a.weights_lag as f64,
        ),
        (
            "hac_learner_actor_undurable_messages",
            Gauge,
            "Messages of an actor stored (acknowledged) and not yet durable in the write-ahead log.",
            |a| a.stored_through.saturating_sub(a.durable_through) as f64,
        ),
    ];
    for (name, kind, help, field) in actor_families {
        m.family(name, kind, help);
        for a in &status.actors {
            m.sample(
                name,
                &[("actor", &a.actor_id), ("role", role_name(a.role))],
                field(a),
            );
        }
    }

    let (evaluations, last) = learner.recent_curve(1);
    if let Some(wal) = &status.wal {
        m.single(
            "hac_learner_wal_bytes",
            Gauge,
            "Bytes of the write-ahead log on disk (what came after the newest checkpoint).",
            wal.bytes as f64,
        );
        m.single(
            "hac_learner_wal_commits_total",
            Counter,
            "Commits (fsyncs) of the write-ahead log.",
            wal.commits as f64,
        );
        m.single(
            "hac_learner_wal_undurable_records",
            Gauge,
            "Records appended to the write-ahead log and not yet committed.",
            wal.appended.saturating_sub(wal.committed) as f64,
        );
    }
    m.single(
        "hac_learner_evaluations_total",
        Counter,
        "Evaluations (greedy test rounds) on the learning curve.",
        evaluations as f64,
    );
    if let Some(last) = last.first() {
        m.single(
            "hac_learner_last_evaluation_success_ratio",
            Gauge,
            "Success rate of the latest evaluation, 0 to 1.",
            f64::from(last.success_rate),
        );
        m.single(
            "hac_learner_last_evaluation_episodes",
            Gauge,
            "Training episodes the latest evaluated weights were trained on.",
            last.episodes as f64,
        );
    }
    m.finish()
}

/// An actor daemon's metrics from its status.
pub fn actor_metrics(s: &ActorNodeStatus) -> String {
    use Kind::{Counter, Gauge};
    let mut m = Exposition::new();
    m.family("hac_actor_info", Gauge, "This actor's identity (always 1).")
        .sample(
            "hac_actor_info",
            &[
                ("actor", &s.actor_id),
                ("role", s.role),
                ("transport", s.transport),
                ("learner", &s.learner),
            ],
            1.0,
        );
    m.single(
        "hac_actor_ready",
        Gauge,
        "1 while registered with the learner and acting, else 0.",
        f64::from(u8::from(s.state == "running")),
    );
    m.single(
        "hac_actor_uptime_seconds",
        Gauge,
        "Seconds since the actor started.",
        s.uptime.as_secs_f64(),
    );
    m.single(
        "hac_actor_incarnation",
        Gauge,
        "The current registration's incarnation (0 before the first).",
        s.incarnation as f64,
    );
    for (name, help, value) in [
        (
            "hac_actor_episodes_total",
            "Training episodes played and sent.",
            s.episodes,
        ),
        (
            "hac_actor_episode_successes_total",
            "Training episodes that reached their goal.",
            s.successes,
        ),
        (
            "hac_actor_env_steps_total",
            "Primitive environment steps of training episodes.",
            s.env_steps,
        ),
        (
            "hac_actor_evaluations_total",
            "Greedy test rounds reported.",
            s.evaluations,
        ),
        (
            "hac_actor_reconnects_total",
            "Reconnects to the learner after a failed call or stream.",
            s.reconnects,
        ),
    ] {
        m.single(name, Counter, help, value as f64);
    }
    for (name, help, value) in [
        (
            "hac_actor_weights_version",
            "The weights version the actor acts with.",
            s.weights_version,
        ),
        (
            "hac_actor_learner_weights_version",
            "The newest weights version the learner announced.",
            s.learner_weights_version,
        ),
        (
            "hac_actor_unacked_messages",
            "Messages sent and not yet acknowledged by the learner.",
            s.unacked,
        ),
        (
            "hac_actor_undurable_messages",
            "Messages acknowledged and not yet durable (kept to be resent to a restarted learner).",
            s.undurable,
        ),
    ] {
        m.single(name, Gauge, help, value as f64);
    }
    m.finish()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_exposition_format_escapes_and_types() {
        let mut m = Exposition::new();
        m.family("x_total", Kind::Counter, "Things\\done\nhere.")
            .sample("x_total", &[("a", "q\"u\\o\nte"), ("b", "2")], 3.0)
            .sample("x_total", &[], 0.5);
        m.single("y", Kind::Gauge, "Y.", f64::NAN);
        m.single("z", Kind::Gauge, "Z.", f64::NEG_INFINITY);
        assert_eq!(
            m.finish(),
            "# HELP x_total Things\\\\done\\nhere.\n# TYPE x_total counter\n\
             x_total{a=\"q\\\"u\\\\o\\nte\",b=\"2\"} 3\nx_total 0.5\n\
             # HELP y Y.\n# TYPE y gauge\ny NaN\n# HELP z Z.\n# TYPE z gauge\nz -Inf\n"
        );
    }

    #[test]
    fn actor_metrics_follow_the_naming_conventions() {
        let text = actor_metrics(&ActorNodeStatus {
            actor_id: "a-0".into(),
            role: "trainer",
            state: "running",
            transport: "grpc",
            episodes: 12,
            unacked: 3,
            ..ActorNodeStatus::default()
        });
        assert!(text.contains("\nhac_actor_episodes_total 12\n"), "{text}");
        assert!(text.contains("\nhac_actor_unacked_messages 3\n"), "{text}");
        assert!(text.contains("\nhac_actor_ready 1\n"), "{text}");
        check_conventions(&text);
    }

    /// Every sample belongs to the family announced just before it, with HELP and TYPE;
    /// counters end in `_total`.
    pub(crate) fn check_conventions(text: &str) {
        let mut family: Option<(&str, &str)> = None;
        let mut help = None;
        for line in text.lines() {
            if let Some(rest) = line.strip_prefix("# HELP ") {
                help = rest.split(' ').next();
            } else if let Some(rest) = line.strip_prefix("# TYPE ") {
                let mut parts = rest.split(' ');
                let (name, kind) = (parts.next().unwrap(), parts.next().unwrap());
                assert_eq!(help, Some(name), "HELP before TYPE for {name}");
                assert_eq!(
                    name.ends_with("_total"),
                    kind == "counter",
                    "{name} is a {kind}"
                );
                assert!(name.starts_with("hac_"), "{name}");
                family = Some((name, kind));
            } else {
                let (name, _) = family.expect("a sample after a TYPE line");
                let sample = line.split(['{', ' ']).next().unwrap();
                assert_eq!(sample, name, "{line}");
                let value = line.rsplit(' ').next().unwrap();
                assert!(value.parse::<f64>().is_ok() || value == "NaN", "{line}");
            }
        }
    }
}
