//! The learner daemon: one [`Learner`] served over gRPC to actors on any host, until the run
//! finishes or a signal stops it; then the trained agent is saved to a run directory.
//!
//! - [`LearnerArgs`] and [`run`]: the `hac-learner` binary and `hac learner` share them.
//! - [`config`]: the run configuration's resolution (defaults, TOML file, `HAC_*` variables,
//!   flags), the same source as `hac train`'s.
//! - `run_dir`: what the learner writes (`config.toml`, `curve.csv` as evaluations arrive, and at
//!   the end `weights/level<i>.safetensors` and `summary.json`).
//! - [`ops`]: metrics, the per-actor message rate limit, token and TLS flags ([`OpsArgs`]).
//! - [`checkpoint`]: checkpoints on a timer, on SIGUSR1 and at shutdown; `--resume`.
//!
//! Life of a run: validate the config (the whole file: [`config_section`]; token and TLS files),
//! start the learner (or resume it from a checkpoint), bind `--listen` and print
//! `listening on <addr>` (one line on stdout, for scripts; then `metrics on <addr>` with
//! `--metrics-listen`), serve (health `SERVING`; with `--shm`, shared memory for actors on this host as well, see
//! `hac_transport::shm`), checkpointing as configured. When the run
//! finishes by itself (episode budget or `stop_at`), or on SIGINT/SIGTERM (which finishes the run
//! at once), health turns `NOT_SERVING` and the learner keeps serving for `--grace-period` so
//! that actors receive the final weights and stop; then it stops accepting, ends open streams,
//! drains connections (at most `--drain-timeout`), saves the run directory and a final
//! checkpoint, and exits 0. A second signal exits at once.

// The same config resolution as `hac train`, so that every entry point resolves a run identically.
pub use hac_run::config;
pub mod checkpoint;
pub mod ops;
mod run_dir;

use std::io::Write as _;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use anyhow::{Context, Result};
use clap::Args as _;
use hac_agent::RunConfig;
use hac_learner::{Learner, LearnerOptions};
use hac_run::daemon::{ConfigArgs, Section};
use hac_serve::grpc::{ServerOptions, serve};
use hac_serve::shm::{ShmServer, ShmServerOptions};
use hac_transport::shm::Namespace;
use tokio::net::TcpListener;
use tokio::signal::unix::{Signal, SignalKind, signal};
use tokio::sync::watch;

use hac_run::run_dir::RunDir;
pub use ops::OpsArgs;

use crate::checkpoint::{CheckpointArgs, Checkpoints, Start};

