//! `hac bench ingest`: how fast the learner takes transitions in, through a chosen transport (or
//! all three, `--transport all`, one after the other in one table).
//!
//! A learner is started in this process for a pendulum-sized 2-level run (its trainers stay idle:
//! the bench sends batches but no episode ends, so no updates are owed), then `--actors`
//! concurrent senders push pre-made level-0 batches for `--seconds`. Reported: transitions/s and
//! batches/s stored by the learner (from its own counters, so nothing is counted that was not
//! stored), ack latency p50/p99 (send to cumulative ack), and a check that the learner stored
//! exactly what was acknowledged (no loss, no duplicates).

use std::path::Path;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use hac_agent::RunConfig;
use hac_core::{Batch, LevelDims};
use hac_learner::{Learner, LearnerOptions, LearnerStatus, WalOptions};
use hac_proto::{ActorRole, DecodedBatch, IngestItem, IngestMessage, Registration};
use serde::Serialize;

/// Which path the batches take.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Transport {
    /// Direct calls into the learner (the embedded run's path): the learner's own ceiling.
    InProcess,
    /// tonic over loopback TCP: one bidirectional ingest stream per actor, `--window` batches in
    /// flight each.
    Grpc,
    /// Shared memory (iceoryx2): each actor a real `ShmLink` (registered over gRPC), `--window`
    /// batches unacknowledged each.
    Shm,
    /// in-process, grpc and shm one after the other, each with a fresh learner, in one table.
    All,
}

/// Where `hac bench weights` sends the weights.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum WeightsTransport {
    /// gRPC `WatchWeights` streams over loopback.
    Grpc,
    /// The shared-memory weights service, as same-host actors receive it.
    Shm,
}

/// `hac bench ingest` settings.
#[derive(Debug, Clone)]
pub struct IngestBench {
    pub transport: Transport,
    pub actors: usize,
    pub seconds: f64,
    pub batch: usize,
    pub window: usize,
    pub json: bool,
    /// The learner's write-ahead log commit interval, as the daemon's `--durable-interval`
    /// in seconds (the log goes to a temporary directory); zero: no log.
    pub durable_interval: f64,
}

/// One bench result, as printed.
#[derive(Debug, Clone, Serialize)]
pub struct IngestReport {
    pub transport: Transport,
    pub actors: usize,
    pub batch_transitions: usize,
    pub window: usize,
    pub seconds: f64,
    pub transitions_per_s: f64,
    pub batches_per_s: f64,
    pub ack_latency_p50_us: f64,
    pub ack_latency_p99_us: f64,
    pub transitions_stored: u64,
    pub transitions_acked: u64,
    pub duplicates: u64,
    pub floats_per_transition: usize,
}

/// What one ingest measurement saw, for [`IngestReport::new`].
pub struct Measured<'a> {
    /// The bench learner's status after the run: it is fresh, so its totals are the bench's.
    pub status: &'a LearnerStatus,
    pub seconds: f64,
    pub acked_batches: u64,
    pub latencies_us: &'a mut [u32],
    /// Floats in one bench batch.
    pub floats: usize,
}

impl IngestReport {
    /// The report of `bench` over `transport` with `window` batches in flight per actor.
    pub fn new(transport: Transport, bench: &IngestBench, window: usize, m: Measured<'_>) -> Self {
        let (p50, p99) = percentiles(m.latencies_us);
        Self {
            transport,
            actors: bench.actors,
            batch_transitions: bench.batch,
            window,
            seconds: m.seconds,
            transitions_per_s: m.status.transitions as f64 / m.seconds,
            batches_per_s: m.status.batches as f64 / m.seconds,
            ack_latency_p50_us: p50,
            ack_latency_p99_us: p99,
            transitions_stored: m.status.transitions,
            transitions_acked: m.acked_batches * bench.batch as u64,
            duplicates: m.status.duplicates,
            floats_per_transition: m.floats / bench.batch,
        }
    }
}

/// Sender threads: each waits at `start`, sends until `stop` and returns its acknowledged
/// batches and ack latencies (microseconds).
pub type Sender = std::thread::JoinHandle<Result<(u64, Vec<u32>)>>;

/// Releases `senders` at `start`, lets them run `seconds`, stops them and joins them: their
/// acknowledged batches, their latencies, and the seconds measured.
pub fn run_senders(
    start: &std::sync::Barrier,
    stop: &AtomicBool,
    seconds: f64,
    senders: Vec<Sender>,
) -> Result<(u64, Vec<u32>, f64)> {
    start.wait();
    let started = Instant::now();
    std::thread::sleep(Duration::from_secs_f64(seconds));
    stop.store(true, Ordering::Relaxed);
    let mut acked_batches = 0;
    let mut latencies = Vec::new();
    for s in senders {
        let (n, l) = s.join().expect("a bench sender panicked")?;
        acked_batches += n;
        latencies.extend(l);
    }
    Ok((acked_batches, latencies, started.elapsed().as_secs_f64()))
}

