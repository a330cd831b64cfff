//! `hac status`: a learner's (or an actor's) `hac.v1.Status`, as a readable table or JSON, once
//! or live (`--watch`).

use std::fmt::Write as _;
use std::io::{IsTerminal as _, Write as _};
use std::time::Duration;

use anyhow::{Context, Result, bail};
use hac_proto::pb;
use hac_proto::pb::node_status::Node;
use hac_run::security::{ClientTlsArgs, TokenArgs};
use hac_transport::security::{BearerToken, endpoint};
use tonic::service::interceptor::InterceptedService;
use tonic::transport::Channel;

/// The learner's default address, as the daemons' `--listen` default.
const DEFAULT_LEARNER: &str = "http://127.0.0.1:50051";
/// Evaluations shown in the table (the JSON has the whole curve).
const TABLE_EVALUATIONS: u32 = 5;

#[derive(Debug, clap::Args)]
pub struct StatusArgs {
    /// The learner's gRPC address: http://host:port, https://host:port, or host:port (https with
    /// --tls-ca) [default: http://127.0.0.1:50051].
    #[arg(long, value_name = "URL", conflicts_with = "actor")]
    pub learner: Option<String>,
    /// An actor's status address instead (its --status-listen).
    #[arg(long, value_name = "URL")]
    pub actor: Option<String>,
    /// Refresh live until interrupted (a server-streaming watch).
    #[arg(long)]
    pub watch: bool,
    /// Seconds between refreshes with --watch (at least 0.1).
    #[arg(long, value_name = "SECS", default_value = "2", value_parser = seconds)]
    pub interval: Duration,
    /// Print one JSON object (per refresh with --watch) instead of a table; the learner's
    /// includes the whole learning curve.
    #[arg(long)]
    pub json: bool,
    /// Seconds to wait for the connection and the first answer.
    #[arg(long, value_name = "SECS", default_value = "10", value_parser = seconds)]
    pub timeout: Duration,
    #[command(flatten)]
    pub token: TokenArgs,
    #[command(flatten)]
    pub tls: ClientTlsArgs,
}

fn seconds(text: &str) -> Result<Duration, String> {
    let secs: f64 = text
        .parse()
        .map_err(|e| format!("`{text}` is not a number of seconds: {e}"))?;
    Duration::try_from_secs_f64(secs).map_err(|e| format!("`{text}` seconds: {e}"))
}

type Client = pb::status_client::StatusClient<InterceptedService<Channel, BearerToken>>;

/// What answered a status request.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Kind {
    Learner,
    Actor,
}

impl Kind {
    fn of(status: &pb::NodeStatus) -> Option<Self> {
        match status.node {
            Some(Node::Learner(_)) => Some(Self::Learner),
            Some(Node::Actor(_)) => Some(Self::Actor),
            None => None,
        }
    }
}

/// Refuses an answer from another kind of node than the flag named: `--actor` pointed at a
/// learner's port (or `--learner` at an actor's) would otherwise show the wrong node's table
/// under the right flag.
fn check_kind(url: &str, expected: Kind, status: &pb::NodeStatus) -> Result<()> {
    match (expected, Kind::of(status)) {
        (Kind::Actor, Some(Kind::Learner)) => bail!(
            "{url} answers as a learner, not an actor: use --learner {url} for the learner's \
             status, or give an actor's --status-listen address to --actor"
        ),
        (Kind::Learner, Some(Kind::Actor)) => bail!(
            "{url} answers as an actor, not a learner: use --actor {url} for the actor's status"
        ),
        _ => Ok(()),
    }
}

