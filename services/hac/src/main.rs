//! `hac`: train and evaluate Hierarchical Actor-Critic agents.
//!
//! - `hac train`: the embedded default: rollouts, replay and learning in one process, with a
//!   progress line per test round; writes a run directory (see [`run_dir`]).
//! - `hac eval`: greedy test episodes of a trained run.
//! - `hac experiment`: a grid of level counts x seeds with mean +- std plots and a summary.
//! - `hac render`: one greedy episode of a trained run as an animated GIF or PNG frames.
//! - `hac export`: a trained run's greedy policy as one self-contained safetensors file.
//! - `hac learner`, `hac actor`: the daemons (the same as `hac-learner`, `hac-actor`).
//! - `hac env list | describe | rollout`: inspect and hand-step the built-in environments.
//! - `hac bench ...`: ingest throughput, weights fan-out, many connections held for a long time,
//!   a learner under attack, one level's update speed on 1..N threads (sizing a learner host).
//! - `hac learner`, `hac actor`: the daemons of a distributed run; `hac status`: a running
//!   learner's (or actor's) status as a table or JSON, live with `--watch` ([`status_cmd`]);
//!   `hac health`: one gRPC health check, for container health checks.
//!
//! Modules: [`config`] resolves the run configuration from every source, [`registry`] names
//! every environment, [`plot`] draws SVG learning curves, [`run_dir`] owns the layout of a run
//! directory, [`schedule`] is the reference training schedule for any learner, [`tabular_cmd`]
//! trains and loads the grid worlds' tabular learner, [`render`] draws episodes.

// `outln!` and `out!` (hac_run::output) in every module.
#[macro_use]
extern crate hac_run;

mod bench;
mod bench_connections;
mod bench_grpc;
mod bench_hostile;
mod bench_shm;
mod bench_update;
mod env_cmd;
mod experiment;
mod export;
mod health;
mod render;
mod schedule;
mod state;
mod status_cmd;
mod tabular_cmd;

use hac_run::logging::{LogFormat, error_chain, init_tracing};
use hac_run::{config, plot, registry, run_dir};

use std::cell::RefCell;
use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{Context, Result};
use clap::{Args, Parser, Subcommand};
use hac_agent::{Agent, RunConfig};
use hac_core::{Episodes, LevelCounts, Mode, Policy};
use hac_learner::LearnerOptions;
use hac_run::daemon::{self, ConfigFile, Mount};
use state::Embedded;