/// The learner daemon's flags (also `hac learner`'s).
#[derive(Debug, clap::Args)]
pub struct LearnerArgs {
    /// Algorithm: hac, or hiro (the HAC paper's baseline; 2 levels only) [default: hac].
    #[arg(long, env = "HAC_ALGO")]
    pub algo: Option<hac_core::hiro::Algo>,
    /// Built-in environment: pendulum, ur5-reacher, mountain-car, cartpole, pick-and-place
    /// [default: pendulum].
    #[arg(long, env = "HAC_ENV")]
    pub env: Option<String>,
    /// Number of levels; 1 is the flat DDPG + HER baseline [default: 2].
    #[arg(long, env = "HAC_LEVELS")]
    pub levels: Option<usize>,
    /// Seed of every random stream; actors get seeds derived from it [default: 0].
    #[arg(long, env = "HAC_SEED")]
    pub seed: Option<u64>,
    /// Training episodes in total, over all actors [default: 1000].
    #[arg(long, env = "HAC_EPISODES")]
    pub episodes: Option<u64>,
    /// Finish early once an evaluation reaches this success rate (e.g. 0.9).
    #[arg(long, env = "HAC_STOP_AT")]
    pub stop_at: Option<f32>,
    /// Replay shards per level [default: 1].
    #[arg(long, env = "HAC_REPLAY_SHARDS")]
    pub replay_shards: Option<usize>,
    /// Episode budget in primitive actions, replacing the environment's (see `hac env
    /// describe`); actors get it with the run's configuration.
    #[arg(long, env = "HAC_MAX_ACTIONS")]
    pub max_actions: Option<usize>,
    #[command(flatten)]
    pub config: ConfigArgs,
    /// Override one agent hyperparameter, VALUE in TOML syntax (repeatable), e.g.
    /// `--set horizon=20`. Also read from HAC_AGENT_<KEY>.
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub set: Vec<String>,
    /// Address to serve actors on; port 0 picks a free port. Once bound, the address is printed
    /// on stdout as one line `listening on <addr>`.
    #[arg(long, env = "HAC_LISTEN", default_value = "127.0.0.1:50051")]
    pub listen: SocketAddr,
    /// Run directory: config.toml, curve.csv (a row per evaluation), and at the end
    /// weights/level<i>.safetensors and summary.json [default: runs/<env>-<levels>l-seed<seed>;
    /// HIRO: runs/<env>-hiro-2l-seed<seed>].
    #[arg(long, env = "HAC_OUT")]
    pub out: Option<PathBuf>,
    /// Replace a run already in the run directory.
    #[arg(long)]
    pub overwrite: bool,
    /// Largest gRPC message accepted (larger ones are refused as oversized) or sent, in bytes.
    #[arg(long, env = "HAC_MAX_MESSAGE_BYTES", default_value_t = 64 << 20,
          value_parser = clap::value_parser!(u64).range(1024..=(1 << 31)))]
    pub max_message_bytes: u64,
    /// Largest transition batch accepted, in transitions (actors learn it at registration)
    /// [default: 4096].
    #[arg(long, value_parser = clap::value_parser!(u64).range(1..=(1 << 20)))]
    pub max_batch_transitions: Option<u64>,
    /// Publish weights after every level did this many more updates (besides whenever every
    /// level has caught up with the episodes ingested) [default: the run's updates_per_episode].
    #[arg(long, value_parser = clap::value_parser!(u64).range(1..))]
    pub publish_every_updates: Option<u64>,
    /// Actors refuse to act on weights more than this many versions behind the newest
    /// [default: 16].
    #[arg(long)]
    pub max_weights_lag: Option<u64>,
    /// Episode turns: at most this many training episodes played or waiting to be trained on at
    /// once, over all trainers, which ask for a turn before each episode (granted in the order
    /// asked). 1 reproduces the embedded schedule with any number of actors; 0 lets every
    /// trainer play whenever its previous episode is acknowledged, acting on weights that miss
    /// the episodes the others have in flight [default: 0].
    #[arg(long, value_parser = clap::value_parser!(u32).range(0..=1024))]
    pub episodes_in_flight: Option<u32>,
    /// Episode turns: seconds a granted turn is held for a trainer whose episode has not arrived
    /// (one that died or stalls delays the others at most this long); above the longest episode.
    #[arg(long, value_name = "SECS", default_value = "60", value_parser = seconds)]
    pub turn_lease: Duration,
    /// Seconds after which an actor not heard from (no message, turn request or evaluation) is
    /// dropped from the registry and from status; if it comes back it registers again.
    #[arg(long, value_name = "SECS", default_value = "600", value_parser = seconds)]
    pub forget_actors_after: Duration,
    /// How far ingest may run ahead of training before actors are held back, in episodes'
    /// worth of updates (the rate limiter's error buffer) [default: 2].
    #[arg(long, value_parser = at_least_one)]
    pub error_buffer_episodes: Option<f64>,
    /// Threads updating the networks, shared among the levels (which update in parallel; each
    /// level gets at least one): size it from `hac bench update`. The weights do not depend on
    /// it [default: the cores available to the process].
    #[arg(long, value_parser = clap::value_parser!(u64).range(1..=1024))]
    pub learner_threads: Option<u64>,
    /// Seconds to keep serving after the run finishes (by itself, or on SIGINT/SIGTERM), so that
    /// every actor receives the final weights and stops; health is NOT_SERVING meanwhile.
    #[arg(long, value_name = "SECS", default_value = "2", value_parser = seconds)]
    pub grace_period: Duration,
    /// Seconds to wait at shutdown for actors' connections to close.
    #[arg(long, value_name = "SECS", default_value = "5", value_parser = seconds)]
    pub drain_timeout: Duration,
    #[command(flatten)]
    pub ops: OpsArgs,
    #[command(flatten)]
    pub checkpoint: CheckpointArgs,
    #[command(flatten)]
    pub shm: ShmArgs,
}