/// The run the bench learner serves: pendulum, 2 levels, a replay large enough that the bench
/// measures inserts rather than a tiny ring's cache behaviour.
pub fn bench_run() -> Result<RunConfig> {
    let env = hac_envs::make("pendulum")?;
    let mut agent = env.default_config(2);
    agent.replay_capacity_max = 1 << 20;
    Ok(RunConfig {
        env: "pendulum".into(),
        levels: 2,
        seed: 0,
        episodes: u64::MAX,
        stop_at: None,
        replay_shards: 4,
        max_actions: None,
        subgoal_bounds: None,
        agent,
        tabular: None,
        hiro: None,
        algo: Default::default(),
    })
}

/// A full level-0 batch of `len` plausible pendulum transitions.
pub fn level0_batch(dims: LevelDims, len: usize) -> Batch {
    let mut batch = Batch::zeros(dims, len);
    for (i, x) in batch.states.iter_mut().enumerate() {
        *x = (i % 17) as f32 * 0.1 - 0.8;
    }
    batch.next_states.copy_from_slice(&batch.states);
    batch.actions.fill(0.5);
    batch.goals.fill(0.1);
    batch.rewards.fill(-1.0);
    batch
}

/// Latency percentiles in microseconds from unsorted samples.
pub fn percentiles(samples: &mut [u32]) -> (f64, f64) {
    if samples.is_empty() {
        return (0.0, 0.0);
    }
    samples.sort_unstable();
    let at = |q: f64| samples[((samples.len() - 1) as f64 * q).round() as usize] as f64;
    (at(0.50), at(0.99))
}

/// Starts the bench learner.
pub fn bench_learner(max_batch: usize, wal: Option<(&Path, Duration)>) -> Result<Arc<Learner>> {
    let run = bench_run()?;
    let mut options = LearnerOptions::for_run(&run);
    options.max_batch_transitions = options.max_batch_transitions.max(max_batch);
    options.wal = wal.map(|(dir, interval)| WalOptions::new(dir, interval));
    Ok(Arc::new(
        Learner::start(run, options).context("starting the bench learner")?,
    ))
}

/// `hac bench weights`: a new weights version reaching `watchers` actors, over gRPC weights
/// streams or shared memory.
pub fn run_weights(
    transport: WeightsTransport,
    watchers: usize,
    versions: u64,
    interval_ms: u64,
    json: bool,
) -> Result<()> {
    if watchers == 0 || versions == 0 {
        bail!("--actors and --versions must be at least 1");
    }
    let learner = bench_learner(1, None)?;
    let interval = Duration::from_millis(interval_ms);
    let r = match transport {
        WeightsTransport::Grpc => crate::bench_grpc::fanout(&learner, watchers, versions, interval),
        WeightsTransport::Shm => crate::bench_shm::fanout(&learner, watchers, versions, interval),
    }?;
    learner.finish("bench over");
    if let Some(learner) = Arc::into_inner(learner) {
        learner.shutdown();
    }
    if json {
        outln!("{}", serde_json::to_string(&r)?);
    } else {
        outln!(
            "| transport | watchers | versions | snapshot | delivered | delay p50 | delay p99 | max |"
        );
        outln!("| --- | --- | --- | --- | --- | --- | --- | --- |");
        outln!(
            "| {transport:?} | {} | {} | {} KiB | {} of {} | {:.0} us | {:.0} us | {:.0} us |",
            r.watchers,
            r.versions,
            r.snapshot_bytes / 1024,
            r.deliveries,
            r.expected_deliveries,
            r.delay_p50_us,
            r.delay_p99_us,
            r.delay_max_us
        );
    }
    Ok(())
}