pub fn run(args: &StatusArgs) -> Result<()> {
    let (url, expected) = match (&args.actor, &args.learner) {
        (Some(actor), _) => (actor.as_str(), Kind::Actor),
        (None, learner) => (learner.as_deref().unwrap_or(DEFAULT_LEARNER), Kind::Learner),
    };
    let token = args.token.token()?;
    let tls = args.tls.client_tls()?;
    let endpoint = endpoint(url, tls.as_ref())?
        .connect_timeout(args.timeout)
        .tcp_nodelay(true);
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("starting the async runtime")?;
    runtime.block_on(async {
        let channel = tokio::time::timeout(args.timeout, endpoint.connect())
            .await
            .map_err(|_| anyhow::anyhow!("no connection to {url} within {:?}", args.timeout))?
            .with_context(|| format!("connecting to {url}"))?;
        let mut client =
            pb::status_client::StatusClient::with_interceptor(channel, BearerToken(token));
        let max_evaluations = if args.json { 0 } else { TABLE_EVALUATIONS };
        if args.watch {
            watch(&mut client, args, url, expected, max_evaluations).await
        } else {
            let request = pb::GetStatusRequest { max_evaluations };
            let status = tokio::time::timeout(args.timeout, client.get_status(request))
                .await
                .map_err(|_| anyhow::anyhow!("no answer from {url} within {:?}", args.timeout))?
                .map_err(|s| status_error(url, &s))?
                .into_inner();
            check_kind(url, expected, &status)?;
            print(&status, args.json, false)
        }
    })
}

async fn watch(
    client: &mut Client,
    args: &StatusArgs,
    url: &str,
    expected: Kind,
    max_evaluations: u32,
) -> Result<()> {
    let interval_ms = u32::try_from(args.interval.as_millis()).unwrap_or(u32::MAX);
    let request = pb::WatchStatusRequest {
        interval_ms: interval_ms.max(100),
        max_evaluations,
    };
    let mut stream = client
        .watch_status(request)
        .await
        .map_err(|s| status_error(url, &s))?
        .into_inner();
    let clear = !args.json && std::io::stdout().is_terminal();
    loop {
        tokio::select! {
            next = stream.message() => match next {
                Ok(Some(status)) => {
                    check_kind(url, expected, &status)?;
                    print(&status, args.json, clear)?;
                }
                Ok(None) => return Ok(()),
                Err(s) => bail!("the status stream ended: {}", s.message()),
            },
            _ = tokio::signal::ctrl_c() => return Ok(()),
        }
    }
}

fn status_error(url: &str, status: &tonic::Status) -> anyhow::Error {
    anyhow::anyhow!("{url} answered {:?}: {}", status.code(), status.message())
}

fn print(status: &pb::NodeStatus, json: bool, clear: bool) -> Result<()> {
    let text = if json {
        serde_json::to_string(status)? + "\n"
    } else {
        match &status.node {
            Some(Node::Learner(l)) => learner_table(l),
            Some(Node::Actor(a)) => actor_table(a),
            None => bail!("the server sent an empty status"),
        }
    };
    let mut out = std::io::stdout().lock();
    if clear {
        // Home and clear: the table redraws in place.
        out.write_all(b"\x1b[H\x1b[2J")?;
    }
    out.write_all(text.as_bytes())?;
    if !json && !clear {
        out.write_all(b"\n")?;
    }
    out.flush()?;
    Ok(())
}

/// `1h 02m`, `3m 04s`, `5.2s`.
fn duration(secs: f64) -> String {
    if !secs.is_finite() || secs < 0.0 {
        return "-".into();
    }
    let whole = secs as u64;
    if whole >= 3600 {
        format!("{}h {:02}m", whole / 3600, whole % 3600 / 60)
    } else if whole >= 60 {
        format!("{}m {:02}s", whole / 60, whole % 60)
    } else {
        format!("{secs:.1}s")
    }
}

/// A rate with a precision that suits its size.
fn rate(per_s: f64) -> String {
    if per_s >= 100.0 {
        format!("{per_s:.0}")
    } else {
        format!("{per_s:.1}")
    }
}

fn optional(value: Option<f32>) -> String {
    value.map_or_else(|| "-".into(), |v| format!("{v:.4}"))
}

