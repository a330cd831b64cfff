//! The actor daemon: connects to a learner service over gRPC (and, on the learner's host, shared
//! memory: `--transport`), registers, and runs the actor loop
//! ([`hac_actor::run_actor`]) as a trainer (rollouts streamed as transitions) or an evaluator
//! (greedy test rounds reported to the learning curve).
//!
//! [`ActorArgs`] and [`run`] are shared by the `hac-actor` binary and `hac actor`; the config
//! file's `[actor]` table holds the same settings ([`config_section`]). The actor exits
//! 0 when the learner says the run is finished, after `--max-episodes`, or after SIGINT/SIGTERM
//! (checked between episodes; unacknowledged messages get `--flush-timeout` to reach the
//! learner). A second signal exits at once.
//!
//! [`ops`]: the token and TLS it connects with, and its own status (`--status-listen`: the
//! `hac.v1.Status` service, health `SERVING` while registered and acting, reflection) and
//! Prometheus metrics (`--metrics-listen`).

pub mod ops;

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use anyhow::{Context, Result, bail};
use clap::Args as _;
use hac_actor::{ActorOptions, ActorSummary, run_actor};
use hac_proto::ActorRole;
use hac_run::daemon::{ConfigArgs, Section};
use hac_transport::grpc::{GrpcLink, GrpcLinkOptions};
use hac_transport::shm::{self, Overflow, ShmLink, ShmLinkOptions, ShmMode};
use hac_transport::{ActorLink, LinkError};

/// What the actor does.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Role {
    /// Training episodes with the behaviour policy, streamed to the learner.
    Trainer,
    /// Greedy test rounds of the newest weights, reported to the learning curve.
    Evaluator,
}

/// The actor daemon's flags (also `hac actor`'s).
#[derive(Debug, clap::Args)]
pub struct ActorArgs {
    /// The learner service, as `http://host:port`.
    #[arg(long, env = "HAC_LEARNER", default_value = "http://127.0.0.1:50051")]
    pub learner: String,
    /// This actor's name, unique among live actors [default: <hostname>-<pid>].
    #[arg(long, env = "HAC_ACTOR_ID")]
    pub id: Option<String>,
    /// What the actor does.
    #[arg(long, value_enum, env = "HAC_ACTOR_ROLE", default_value_t = Role::Trainer)]
    pub role: Role,
    /// Trainers: run a greedy test round after every N training episodes and report it.
    /// Evaluators: evaluate whenever the learner has trained N more episodes [default: trainers
    /// never; evaluators the run's exploration_episodes].
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u64).range(1..))]
    pub eval_every: Option<u64>,
    /// Trainers: stop after N training episodes [default: when the run finishes].
    #[arg(long, value_name = "N")]
    pub max_episodes: Option<u64>,
    /// Transitions per batch sent (capped by the learner's limit).
    #[arg(long, value_name = "N", default_value_t = 1024,
          value_parser = clap::value_parser!(u64).range(1..))]
    pub batch_transitions: u64,
    /// Most messages sent and not yet acknowledged by the learner; sending blocks beyond it
    /// (the learner's backpressure).
    #[arg(long, value_name = "N", default_value_t = 256,
          value_parser = clap::value_parser!(u64).range(1..))]
    pub window: u64,
    /// Trainers: before each episode, wait for the updates this actor's episodes earned (the
    /// paper's schedule exactly with a single trainer; slower with several).
    #[arg(long)]
    pub lockstep: bool,
    /// Give up if no usable weights arrive for this many seconds [default: wait as long as it
    /// takes].
    #[arg(long, value_name = "SECS", value_parser = seconds)]
    pub weights_timeout: Option<Duration>,
    /// Give up once the learner has not answered for this many seconds (reconnects back off
    /// exponentially up to 5 s meanwhile).
    #[arg(long, value_name = "SECS", default_value = "300", value_parser = seconds)]
    pub give_up_after: Duration,
    /// Seconds to wait, after an interrupt, for the learner to acknowledge what was sent.
    #[arg(long, value_name = "SECS", default_value = "10", value_parser = seconds)]
    pub flush_timeout: Duration,
    #[command(flatten)]
    pub ops: ops::OpsArgs,
    #[command(flatten)]
    pub config: ConfigArgs,
    #[command(flatten)]
    pub transport: TransportArgs,
}