/// The learner's table of the config file, `[learner]`: every flag of [`LearnerArgs`] but the
/// run keys and the command-line-only ones ([`hac_run::daemon`]).
pub fn config_section() -> Section {
    Section::of_flags(
        "learner",
        LearnerArgs::augment_args(clap::Command::new("learner")),
    )
}

/// Shared memory beside gRPC (docs/SHM.md).
#[derive(Debug, Clone, clap::Args)]
pub struct ShmArgs {
    /// Also serve actors on this host over shared memory (iceoryx2, /dev/shm) beside gRPC;
    /// actors with `--transport auto` (their default) or `shm` use it [default: off].
    #[arg(long = "shm", env = "HAC_SHM")]
    pub enabled: bool,
    /// Shared memory: most actors attached at once (sizes the learner's share of /dev/shm;
    /// more actors fall back to gRPC).
    #[arg(long = "shm-max-actors", env = "HAC_SHM_MAX_ACTORS", value_name = "N",
          default_value_t = 32, value_parser = clap::value_parser!(u64).range(1..=1024))]
    pub max_actors: u64,
    /// Shared memory: messages each actor may have unacknowledged (sizes each actor's share of
    /// /dev/shm).
    #[arg(long = "shm-window", env = "HAC_SHM_WINDOW", value_name = "N",
          default_value_t = 32, value_parser = clap::value_parser!(u64).range(1..=4096))]
    pub window: u64,
}

impl ShmArgs {
    /// Starts the shared-memory server for the run served at `addr`, if enabled.
    fn start(&self, learner: &Arc<Learner>, addr: SocketAddr) -> Result<Option<ShmServer>> {
        if !self.enabled {
            return Ok(None);
        }
        let namespace = Namespace::for_run(&learner.status().run_config_digest, addr);
        let options = ShmServerOptions {
            max_actors: usize::try_from(self.max_actors).context("--shm-max-actors")?,
            window: usize::try_from(self.window).context("--shm-window")?,
            ..ShmServerOptions::default()
        };
        let server = ShmServer::start(learner.clone(), namespace, options)
            .context("serving shared memory (--shm)")?;
        Ok(Some(server))
    }
}

/// A flag value in seconds (fractions allowed).
fn seconds(text: &str) -> Result<Duration, String> {
    let secs: f64 = text
        .parse()
        .map_err(|e| format!("`{text}` is not a number of seconds: {e}"))?;
    Duration::try_from_secs_f64(secs).map_err(|e| format!("`{text}` seconds: {e}"))
}

fn at_least_one(text: &str) -> Result<f64, String> {
    match text.parse::<f64>() {
        Ok(x) if x.is_finite() && x >= 1.0 => Ok(x),
        Ok(x) => Err(format!("must be a number of at least 1, got {x}")),
        Err(e) => Err(format!("`{text}` is not a number: {e}")),
    }
}

impl LearnerArgs {
    fn resolve(&self) -> Result<RunConfig> {
        config::resolve(
            self.config.path.as_deref(),
            config::Overrides {
                algo: self.algo,
                env: self.env.clone(),
                levels: self.levels,
                seed: self.seed,
                episodes: self.episodes,
                stop_at: self.stop_at,
                replay_shards: self.replay_shards,
                max_actions: self.max_actions,
                set: self.set.clone(),
                hiro_settings_for_hiro_only: false,
            },
        )
    }

    fn learner_options(&self, run: &RunConfig) -> Result<LearnerOptions> {
        let mut options = LearnerOptions::for_run(run);
        if let Some(n) = self.max_batch_transitions {
            options.max_batch_transitions =
                usize::try_from(n).context("invalid value for --max-batch-transitions")?;
        }
        if let Some(n) = self.publish_every_updates {
            options.publish_every_updates = n;
        }
        if let Some(n) = self.max_weights_lag {
            options.max_weights_lag = n;
        }
        if let Some(n) = self.episodes_in_flight {
            options.episodes_in_flight = n;
        }
        options.turn_lease = self.turn_lease;
        options.forget_actors_after = self.forget_actors_after;
        if let Some(x) = self.error_buffer_episodes {
            options.error_buffer_episodes = x;
        }
        options.max_actor_messages_per_second = self.ops.max_actor_messages_per_second;
        if let Some(n) = self.learner_threads {
            options.learner_threads =
                usize::try_from(n).context("invalid value for --learner-threads")?;
        }
        options.validate()?;
        Ok(options)
    }