fn percent(part: u64, whole: u64) -> String {
    if whole == 0 {
        "-".into()
    } else {
        format!("{:.1}%", 100.0 * part as f64 / whole as f64)
    }
}

/// Left-aligned columns, two spaces apart.
fn table(out: &mut String, rows: &[Vec<String>]) {
    let columns = rows.iter().map(Vec::len).max().unwrap_or(0);
    let widths: Vec<usize> = (0..columns)
        .map(|c| {
            rows.iter()
                .filter_map(|r| r.get(c))
                .map(|cell| cell.chars().count())
                .max()
                .unwrap_or(0)
        })
        .collect();
    for row in rows {
        let mut line = String::new();
        for (c, cell) in row.iter().enumerate() {
            if c + 1 == row.len() {
                line.push_str(cell);
            } else {
                let _ = write!(line, "{cell:<width$}  ", width = widths[c]);
            }
        }
        out.push_str(line.trim_end());
        out.push('\n');
    }
}

fn learner_table(s: &pb::LearnerStatus) -> String {
    let mut out = String::new();
    let digest: String = s.run_config_digest.chars().take(12).collect();
    let _ = writeln!(
        out,
        "learner  {}  env {}  levels {}  algo {}  seed {}  run {digest}  uptime {}",
        s.state,
        s.env,
        s.levels,
        if s.algo.is_empty() { "hac" } else { &s.algo },
        s.seed,
        duration(s.uptime_seconds)
    );
    if !s.trouble.is_empty() {
        let _ = writeln!(out, "trouble: {}", s.trouble);
    }
    let _ = writeln!(
        out,
        "weights v{}  episodes {}/{} (success {})  env steps {}  transitions {}  batches {}  duplicates {}",
        s.weights_version,
        s.episodes,
        s.episode_budget,
        percent(s.successes, s.episodes),
        s.env_steps,
        s.transitions,
        s.batches,
        s.duplicates
    );
    let _ = writeln!(
        out,
        "rates over {}: {} transitions/s  {} batches/s  {} episodes/s  {} env steps/s  {} updates/s",
        duration(s.rates_window_seconds),
        rate(s.transitions_per_second),
        rate(s.batches_per_second),
        rate(s.episodes_per_second),
        rate(s.env_steps_per_second),
        rate(s.updates_per_second)
    );
    out.push('\n');
    let mut rows = vec![
        [
            "level",
            "updates",
            "updates/s",
            "critic loss",
            "actor loss",
            "mean Q",
            "replay",
            "fill",
            "shards",
            "deficit",
            "trainer wait",
            "ingest waits",
            "diverged",
        ]
        .map(String::from)
        .to_vec(),
    ];
    for l in &s.level_status {
        let shards: Vec<String> = l.shard_sizes.iter().map(u64::to_string).collect();
        rows.push(vec![
            l.level.to_string(),
            l.updates.to_string(),
            rate(l.updates_per_second),
            optional(l.critic_loss),
            optional(l.actor_loss),
            optional(l.mean_q),
            format!("{}/{}", l.replay_size, l.replay_capacity),
            percent(l.replay_size, l.replay_capacity),
            shards.join(" "),
            format!("{:.1}", l.update_deficit),
            duration(l.trainer_wait_seconds),
            format!("{} ({})", l.ingest_waits, duration(l.ingest_wait_seconds)),
            l.diverged_updates.to_string(),
        ]);
    }
    table(&mut out, &rows);
    out.push('\n');
    let rejected: Vec<String> = s
        .rejected
        .iter()
        .filter(|r| r.count > 0)
        .map(|r| format!("{} {}", r.reason, r.count))
        .collect();
    let _ = writeln!(
        out,
        "rejected: {}",
        if rejected.is_empty() {
            "none".into()
        } else {
            rejected.join(", ")
        }
    );
    let _ = writeln!(
        out,
        "actor rate limit: {} messages held back ({})",
        s.actor_rate_limit_waits,
        duration(s.actor_rate_limit_wait_seconds)
    );
    if s.episodes_in_flight > 0 {
        let _ = writeln!(
            out,
            "episode turns: at most {} in flight; {} held, {} waiting, {} granted, {} expired",
            s.episodes_in_flight, s.turns_held, s.turns_waiting, s.turns_granted, s.turns_expired
        );
    }
    match &s.wal {
        Some(w) => {
            let _ = writeln!(
                out,
                "write-ahead log: {} in {} segments, {} of {} records durable, {} commits (last {}){}",
                bytes(w.bytes),
                w.segments,
                w.committed,
                w.appended,
                w.commits,
                duration(w.last_commit_seconds),
                if w.failed { "  FAILED" } else { "" }
            );
        }
        None => out.push_str("write-ahead log: off (durable = acknowledged)\n"),
    }
    out.push('\n');
    if s.actors.is_empty() {
        out.push_str("actors: none registered\n");
    } else {
        let mut rows = vec![
            [
                "actor",
                "role",
                "host",
                "transport",
                "incarnation",
                "connected",
                "last seen",
                "episodes",
                "env steps/s",
                "weights",
                "lag",
                "acked",
                "durable",
            ]
            .map(String::from)
            .to_vec(),
        ];
        for a in &s.actors {
            rows.push(vec![
                a.actor_id.clone(),
                a.role.clone(),
                a.hostname.clone(),
                if a.transport.is_empty() {
                    "-".into()
                } else {
                    a.transport.clone()
                },
                a.incarnation.to_string(),
                duration(a.connected_seconds),
                format!("{} ago", duration(a.last_seen_seconds)),
                a.episodes.to_string(),
                rate(a.env_steps_per_second),
                format!("v{}", a.weights_version),
                a.weights_lag.to_string(),
                a.stored_through.to_string(),
                a.durable_through.to_string(),
            ]);
        }
        table(&mut out, &rows);
    }
    out.push('\n');
    if s.evaluations.is_empty() {
        out.push_str("evaluations: none yet\n");
    } else {
        let _ = writeln!(
            out,
            "evaluations (last {} of {}):",
            s.evaluations.len(),
            s.evaluations_total
        );
        let mut rows = vec![
            ["round", "episodes", "env steps", "success", "elapsed"]
                .map(String::from)
                .to_vec(),
        ];
        for e in &s.evaluations {
            rows.push(vec![
                e.round.to_string(),
                e.episodes.to_string(),
                e.env_steps.to_string(),
                format!("{:.1}%", 100.0 * e.success_rate),
                duration(e.elapsed_seconds),
            ]);
        }
        table(&mut out, &rows);
    }
    out
}