/// The actor's table of the config file, `[actor]`: every flag of [`ActorArgs`] but the
/// command-line-only ones ([`hac_run::daemon`]).
pub fn config_section() -> Section {
    Section::of_flags(
        "actor",
        ActorArgs::augment_args(clap::Command::new("actor")),
    )
}

/// How the actor reaches the learner (docs/SHM.md).
#[derive(Debug, Clone, clap::Args)]
pub struct TransportArgs {
    /// grpc; shm (shared memory: fails unless the learner serves it to this host); auto (shared
    /// memory when the learner offers it to this host at registration, else gRPC).
    #[arg(long = "transport", value_enum, env = "HAC_TRANSPORT", default_value_t = Transport::Auto)]
    pub transport: Transport,
    /// Shared memory: when the window of unacknowledged messages is full, block (the learner's
    /// backpressure) or drop new transition batches (counted and logged; episode summaries
    /// always wait).
    #[arg(long = "shm-overflow", value_enum, env = "HAC_SHM_OVERFLOW",
          default_value_t = ShmOverflow::Block)]
    pub overflow: ShmOverflow,
}

/// `--transport`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Transport {
    Grpc,
    Shm,
    Auto,
}

/// `--shm-overflow`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum ShmOverflow {
    Block,
    Drop,
}

/// A flag value in seconds (fractions allowed).
fn seconds(text: &str) -> Result<Duration, String> {
    let secs: f64 = text
        .parse()
        .map_err(|e| format!("`{text}` is not a number of seconds: {e}"))?;
    Duration::try_from_secs_f64(secs).map_err(|e| format!("`{text}` seconds: {e}"))
}