#[derive(Debug, Parser)]
#[command(
    name = "hac",
    version,
    about = "Hierarchical Actor-Critic (Levy et al., ICLR 2019): train and evaluate multi-level agents"
)]
struct Cli {
    /// Log format on stderr (filter with RUST_LOG, default `info`).
    #[arg(long, global = true, value_enum, default_value_t = LogFormat::Plain, env = "HAC_LOG_FORMAT")]
    log_format: LogFormat,
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Train an agent in one process (the reference schedule: training episodes, then greedy test
    /// rounds), writing the learning curve, plot, config and weights to the run directory.
    Train(TrainArgs),
    /// Run greedy test episodes with a trained run's weights and print the success rate.
    Eval(EvalArgs),
    /// Run a grid of level counts x seeds (several at a time) and summarise it: a plot per
    /// environment with mean +- 1 std per level count, and a markdown table.
    Experiment(ExperimentArgs),
    /// Draw one greedy test episode of a trained run: the state, the end goal and every level's
    /// current subgoal, as an animated GIF or a directory of numbered PNG frames.
    Render(render::RenderArgs),
    /// Write a trained run's greedy policy (every level's actor network, with the spaces and
    /// bounds it acts in) to one safetensors file for use elsewhere (layout in
    /// docs/CHECKPOINTS.md).
    Export(export::ExportArgs),
    /// Inspect the built-in environments.
    #[command(subcommand)]
    Env(EnvCommand),
    /// Measure the system's throughput.
    #[command(subcommand)]
    Bench(BenchCommand),
    /// Serve a distributed run: the learner trains on what actors stream to it over gRPC.
    Learner(Box<hac_learner_service::LearnerArgs>),
    /// Run one actor of a distributed run: connects to a learner service and streams rollouts.
    Actor(hac_actor_service::ActorArgs),
    /// Show a running learner's status (or an actor's, with --actor): run, per-level updates,
    /// losses, replay fill per shard, rates, rejections, actors and the latest evaluations; a
    /// table, JSON with --json, refreshed live with --watch.
    Status(status_cmd::StatusArgs),
    /// Ask a learner or actor whether it is serving (the standard gRPC health check); exits 0
    /// when SERVING, 1 otherwise.
    Health(health::HealthArgs),
}

#[derive(Debug, Subcommand)]
enum BenchCommand {
    /// Transitions/s, batches/s and ack latency p50/p99 of learner ingest through a transport,
    /// with pre-made pendulum-sized batches from concurrent actors; checks that the learner
    /// stored exactly what it acknowledged.
    Ingest {
        /// The path batches take.
        #[arg(long, value_enum, default_value_t = bench::Transport::InProcess)]
        transport: bench::Transport,
        /// Concurrent senders, each registered as its own actor.
        #[arg(long, default_value_t = 4)]
        actors: usize,
        /// How long to send.
        #[arg(long, default_value_t = 5.0)]
        seconds: f64,
        /// Transitions per batch.
        #[arg(long, default_value_t = 512)]
        batch: usize,
        /// Unacknowledged batches each sender keeps in flight (streaming transports).
        #[arg(long, default_value_t = 32)]
        window: usize,
        /// Print one JSON object instead of a table.
        #[arg(long)]
        json: bool,
        /// Seconds between commits of the learner's write-ahead log, as the learner daemon's
        /// flag (the log goes to a temporary directory, removed after); 0: no log.
        #[arg(long, value_name = "SECS", default_value_t = 0.1)]
        durable_interval: f64,
    },
    /// Weights fan-out: the learner publishes new versions (pendulum, 2 levels) to many
    /// actors' weights watchers; prints the publication-to-receipt delay p50/p99.
    Weights {
        /// How the weights travel: gRPC streams, or shared memory to same-host actors.
        #[arg(long, value_enum, default_value_t = bench::WeightsTransport::Grpc)]
        transport: bench::WeightsTransport,
        /// Connected watchers (actors).
        #[arg(long, default_value_t = 32)]
        actors: usize,
        /// Versions published.
        #[arg(long, default_value_t = 50)]
        versions: u64,
        /// Milliseconds between publications.
        #[arg(long, default_value_t = 20)]
        interval_ms: u64,
        /// Print one JSON object instead of a table.
        #[arg(long)]
        json: bool,
    },
    /// Many lightweight actors held by one learner process: each opens its own gRPC connection,
    /// registers, watches weights and streams small pre-made batches; the learner's resident
    /// memory (VmRSS, VmHWM) is sampled throughout.
    Connections {
        /// Simulated actors, each with its own connection.
        #[arg(long, default_value_t = 256)]
        actors: usize,
        /// How long to hold them.
        #[arg(long, default_value_t = 600.0)]
        seconds: f64,
        /// Transitions per batch.
        #[arg(long, default_value_t = 64)]
        batch: usize,
        /// Milliseconds between one actor's batches.
        #[arg(long, default_value_t = 250)]
        interval_ms: u64,
        /// Unacknowledged batches an actor may have; a tick with a full window sends nothing.
        #[arg(long, default_value_t = 8)]
        window: u64,
        /// Seconds between memory samples.
        #[arg(long, default_value_t = 10, value_parser = clap::value_parser!(u64).range(1..))]
        sample_every: u64,
        /// Print one JSON object (with every sample) instead of a table.
        #[arg(long)]
        json: bool,
    },
    /// A learner under attack, from outside: a `hac learner` process with honest `hac actor`
    /// trainers, while hostile clients built from the wire contract send poison batches, NaN,
    /// out-of-box values, wrong levels and shapes, oversized messages and strings, stale and
    /// unknown identities, sequence gaps, duplicates, garbage bytes to every RPC and mutated
    /// messages. Tallies every answer against what it must be, checks every published weights
    /// version for non-finite values and samples the learner's memory; fails if the learner
    /// crashed, answered wrongly, lost count of a message, published a non-finite weight, or
    /// (attack) the run missed --stop-at.
    Hostile(HostileArgs),
    /// One level's learner update (critic and actor step) on 1..N threads: milliseconds per
    /// update, the update's FLOP count (its matrix products, from the layer shapes), GFLOP/s,
    /// and this machine's single-core sgemm on the same shapes measured now, with the ratio.
    /// The level is built from the environment's default configuration. For sizing a learner
    /// host (docs/OPERATIONS.md).
    Update(UpdateArgs),
}

/// `hac bench update` arguments.
#[derive(Debug, Args)]
struct UpdateArgs {
    /// Built-in environment (see `hac env list`).
    #[arg(long, default_value = "pendulum")]
    env: String,
    /// Levels of the hierarchy (the level's dimensions depend on it).
    #[arg(long, default_value_t = 2)]
    levels: usize,
    /// The level measured, 0 the lowest.
    #[arg(long, default_value_t = 0)]
    level: usize,
    /// Minibatch size [default: the environment's batch_size].
    #[arg(long)]
    batch: Option<usize>,
    /// Hidden layer widths, comma-separated, e.g. 64,64,64 [default: the environment's
    /// hidden_layers].
    #[arg(long, value_delimiter = ',')]
    hidden: Option<Vec<usize>>,
    /// Thread counts to measure, comma-separated, e.g. 1,2,4 [default: 1 to the cores
    /// available].
    #[arg(long, value_delimiter = ',')]
    threads: Vec<usize>,
    /// Seconds of updates per thread count (after a short warm-up).
    #[arg(long, default_value_t = 3.0)]
    seconds: f64,
    /// Print one JSON object instead of a table.
    #[arg(long)]
    json: bool,
}

/// `hac bench hostile` arguments.
#[derive(Debug, Args)]
struct HostileArgs {
    /// Built-in environment (see `hac env list`).
    #[arg(long, default_value = "pendulum")]
    env: String,
    /// Levels of the hierarchy.
    #[arg(long, default_value_t = 2)]
    levels: usize,
    /// The run's seed (and the hostile clients').
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Attack: the success rate the run must reach while attacked.
    #[arg(long, default_value_t = 0.9)]
    stop_at: f64,
    /// Attack: the run's episode budget.
    #[arg(long, default_value_t = 1000)]
    episodes: u64,
    /// Attack: the longest attack in seconds (it also ends when the run does).
    #[arg(long, default_value_t = 60.0)]
    seconds: f64,
    /// Fuzz instead of attack: send this many hostile inputs in all while honest trainers keep
    /// the learner training, then measure honest gRPC ingest on the same learner.
    #[arg(long)]
    inputs: Option<u64>,
    /// Hostile clients, each with its own connection and registered trainer identity (attack:
    /// 0 runs the same without an attack, for comparison).
    #[arg(long, default_value_t = 1)]
    clients: usize,
    /// Honest `hac actor` trainer processes (an attack adds an evaluator).
    #[arg(long, default_value_t = 2)]
    trainers: usize,
    /// Fuzz: seconds of the honest ingest measurement after the inputs (0: none).
    #[arg(long, default_value_t = 5.0)]
    throughput_seconds: f64,
    /// Keep the learner's run directory and every process's log here (default: a temporary
    /// directory, removed).
    #[arg(long)]
    dir: Option<PathBuf>,
    /// Print one JSON object (with the memory samples) instead of a table.
    #[arg(long)]
    json: bool,
}

#[derive(Debug, Args)]
struct ExperimentArgs {
    /// Built-in environments, comma-separated (see `hac env list`).
    #[arg(long, value_delimiter = ',', required = true)]
    env: Vec<String>,
    /// Algorithms to compare, comma-separated: hac, hiro (HIRO: 2 levels only).
    #[arg(long, value_delimiter = ',', default_value = "hac")]
    algo: Vec<hac_core::hiro::Algo>,
    /// Level counts to compare, comma-separated.
    #[arg(long, value_delimiter = ',', default_value = "1,2,3")]
    levels: Vec<usize>,
    /// Seeds per level count (seeds 0..N).
    #[arg(long, default_value_t = 5)]
    seeds: u64,
    /// Training episodes per run [default: as `hac train`].
    #[arg(long)]
    episodes: Option<u64>,
    /// Episode budget of every run, as for `hac train` [default: the environment's].
    #[arg(long)]
    max_actions: Option<usize>,
    /// Runs at a time.
    #[arg(long, default_value_t = 2)]
    jobs: usize,
    /// Each run's learner threads (see `hac train --learner-threads`) [default: the cores
    /// available divided among the jobs, at least 1]. Results do not depend on it.
    #[arg(long)]
    learner_threads: Option<usize>,
    /// Output directory [default: runs/experiment-<env>].
    #[arg(long)]
    out: Option<PathBuf>,
    /// TOML config file applied to every run (as for `hac train`).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Override one agent hyperparameter for every run (repeatable), as for `hac train`. With
    /// `--algo hac,hiro`, `hiro.KEY` settings apply to the HIRO runs only.
    #[arg(long = "set", value_name = "KEY=VALUE")]
    set: Vec<String>,
    /// Replace runs already in the output directory.
    #[arg(long)]
    overwrite: bool,
    /// Finish an interrupted grid in the same --out: a run whose directory holds a finished run
    /// of the same configuration is read back instead of trained again (the summary covers it
    /// with its recorded wall time), an unfinished one (killed, or stopped by Ctrl-C) is trained
    /// again from the start; a finished run of another configuration is refused before any run
    /// starts. A run that saved its state (`--keep-state`) goes on from it instead: an
    /// interrupted one to its budget, a finished one to a larger `--episodes` (the only key,
    /// with `stop_at`, that may differ), each the run the larger budget gives from the start.
    /// Not with --overwrite.
    #[arg(long)]
    resume: bool,
    /// Each run saves its whole state when it stops (as `hac train --keep-state`), so that
    /// `--resume` can train the grid on to a larger `--episodes`.
    #[arg(long)]
    keep_state: bool,
}

#[derive(Debug, Subcommand)]
enum EnvCommand {
    /// List the built-in environments.
    List,
    /// Show an environment's spaces, bounds, thresholds and default hyperparameters.
    Describe {
        /// Environment name (see `hac env list`).
        name: String,
        /// Print as JSON.
        #[arg(long)]
        json: bool,
        /// Describe it with this episode budget, as a run with `--max-actions` has it (the
        /// defaults derived from the budget follow).
        #[arg(long)]
        max_actions: Option<usize>,
    },
    /// Step an environment by hand: reads one JSON action array per stdin line (lines of at most
    /// 1 MiB), prints one JSON object per state (`{"step": n, "state": [...]}`), starting with
    /// the initial state. Actions are clipped to the action bounds.
    Rollout {
        /// Environment name (see `hac env list`).
        #[arg(long)]
        env: String,
        /// Seed of the initial-state draw.
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Start from this physical state instead (JSON array): pendulum `[q, qdot]`,
        /// ur5-reacher `[q1, q2, q3, qdot1, qdot2, qdot3]`, mountain-car `[x, v]`, cartpole
        /// `[x, q, xdot, qdot]`, pick-and-place `[hand x, y, z, opening, block x, y, z]` (at rest,
        /// block axis-aligned), four-rooms `[row, col]` (a free cell).
        #[arg(long)]
        state: Option<String>,
    },
}

#[derive(Debug, Args)]
struct TrainArgs {
    /// Algorithm: hac, or hiro (the HAC paper's baseline; 2 levels only) [default: hac].
    #[arg(long, env = "HAC_ALGO")]
    algo: Option<hac_core::hiro::Algo>,
    /// Built-in environment: pendulum, ur5-reacher, mountain-car, cartpole, pick-and-place, or a
    /// grid world
    /// (four-rooms, four-rooms-25; learned by tabular HAC) [default: pendulum].
    #[arg(long, env = "HAC_ENV")]
    env: Option<String>,
    /// Number of levels; 1 is the flat DDPG + HER baseline [default: 2].
    #[arg(long, env = "HAC_LEVELS")]
    levels: Option<usize>,
    /// Seed of every random stream [default: 0].
    #[arg(long, env = "HAC_SEED")]
    seed: Option<u64>,
    /// Training episodes in total [default: 1000].
    #[arg(long, env = "HAC_EPISODES")]
    episodes: Option<u64>,
    /// Stop early once a test round reaches this success rate (e.g. 0.9).
    #[arg(long, env = "HAC_STOP_AT")]
    stop_at: Option<f32>,
    /// Replay shards per level [default: 1].
    #[arg(long, env = "HAC_REPLAY_SHARDS")]
    replay_shards: Option<usize>,
    /// Episode budget in primitive actions, replacing the environment's (see `hac env
    /// describe`); an H the environment derives from its budget follows it.
    #[arg(long, env = "HAC_MAX_ACTIONS")]
    max_actions: Option<usize>,
    /// TOML config file (top-level keys as these flags, hyperparameters under [agent]; the
    /// daemons' [learner] and [actor] tables are checked and ignored).
    #[arg(long, env = "HAC_CONFIG")]
    config: Option<PathBuf>,
    /// Override one agent hyperparameter, VALUE in TOML syntax (repeatable), e.g.
    /// `--set horizon=20 --set hidden_layers=[64,64]`. Also read from HAC_AGENT_<KEY>.
    #[arg(long = "set", value_name = "KEY=VALUE")]
    set: Vec<String>,
    /// Run directory [default: runs/<env>-<levels>l-seed<seed>; HIRO: runs/<env>-hiro-2l-seed<seed>].
    #[arg(long, env = "HAC_OUT")]
    out: Option<PathBuf>,
    /// Print the resolved configuration as TOML and exit.
    #[arg(long)]
    print_config: bool,
    /// Replace a run already in the run directory.
    #[arg(long)]
    overwrite: bool,
    /// Threads updating the networks, shared among the levels, which update in parallel
    /// [default: the cores available]. The weights, and so the run, do not depend on it; size
    /// it with `hac bench update`.
    #[arg(long, env = "HAC_LEARNER_THREADS")]
    learner_threads: Option<usize>,
    /// When the run stops (its budget trained, its target reached, or Ctrl-C), save its whole
    /// state in `<out>/checkpoints/`: networks, optimisers, replay, random streams. `--resume`
    /// continues from it exactly. The replay makes it large (tens to hundreds of MB for the
    /// 3-level tasks; see docs/CHECKPOINTS.md).
    #[arg(long, env = "HAC_KEEP_STATE")]
    keep_state: bool,
    /// Continue the run in `--out` from the state `--keep-state` saved, to `--episodes` (more
    /// than it has trained, for a run that completed) and `--stop-at`, the only settings that
    /// may change: the config is the run's own. The curve, best weights and weights go on
    /// from where they stood, and the run is the one a larger budget would have given from the
    /// start, bit for bit. Its state is saved again at the end.
    #[arg(long, conflicts_with_all = ["overwrite", "keep_state"])]
    resume: bool,
}

#[derive(Debug, Args)]
struct EvalArgs {
    /// A run directory written by `hac train`.
    #[arg(long)]
    run: PathBuf,
    /// Greedy test episodes [default: the run's test_episodes].
    #[arg(long)]
    episodes: Option<usize>,
    /// Seed of the test episodes' initial states and goals.
    #[arg(long, default_value_t = 12345)]
    seed: u64,
    /// Evaluate the weights of the run's best test round (`weights/best/`) instead of its last.
    #[arg(long)]
    best: bool,
    /// Print the result as JSON.
    #[arg(long)]
    json: bool,
    /// Also print one JSON line per episode (success, primitive steps, end goal, the achieved
    /// end goal at the first and the last state and whether it moved beyond the end goal's
    /// thresholds, final state, what each level did).
    #[arg(long)]
    per_episode: bool,
    /// `--per-episode`, and before each episode's line one JSON line per subgoal that a level
    /// above 0 proposed: the episode, the level, the state and goal it proposed from, and its
    /// output (HIRO's high level: the relative goal). A level's next line gives the state its
    /// attempt ended in. Greedy episodes of a neural run only.
    #[arg(long, conflicts_with = "behaviour")]
    subgoals: bool,
    /// Play the behaviour policy of training instead of greedy episodes: exploration noise,
    /// random actions and subgoal testing as in training episodes, with training end goals,
    /// nothing stored or learned. The per-level figures then also say how many subgoals each
    /// level tested and how many of those tests the level below failed (penalties).
    #[arg(long)]
    behaviour: bool,
}

fn main() {
    let learner = hac_learner_service::config_section();
    let actor = hac_actor_service::config_section();
    let daemons = [
        Mount {
            path: &["learner"],
            section: &learner,
        },
        Mount {
            path: &["actor"],
            section: &actor,
        },
    ];
    let cli = match daemon::parse::<Cli>(&daemons, &[]) {
        Ok((mut cli, resolved)) => {
            match &mut cli.command {
                Command::Learner(args) => args.config.resolved = resolved,
                Command::Actor(args) => args.config.resolved = resolved,
                _ => {}
            }
            cli
        }
        Err(e) => {
            eprintln!("error: {}", error_chain(&e));
            std::process::exit(1);
        }
    };
    init_tracing(cli.log_format);
    // `hac train` and `hac experiment` ignore the daemons' tables but check them all the same.
    let file = match &cli.command {
        Command::Train(args) => args.config.clone(),
        Command::Experiment(args) => args.config.clone(),
        _ => None,
    };
    if let Some(path) = file
        && let Err(e) = ConfigFile::load(&path).and_then(|f| f.validate(&[&learner, &actor]))
    {
        eprintln!("error: {}", error_chain(&e));
        std::process::exit(1);
    }
    let result = match cli.command {
        Command::Train(args) => train(args),
        Command::Eval(args) => eval(args),
        Command::Experiment(args) => hac_run::signals::interrupt_flag().and_then(|interrupt| {
            experiment::run(experiment::Grid {
                out: args.out.unwrap_or_else(|| {
                    PathBuf::from(format!("runs/experiment-{}", args.env.join("-")))
                }),
                envs: args.env,
                algos: args.algo,
                levels: args.levels,
                seeds: args.seeds,
                episodes: args.episodes,
                max_actions: args.max_actions,
                jobs: args.jobs,
                learner_threads: args.learner_threads,
                config: args.config,
                set: args.set,
                overwrite: args.overwrite,
                resume: args.resume,
                keep_state: args.keep_state,
                interrupt,
            })
        }),
        Command::Bench(BenchCommand::Ingest {
            transport,
            actors,
            seconds,
            batch,
            window,
            json,
            durable_interval,
        }) => bench::run_ingest(&bench::IngestBench {
            transport,
            actors,
            seconds,
            batch,
            window,
            json,
            durable_interval,
        }),
        Command::Render(args) => render::run(&args),
        Command::Export(args) => export::run(&args),
        Command::Bench(BenchCommand::Weights {
            transport,
            actors,
            versions,
            interval_ms,
            json,
        }) => bench::run_weights(transport, actors, versions, interval_ms, json),
        Command::Bench(BenchCommand::Connections {
            actors,
            seconds,
            batch,
            interval_ms,
            window,
            sample_every,
            json,
        }) => bench_connections::run_and_print(&bench_connections::ConnectionsBench {
            actors,
            seconds,
            batch,
            interval: Duration::from_millis(interval_ms),
            window,
            sample_every: Duration::from_secs(sample_every),
            json,
        }),
        Command::Bench(BenchCommand::Update(args)) => {
            bench_update::run_and_print(&bench_update::UpdateBench {
                env: args.env,
                levels: args.levels,
                level: args.level,
                batch: args.batch,
                hidden: args.hidden,
                threads: args.threads,
                seconds: args.seconds,
                json: args.json,
            })
        }
        Command::Bench(BenchCommand::Hostile(args)) => {
            bench_hostile::run_and_print(&bench_hostile::HostileBench {
                env: args.env,
                levels: args.levels,
                seed: args.seed,
                stop_at: args.stop_at,
                episodes: args.episodes,
                seconds: args.seconds,
                inputs: args.inputs,
                clients: args.clients,
                trainers: args.trainers,
                throughput_seconds: args.throughput_seconds,
                dir: args.dir,
                json: args.json,
            })
        }
        Command::Health(args) => health::run(&args),
        Command::Env(EnvCommand::List) => env_cmd::list(),
        Command::Env(EnvCommand::Describe {
            name,
            json,
            max_actions,
        }) => env_cmd::describe(&name, json, max_actions),
        Command::Env(EnvCommand::Rollout { env, seed, state }) => {
            env_cmd::rollout(&env, seed, state.as_deref())
        }
        Command::Learner(args) => hac_learner_service::run(*args),
        Command::Actor(args) => hac_actor_service::run(args),
        Command::Status(args) => status_cmd::run(&args),
    };
    if let Err(e) = result {
        hac_run::output::exit_if_broken_pipe(&e);
        eprintln!("error: {}", error_chain(&e));
        std::process::exit(1);
    }
}

fn train(args: TrainArgs) -> Result<()> {
    if args.resume {
        return train_on(args);
    }
    let run = config::resolve(
        args.config.as_deref(),
        config::Overrides {
            algo: args.algo,
            env: args.env,
            levels: args.levels,
            seed: args.seed,
            episodes: args.episodes,
            stop_at: args.stop_at,
            replay_shards: args.replay_shards,
            max_actions: args.max_actions,
            set: args.set,
            hiro_settings_for_hiro_only: false,
        },
    )?;
    if args.print_config {
        out!("{}", toml::to_string(&run)?);
        return Ok(());
    }
    // Checked before the run directory is made.
    let options = learner_options(&run, args.learner_threads)?;
    if args.keep_state && tabular_cmd::handles(&run.env) {
        anyhow::bail!(
            "--keep-state is for neural runs: `{}` is a grid world, whose tabular runs train in \
             seconds and keep no state",
            run.env
        );
    }
    let out = args
        .out
        .unwrap_or_else(|| PathBuf::from("runs").join(run.run_name()));
    let mut dir = run_dir::RunDir::create(&out, &run, args.overwrite)?;
    if tabular_cmd::handles(&run.env) {
        return tabular_cmd::train(&run, dir, &out);
    }
    outln!("{}", run_dir::training_banner(&run, &out, None));
    train_into(
        Embedded {
            run: &run,
            options,
            from: None,
            keep_state: args.keep_state,
            interrupt: &*hac_run::signals::interrupt_flag()?,
            progress: true,
        },
        &mut dir,
        &out,
    )
}

/// `hac train`'s run into `dir`, with its last line.
fn train_into(embedded: Embedded<'_>, dir: &mut run_dir::RunDir, out: &Path) -> Result<()> {
    let (_, summary) = embedded.train(dir, out)?;
    outln!("{}", summary.done_line(out));
    Ok(())
}

/// The embedded learner's options for `run`, with `--learner-threads` if given.
fn learner_options(run: &RunConfig, threads: Option<usize>) -> Result<LearnerOptions> {
    let mut options = LearnerOptions::for_run(run);
    if let Some(threads) = threads {
        options.learner_threads = threads;
        options.validate()?;
    }
    Ok(options)
}

/// `hac train --resume`: the run in `--out` continued from the state `--keep-state` saved.
fn train_on(args: TrainArgs) -> Result<()> {
    let given: Vec<&str> = [
        ("--algo", args.algo.is_some()),
        ("--env", args.env.is_some()),
        ("--levels", args.levels.is_some()),
        ("--seed", args.seed.is_some()),
        ("--replay-shards", args.replay_shards.is_some()),
        ("--max-actions", args.max_actions.is_some()),
        ("--config", args.config.is_some()),
        ("--set", !args.set.is_empty()),
    ]
    .into_iter()
    .filter_map(|(flag, given)| given.then_some(flag))
    .collect();
    if !given.is_empty() {
        anyhow::bail!(
            "--resume continues the run with its own config; only --episodes and --stop-at may \
             change (drop {}, or its HAC_* variable)",
            given.join(", ")
        );
    }
    let out = args
        .out
        .context("--resume needs the run directory: pass --out")?;
    let mut run = config::load_run(&out)?;
    if tabular_cmd::handles(&run.env) {
        anyhow::bail!(
            "{} is a grid-world run: tabular runs train in seconds and cannot be continued",
            out.display()
        );
    }
    if let Some(episodes) = args.episodes {
        run.episodes = episodes;
    }
    if args.stop_at.is_some() {
        run.stop_at = args.stop_at;
    }
    let loaded = state::load(&out)?.with_context(|| {
        format!(
            "{} holds no saved state to continue from: train it with --keep-state",
            out.display()
        )
    })?;
    let mut saved = loaded.value;
    saved
        .checkpoint
        .continue_as(&run)
        .with_context(|| format!("continuing {}", out.display()))?;
    if args.print_config {
        out!("{}", toml::to_string(&run)?);
        return Ok(());
    }
    let options = learner_options(&run, args.learner_threads)?;
    let mut dir = run_dir::RunDir::resume(&out, &run, saved.checkpoint.curve())?;
    outln!(
        "continuing {} from {} episodes ({} test rounds, {}) to {} episodes",
        out.display(),
        saved.trainer.episodes,
        saved.checkpoint.curve().len(),
        loaded.name,
        run.episodes
    );
    train_into(
        Embedded {
            run: &run,
            options,
            from: Some(&saved),
            keep_state: true,
            interrupt: &*hac_run::signals::interrupt_flag()?,
            progress: true,
        },
        &mut dir,
        &out,
    )
}

/// A subgoal a level above 0 proposed: the level, the state and goal it proposed from, and its
/// output.
type Proposal = (usize, Vec<f32>, Vec<f32>, Vec<f32>);

/// A policy that records what the levels above 0 propose when given somewhere to put it, for
/// `hac eval --subgoals`; the episode's callback prints the records.
struct Traced<'a, P> {
    inner: &'a mut P,
    proposals: Option<&'a RefCell<Vec<Proposal>>>,
}