    fn server_options(&self) -> Result<ServerOptions> {
        Ok(ServerOptions {
            max_message_bytes: usize::try_from(self.max_message_bytes)
                .context("invalid value for --max-message-bytes")?,
            drain_timeout: self.drain_timeout,
            security: self.ops.security()?,
            shm_offer: None,
        })
    }
}

/// Runs the learner daemon until the run finishes or a signal stops it; see the crate docs.
pub fn run(args: LearnerArgs) -> Result<()> {
    let run = args.resolve()?;
    if args.config.print {
        hac_run::out!("{}", run.to_toml());
        if let Some(table) = &args.config.resolved {
            hac_run::out!("\n{}", table.to_toml());
        }
        return Ok(());
    }
    let mut options = args.learner_options(&run)?;
    let server_options = args.server_options()?;
    let out = args
        .out
        .clone()
        .unwrap_or_else(|| PathBuf::from("runs").join(run.run_name()));
    options.wal = args.checkpoint.wal(&out);
    // The log cut of the checkpoint resumed from: the log stays from there until newer
    // checkpoints replace it among those kept.
    let mut resumed_cut = None;
    let (learner, mut dir) = match checkpoint::start(&args.checkpoint, &out)? {
        Start::New { replace } => {
            let dir = RunDir::create(&out, &run, args.overwrite || replace)?;
            if !args.checkpoint.resume {
                // A new run: a log an earlier run left in the directory is not this run's.
                // (Resuming a run killed before its first checkpoint replays its log instead.)
                let wal = out.join(checkpoint::WAL_DIR);
                if wal.exists() {
                    std::fs::remove_dir_all(&wal).with_context(|| {
                        format!("removing the old write-ahead log {}", wal.display())
                    })?;
                }
            }
            (Learner::start(run, options)?, dir)
        }
        Start::Resume { checkpoint, name } => {
            let learner =
                Learner::resume(run.clone(), options, &checkpoint).with_context(|| {
                    format!(
                        "resuming from {}",
                        out.join("checkpoints").join(&name).display()
                    )
                })?;
            tracing::info!(
                checkpoint = %name,
                weights_version = checkpoint.weights_version(),
                episodes = checkpoint.episodes(),
                updates = ?checkpoint.updates(),
                evaluations = checkpoint.curve().len(),
                replay = checkpoint.has_replay(),
                "resuming the run"
            );
            resumed_cut = Some(checkpoint.wal_lsn());
            (learner, RunDir::resume(&out, &run, checkpoint.curve())?)
        }
        Start::Complete { reason } => {
            eprintln!(
                "nothing to resume: the run in {} is complete ({reason})",
                out.display()
            );
            return Ok(());
        }
    };
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .thread_name("hac-learner-io")
        .enable_all()
        .build()
        .context("starting the async runtime")?;
    let learner = Arc::new(learner);
    let mut checkpoints =
        runtime.block_on(async { Checkpoints::install(&args.checkpoint, &out, resumed_cut) })?;
    let served = runtime.block_on(serve_run(
        learner.clone(),
        &args,
        server_options,
        &mut dir,
        &mut checkpoints,
    ));
    // Ends every task still holding the learner (connections that outlived the drain).
    runtime.shutdown_timeout(Duration::from_secs(1));
    served?;
    let learner = Arc::into_inner(learner).context("the learner is still in use after shutdown")?;
    let elapsed = learner.elapsed();
    let finished = learner.shutdown();
    run_dir::record_new(&mut dir, &finished.curve, finished.best.as_deref())?;
    let summary = run_dir::finish(&dir, &finished, elapsed.as_secs_f64())?;
    checkpoints.write_final(&finished)?;
    tracing::info!(
        episodes = finished.status.episodes,
        transitions = finished.status.transitions,
        evaluations = summary.rounds,
        final_success = summary.final_success,
        out = %out.display(),
        "run saved"
    );
    Ok(())
}

/// SIGINT and SIGTERM, installed before the port is bound so that neither kills the process
/// uncleanly once it is serving.
struct Signals {
    interrupt: Signal,
    terminate: Signal,
}