/// Runs one actor until the run finishes, its own limit, or a signal; see the crate docs.
pub fn run(args: ActorArgs) -> Result<()> {
    if let Some(path) = &args.config.path {
        // The run keys are the learner's to use, but a mistake in them is caught here too.
        hac_run::config::resolve(Some(path), hac_run::config::Overrides::default())?;
    }
    if args.config.print {
        // The run itself comes from the learner at registration.
        if let Some(table) = &args.config.resolved {
            hac_run::out!("{}", table.to_toml());
        }
        return Ok(());
    }
    let hostname = hostname();
    let actor_id = args
        .id
        .clone()
        .unwrap_or_else(|| format!("{hostname}-{}", std::process::id()));
    if actor_id.trim().is_empty() {
        bail!("invalid value for --id: the actor id must not be empty");
    }
    let transport = args.transport.transport;
    let options = ActorOptions {
        actor_id: actor_id.clone(),
        role: match args.role {
            Role::Trainer => ActorRole::Trainer,
            Role::Evaluator => ActorRole::Evaluator,
        },
        hostname,
        transports: match transport {
            Transport::Grpc => vec!["grpc".into()],
            Transport::Shm | Transport::Auto => vec!["grpc".into(), shm::TRANSPORT.into()],
        },
        lockstep: args.lockstep,
        eval_every_episodes: args.eval_every,
        max_episodes: args.max_episodes,
        weights_timeout: args.weights_timeout,
        batch_transitions: usize::try_from(args.batch_transitions)
            .context("invalid value for --batch-transitions")?,
        resume: None,
    };
    let ops = args.ops.resolve()?;
    let link_options = GrpcLinkOptions {
        window: usize::try_from(args.window).context("invalid value for --window")?,
        give_up_after: args.give_up_after,
        token: ops.token.clone(),
        tls: ops.client_tls.clone(),
        ..GrpcLinkOptions::default()
    };
    let interrupt = hac_run::signals::interrupt_flag()?;
    let board = Arc::new(ops::Board::new(
        actor_id.clone(),
        hac_transport::grpc::role_name(options.role),
        options.hostname.clone(),
        args.learner.clone(),
        interrupt.clone(),
    ));
    let servers = ops::OpsServers::start(&ops, board.clone())?;
    tracing::info!(actor = %actor_id, learner = %args.learner, role = ?args.role, ?transport, "actor starting");
    let result = match transport {
        Transport::Grpc => GrpcLink::connect(&args.learner, link_options)
            .context("invalid value for --learner")
            .and_then(|mut link| {
                drive(
                    &mut ops::Observed::new(&mut link, &board),
                    &options,
                    &interrupt,
                    &args,
                )
            }),
        Transport::Shm | Transport::Auto => {
            let shm_options = ShmLinkOptions {
                mode: if transport == Transport::Shm {
                    ShmMode::Require
                } else {
                    ShmMode::Prefer
                },
                window: link_options.window,
                max_batch_transitions: options.batch_transitions,
                overflow: match args.transport.overflow {
                    ShmOverflow::Block => Overflow::Block,
                    ShmOverflow::Drop => Overflow::Drop,
                },
                give_up_after: args.give_up_after,
                ..ShmLinkOptions::default()
            };
            ShmLink::connect(&args.learner, link_options, shm_options)
                .context("invalid value for --learner")
                .and_then(|mut link| {
                    let summary = drive(
                        &mut ops::Observed::new(&mut link, &board),
                        &options,
                        &interrupt,
                        &args,
                    );
                    let (batches, transitions) = link.dropped();
                    if batches > 0 {
                        tracing::warn!(
                            dropped_batches = batches,
                            dropped_transitions = transitions,
                            "transition batches dropped while the learner was behind (--shm-overflow drop)"
                        );
                    }
                    summary
                })
        }
    };
    board.stopping();
    if let Some(servers) = servers {
        servers.stop();
    }
    let summary = result?;
    let link = board.snapshot();
    tracing::info!(
        actor = %actor_id,
        incarnation = summary.incarnation,
        sent_transitions = link.sent_transitions,
        durable_transitions = link.durable_transitions,
        undurable = link.undurable,
        episodes = summary.episodes,
        env_steps = summary.env_steps,
        evaluations = summary.evaluations,
        weights_version = summary.weights_version,
        run_finished = summary.run_finished,
        interrupted = interrupt.load(Ordering::Relaxed),
        "actor stopped"
    );
    Ok(())
}

/// Runs the actor loop over `link`, then gives what is unacknowledged `--flush-timeout` to reach
/// the learner (unless the run is over).
fn drive(
    link: &mut dyn ActorLink,
    options: &ActorOptions,
    interrupt: &AtomicBool,
    args: &ActorArgs,
) -> Result<ActorSummary> {
    let summary = run_actor(link, options, interrupt, |e| {
        tracing::info!(
            weights_version = e.weights_version,
            trained_episodes = e.trained_episodes,
            success = e.success_rate,
            "evaluation reported"
        );
    })
    .with_context(|| format!("actor {}", options.actor_id))?;
    if !summary.run_finished {
        // Until durable: a learner killed after acknowledging could otherwise lose the last
        // messages of an actor that is gone and cannot resend them.
        match link.flush_durable(args.flush_timeout) {
            Ok(()) | Err(LinkError::Finished) => {}
            Err(e) => tracing::warn!(error = %e, "stopping with messages unacknowledged"),
        }
    }
    Ok(summary)
}

/// This host's name as the kernel knows it (no extra dependency), or `actor` if unreadable.
fn hostname() -> String {
    std::fs::read_to_string("/proc/sys/kernel/hostname")
        .ok()
        .or_else(|| std::env::var("HOSTNAME").ok())
        .map(|name| name.trim().to_string())
        .filter(|name| !name.is_empty())
        .unwrap_or_else(|| "actor".into())
}