/// A byte count in KiB, MiB or GiB.
fn bytes(n: u64) -> String {
    let n = n as f64;
    if n >= f64::from(1 << 30) {
        format!("{:.1} GiB", n / f64::from(1 << 30))
    } else if n >= f64::from(1 << 20) {
        format!("{:.1} MiB", n / f64::from(1 << 20))
    } else {
        format!("{:.1} KiB", n / 1024.0)
    }
}

fn actor_table(a: &pb::ActorStatus) -> String {
    let mut out = String::new();
    let _ = writeln!(
        out,
        "actor {}  {}  role {}  host {}  uptime {}",
        a.actor_id,
        a.state,
        a.role,
        a.hostname,
        duration(a.uptime_seconds)
    );
    let _ = writeln!(
        out,
        "learner {}  transport {}  incarnation {}  reconnects {}  unacked {}  undurable {}",
        a.learner,
        if a.transport.is_empty() {
            "-"
        } else {
            &a.transport
        },
        a.incarnation,
        a.reconnects,
        a.unacked,
        a.undurable
    );
    let _ = writeln!(
        out,
        "transitions sent {}  durable {}",
        a.sent_transitions, a.durable_transitions
    );
    let _ = writeln!(
        out,
        "episodes {} (success {})  env steps {} ({}/s over {})  evaluations {}",
        a.episodes,
        percent(a.successes, a.episodes),
        a.env_steps,
        rate(a.env_steps_per_second),
        duration(a.rates_window_seconds),
        a.evaluations
    );
    let _ = writeln!(
        out,
        "weights v{} (learner v{}, lag {})",
        a.weights_version, a.learner_weights_version, a.weights_lag
    );
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn durations_and_rates_read_well() {
        assert_eq!(duration(5.25), "5.2s");
        assert_eq!(duration(184.0), "3m 04s");
        assert_eq!(duration(3.0 * 3600.0 + 120.0), "3h 02m");
        assert_eq!(duration(f64::NAN), "-");
        assert_eq!(rate(1234.4), "1234");
        assert_eq!(rate(3.25), "3.2");
        assert_eq!(percent(1, 0), "-");
        assert_eq!(percent(1, 4), "25.0%");
    }

    #[test]
    fn the_learner_table_shows_levels_actors_rejections_and_evaluations() {
        let status = pb::LearnerStatus {
            state: "serving".into(),
            env: "pendulum".into(),
            levels: 2,
            run_config_digest: "0123456789abcdef".into(),
            episodes: 10,
            successes: 5,
            episode_budget: 100,
            level_status: vec![pb::LevelStatus {
                level: 0,
                updates: 400,
                replay_size: 30,
                replay_capacity: 60,
                shard_sizes: vec![10, 20],
                critic_loss: Some(0.5),
                ..pb::LevelStatus::default()
            }],
            rejected: vec![
                pb::RejectCount {
                    reason: "malformed".into(),
                    count: 0,
                },
                pb::RejectCount {
                    reason: "unauthenticated".into(),
                    count: 3,
                },
            ],
            actors: vec![pb::RegisteredActor {
                actor_id: "trainer-0".into(),
                role: "trainer".into(),
                transport: "grpc".into(),
                weights_version: 7,
                weights_lag: 2,
                ..pb::RegisteredActor::default()
            }],
            evaluations: vec![pb::EvaluationPoint {
                round: 1,
                episodes: 50,
                success_rate: 0.9,
                ..pb::EvaluationPoint::default()
            }],
            evaluations_total: 4,
            ..pb::LearnerStatus::default()
        };
        let text = learner_table(&status);
        for expected in [
            "learner  serving  env pendulum  levels 2  algo hac  seed 0",
            "run 0123456789ab ",
            "episodes 10/100 (success 50.0%)",
            "30/60",
            "50.0%",
            "10 20",
            "0.5000",
            "rejected: unauthenticated 3\n",
            "trainer-0",
            "v7",
            "evaluations (last 1 of 4):",
            "90.0%",
        ] {
            assert!(text.contains(expected), "{expected:?} in\n{text}");
        }
        // Columns line up: the header's "updates" starts where the row's "400" does.
        let header = text.lines().find(|l| l.starts_with("level")).unwrap();
        let row = text.lines().find(|l| l.starts_with("0 ")).unwrap();
        assert_eq!(header.find("updates"), row.find("400"));
    }

    #[test]
    fn json_output_is_one_object_keyed_by_the_node_kind() {
        let status = pb::NodeStatus {
            node: Some(Node::Actor(pb::ActorStatus {
                actor_id: "a".into(),
                episodes: 3,
                ..pb::ActorStatus::default()
            })),
        };
        let value: serde_json::Value =
            serde_json::from_str(&serde_json::to_string(&status).unwrap()).unwrap();
        assert_eq!(value["actor"]["actor_id"], "a");
        assert_eq!(value["actor"]["episodes"], 3);
        assert!(actor_table(&pb::ActorStatus::default()).contains("transport -"));
    }
}