impl<P: Policy> Policy for Traced<'_, P> {
    fn act(&mut self, level: usize, state: &[f32], goal: &[f32], action: &mut [f32]) {
        self.inner.act(level, state, goal, action);
        if let Some(proposals) = self.proposals
            && level > 0
        {
            proposals
                .borrow_mut()
                .push((level, state.to_vec(), goal.to_vec(), action.to_vec()));
        }
    }
}

fn eval(args: EvalArgs) -> Result<()> {
    let run = config::load_run(&args.run)?;
    let episodes = args.episodes.unwrap_or(run.agent.test_episodes);
    let mode = if args.behaviour {
        Mode::Train
    } else {
        Mode::Test
    };
    let mut index = 0usize;
    let mut totals = vec![LevelCounts::default(); run.levels];
    let mut this_episode = vec![LevelCounts::default(); run.levels];
    let mut moved = 0usize;
    let proposals = RefCell::new(Vec::new());
    let recorded = args.subgoals.then_some(&proposals);
    let on_episode = |outcome: &hac_core::EpisodeOutcome, state: &[f32], rollout: &Episodes| {
        for (level, from, goal, subgoal) in proposals.borrow_mut().drain(..) {
            outln!(
                "{}",
                serde_json::json!({"episode": index, "level": level, "state": from, "goal": goal, "subgoal": subgoal})
            );
        }
        this_episode.fill(LevelCounts::default());
        rollout.add_level_counts(&mut this_episode);
        for (total, this) in totals.iter_mut().zip(&this_episode) {
            total.add(this);
        }
        let moved_this = rollout.moved_end_goal();
        moved += usize::from(moved_this);
        if args.per_episode || args.subgoals {
            outln!(
                "{}",
                serde_json::json!({"episode": index, "success": outcome.success, "steps": outcome.steps, "end_goal": rollout.end_goal(), "start_achieved": rollout.start_achieved(), "final_achieved": rollout.final_achieved(), "moved": moved_this, "final_state": state, "levels": this_episode})
            );
        }
        index += 1;
    };
    let mut weights = "weights/";
    let success = if tabular_cmd::handles(&run.env) {
        if args.subgoals {
            anyhow::bail!(
                "`{}` is a grid world learned by tabular HAC: --subgoals traces neural runs",
                run.env
            );
        }
        if args.best {
            anyhow::bail!(
                "`{}` is a grid world learned by tabular HAC: its runs keep the last Q tables only \
                 (--best is for neural runs)",
                run.env
            );
        }
        tabular_cmd::evaluate(&args.run, &run, episodes, args.seed, mode, on_episode)?
    } else if args.best {
        weights = "weights/best/";
        let mut env = run.make_env()?;
        let (_, mut policy) = export::best_policy(&args.run, &run, env.spec())?;
        hac_agent::evaluate(
            env.as_mut(),
            &mut Traced {
                inner: &mut policy,
                proposals: recorded,
            },
            &run,
            episodes,
            args.seed,
            mode,
            on_episode,
        )
    } else {
        let mut env = run.make_env()?;
        let mut agent = Agent::load(&run_dir::weights_dir(&args.run), env.spec(), &run)
            .context("loading the run's weights")?;
        hac_agent::evaluate(
            env.as_mut(),
            &mut Traced {
                inner: &mut agent,
                proposals: recorded,
            },
            &run,
            episodes,
            args.seed,
            mode,
            on_episode,
        )
    };
    let moved_rate = moved as f64 / episodes.max(1) as f64;
    // HIRO's levels are not given goals in HAC's sense: its rollout counts nothing.
    let counted = totals.iter().any(|t| t.calls > 0);
    let kind = if args.behaviour {
        "behaviour-policy"
    } else {
        "greedy test"
    };
    if args.json {
        outln!(
            "{}",
            serde_json::json!({"run": args.run, "weights": weights, "env": run.env, "levels": run.levels, "episodes": episodes, "mode": if args.behaviour { "behaviour" } else { "greedy" }, "success_rate": success, "moved_rate": moved_rate, "per_level": counted.then_some(&totals)})
        );
    } else {
        outln!(
            "{} ({weights}): {} with {} levels: success {:.1}% over {} {kind} episodes",
            args.run.display(),
            run.env,
            run.levels,
            100.0 * success,
            episodes
        );
        outln!(
            "  achieved end goal moved beyond the end goal's thresholds (last state against \
             first) in {:.1}% of the episodes",
            100.0 * moved_rate
        );
        if counted {
            for (level, t) in totals.iter().enumerate().rev() {
                outln!("  {}", level_counts_line(level, t));
            }
        }
    }
    Ok(())
}

/// One level's [`LevelCounts`] as `hac eval` prints them.
fn level_counts_line(level: usize, t: &LevelCounts) -> String {
    let mut line = format!(
        "level {level}: {} calls, goal reached in {:.1}%, maxed out in {:.1}%, {:.1} attempts per call",
        t.calls,
        100.0 * t.reached_rate(),
        100.0 * t.maxed_out_rate(),
        t.attempts_per_call()
    );
    if t.tested > 0 {
        line.push_str(&format!(
            ", {} subgoals tested, {:.1}% of them penalised",
            t.tested,
            100.0 * t.penalty_rate()
        ));
    }
    line
}