impl Signals {
    fn install() -> Result<Self> {
        Ok(Self {
            interrupt: signal(SignalKind::interrupt()).context("installing signal handlers")?,
            terminate: signal(SignalKind::terminate()).context("installing signal handlers")?,
        })
    }

    async fn recv(&mut self) {
        tokio::select! {
            _ = self.interrupt.recv() => {}
            _ = self.terminate.recv() => {}
        }
    }
}

/// Serves until the run is over (plus the grace period) or a signal; then shuts the server down.
async fn serve_run(
    learner: Arc<Learner>,
    args: &LearnerArgs,
    mut options: ServerOptions,
    dir: &mut RunDir,
    checkpoints: &mut Checkpoints,
) -> Result<()> {
    let mut signals = Signals::install()?;
    let listener = TcpListener::bind(args.listen)
        .await
        .with_context(|| format!("binding --listen {}", args.listen))?;
    let addr = listener.local_addr().context("reading the bound address")?;
    let (stop, mut stopped) = watch::channel(false);
    let metrics = args.ops.start_metrics(&learner, stop.subscribe()).await?;
    // Named after the bound address: stopped (released) after the gRPC server below.
    let shm = args.shm.start(&learner, addr)?;
    options.shm_offer = shm.as_ref().map(ShmServer::offer);
    {
        let mut stdout = std::io::stdout().lock();
        writeln!(stdout, "listening on {addr}")?;
        if let Some((metrics_addr, _)) = &metrics {
            writeln!(stdout, "metrics on {metrics_addr}")?;
        }
        stdout.flush()?;
    }
    let tls = options.security.tls.is_some();
    let token = options.security.token.is_some();
    tracing::info!(%addr, tls, token, run = %learner.status().run_config_digest, "learner service listening");
    if let Some((metrics_addr, _)) = &metrics {
        tracing::info!(addr = %metrics_addr, path = "/metrics", "prometheus metrics served");
    }

    let server = tokio::spawn(serve(learner.clone(), listener, options, async move {
        // An error means the sender is gone: stop as well.
        let _ = stopped.wait_for(|&stop| stop).await;
    }));
    let mut weights = learner.weights().subscribe();
    let mut tick = tokio::time::interval(Duration::from_millis(250));
    let mut grace_until: Option<tokio::time::Instant> = None;
    let mut interrupted = false;
    loop {
        let grace_over = async {
            match grace_until {
                Some(at) => tokio::time::sleep_until(at).await,
                None => std::future::pending().await,
            }
        };
        tokio::select! {
            () = signals.recv() => {
                if interrupted {
                    tracing::warn!("second signal: exiting at once");
                    std::process::exit(130);
                }
                interrupted = true;
                if grace_until.is_some() {
                    tracing::info!("signal received: shutting down (a second signal exits at once)");
                    break;
                }
                tracing::info!(grace_period = ?args.grace_period, "signal received: finishing the run, serving the final weights, then draining (a second signal exits at once)");
                learner.finish("interrupted");
                grace_until = Some(tokio::time::Instant::now() + args.grace_period);
            }
            finished = weights.wait_for(|w| w.as_ref().is_some_and(|w| w.run_finished)),
                if grace_until.is_none() =>
            {
                // An error: the learner's weights cell is gone, so is the run.
                drop(finished);
                tracing::info!(grace_period = ?args.grace_period, "run finished: serving the final weights");
                grace_until = Some(tokio::time::Instant::now() + args.grace_period);
            }
            () = grace_over => break,
            _ = tick.tick() => run_dir::record_new(dir, &learner.curve(), learner.best().latest().as_deref())?,
            () = checkpoints.step(&learner) => {}
        }
    }
    checkpoints.settle().await;
    tokio::spawn(async move {
        signals.recv().await;
        tracing::warn!("second signal: exiting at once");
        std::process::exit(130);
    });
    stop.send_replace(true);
    server
        .await
        .context("the server task failed")?
        .context("serving actors")?;
    if let Some(shm) = shm {
        shm.stop();
    }
    if let Some((_, metrics)) = metrics {
        metrics
            .await
            .context("the metrics task failed")?
            .context("serving metrics")?;
    }
    run_dir::record_new(dir, &learner.curve(), learner.best().latest().as_deref())
}