pub fn run_ingest(bench: &IngestBench) -> Result<()> {
    if bench.actors == 0 || bench.batch == 0 || bench.window == 0 {
        bail!("--actors, --batch and --window must be at least 1");
    }
    if !(bench.seconds.is_finite() && bench.seconds > 0.0) {
        bail!("--seconds must be a positive number");
    }
    let durable_interval = Duration::try_from_secs_f64(bench.durable_interval)
        .map_err(|e| anyhow::anyhow!("--durable-interval {}: {e}", bench.durable_interval))?;
    let transports = match bench.transport {
        Transport::All => vec![Transport::InProcess, Transport::Grpc, Transport::Shm],
        one => vec![one],
    };
    let mut reports = Vec::new();
    for transport in transports {
        // A fresh learner each, so that its counters are the bench's (and a fresh log).
        let wal_dir = std::env::temp_dir().join(format!("hac-bench-wal-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&wal_dir);
        let wal = (!durable_interval.is_zero()).then(|| (wal_dir.clone(), durable_interval));
        let learner = bench_learner(bench.batch, wal.as_ref().map(|(d, i)| (d.as_path(), *i)))?;
        if !bench.json {
            eprintln!(
                "bench ingest: {transport:?}, {} actors, batches of {}, window {}, {} s",
                bench.actors, bench.batch, bench.window, bench.seconds
            );
        }
        let report = match transport {
            Transport::InProcess => in_process(bench, &learner)?,
            Transport::Grpc => crate::bench_grpc::ingest(bench, &learner)?,
            Transport::Shm => crate::bench_shm::ingest(bench, &learner)?,
            Transport::All => unreachable!("expanded above"),
        };
        learner.finish("bench over");
        if let Some(learner) = Arc::into_inner(learner) {
            learner.shutdown();
        }
        let _ = std::fs::remove_dir_all(&wal_dir);
        if report.transitions_stored != report.transitions_acked || report.duplicates != 0 {
            bail!(
                "{transport:?}: the learner stored {} transitions but {} were acknowledged ({} \
                 duplicates)",
                report.transitions_stored,
                report.transitions_acked,
                report.duplicates
            );
        }
        reports.push(report);
    }
    print_reports(&reports, bench.json)
}

fn print_reports(reports: &[IngestReport], json: bool) -> Result<()> {
    if json {
        for r in reports {
            outln!("{}", serde_json::to_string(r)?);
        }
        return Ok(());
    }
    outln!(
        "| transport | actors | batch | transitions/s | batches/s | ack p50 | ack p99 | stored = acked |"
    );
    outln!("| --- | --- | --- | --- | --- | --- | --- | --- |");
    for r in reports {
        outln!(
            "| {:?} | {} | {} | {:.0} | {:.0} | {:.0} us | {:.0} us | {} = {} |",
            r.transport,
            r.actors,
            r.batch_transitions,
            r.transitions_per_s,
            r.batches_per_s,
            r.ack_latency_p50_us,
            r.ack_latency_p99_us,
            r.transitions_stored,
            r.transitions_acked
        );
    }
    Ok(())
}

/// Senders on their own threads calling the learner directly; a call's return is its ack.
fn in_process(bench: &IngestBench, learner: &Arc<Learner>) -> Result<IngestReport> {
    let stop = Arc::new(AtomicBool::new(false));
    let batch = level0_batch(learner.dims()[0], bench.batch);
    let floats = batch.states.len() * 2 + batch.actions.len() + batch.goals.len() + 2 * batch.len;
    let mut senders = Vec::new();
    let start = Arc::new(std::sync::Barrier::new(bench.actors + 1));
    for a in 0..bench.actors {
        let start = start.clone();
        let learner = learner.clone();
        let stop = stop.clone();
        let batch = batch.clone();
        let admission = learner
            .register(Registration {
                actor_id: format!("bench-{a}"),
                role: ActorRole::Trainer,
                hostname: String::new(),
                transports: vec!["in-process".into()],
            })
            .context("registering a bench actor")?;
        senders.push(std::thread::spawn(move || -> Result<(u64, Vec<u32>)> {
            let mut msg = IngestMessage {
                actor_id: format!("bench-{a}"),
                incarnation: admission.incarnation,
                sequence: 0,
                item: IngestItem::Batch(DecodedBatch {
                    level: 0,
                    weights_version: 1,
                    batch,
                }),
            };
            let (mut acked, mut latencies) = (0u64, Vec::with_capacity(1 << 16));
            start.wait();
            while !stop.load(Ordering::Relaxed) {
                msg.sequence += 1;
                let t0 = Instant::now();
                learner.ingest(&msg)?;
                latencies.push(t0.elapsed().as_micros().min(u32::MAX as u128) as u32);
                acked += 1;
            }
            Ok((acked, latencies))
        }));
    }
    let (acked_batches, mut latencies, elapsed) =
        run_senders(&start, &stop, bench.seconds, senders)?;
    Ok(IngestReport::new(
        Transport::InProcess,
        bench,
        1,
        Measured {
            status: &learner.status(),
            seconds: elapsed,
            acked_batches,
            latencies_us: &mut latencies,
            floats,
        },
    ))
}
