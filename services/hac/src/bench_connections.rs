//! `hac bench connections`: many lightweight actors held by one learner process for a long time,
//! with the learner's memory sampled throughout.
//!
//! The learner is a real `hac learner` child process (this binary, pendulum with 2 levels, on an
//! ephemeral loopback port, its run directory in a temporary directory), so that what is sampled
//! is the learner alone. Each simulated actor has its own TCP connection; it registers, keeps a
//! weights stream open (as real actors do) and sends one pre-made level-0 batch every
//! `--interval-ms` on its ingest stream, at most `--window` unacknowledged (a tick with a full
//! window is skipped and counted). No episode ends are sent, so the learner's trainers stay idle
//! and the load is the connections and ingest alone; the replay tables fill up to their capacity
//! and then overwrite, which bounds what the stored transitions cost.
//!
//! Every `--sample-every` seconds the learner's VmRSS, VmHWM and thread count are read from
//! `/proc/<pid>/status`. At the end the learner is stopped with SIGTERM (it drains and exits), and
//! the report compares the resident size after the first minute with the last sample.

use std::io::{BufRead as _, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use hac_proto::{encode_batch, pb};
use serde::Serialize;
use tokio_stream::wrappers::ReceiverStream;

use crate::bench::level0_batch;
use crate::bench_grpc::{client, register};

/// `hac bench connections` settings.
#[derive(Debug, Clone)]
pub struct ConnectionsBench {
    pub actors: usize,
    pub seconds: f64,
    pub batch: usize,
    pub interval: Duration,
    pub window: u64,
    pub sample_every: Duration,
    pub json: bool,
}

/// One reading of the learner's memory.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct Sample {
    pub at_s: f64,
    pub rss_kib: u64,
    pub hwm_kib: u64,
    pub threads: u64,
    pub transitions_acked: u64,
}

/// `hac bench connections` result.
#[derive(Debug, Clone, Serialize)]
pub struct ConnectionsReport {
    pub actors: usize,
    pub actors_connected: usize,
    pub seconds: f64,
    pub batch_transitions: usize,
    pub interval_ms: u64,
    pub batches_acked: u64,
    pub transitions_per_s: f64,
    pub ticks_skipped_full_window: u64,
    /// The learner's peak resident size (VmHWM at the end, or a larger sample).
    pub peak_rss_kib: u64,
    /// VmRSS at the first sample at or after 60 s (or the first sample of a shorter run).
    pub rss_after_1_min_kib: u64,
    pub rss_last_kib: u64,
    pub samples: Vec<Sample>,
}

/// A `hac learner` child on an ephemeral loopback port; killed if still running when dropped
/// (a failed bench leaves nothing), its run directory removed then unless kept.
pub(crate) struct LearnerProcess {
    child: Child,
    dir: PathBuf,
    keep: bool,
}

impl LearnerProcess {
    /// Starts `hac learner --listen 127.0.0.1:0 --overwrite --out <dir> <args>` with its stderr
    /// to `stderr`; returns it with its URL.
    pub(crate) fn spawn(
        args: &[String],
        dir: &Path,
        keep: bool,
        stderr: Stdio,
    ) -> Result<(Self, String)> {
        let exe = std::env::current_exe().context("locating the hac binary")?;
        let mut child = Command::new(exe)
            .args(["learner", "--listen", "127.0.0.1:0", "--overwrite", "--out"])
            .arg(dir)
            .args(args)
            // The bench's learner is fully specified by these flags.
            .env_remove("HAC_CONFIG")
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(stderr)
            .spawn()
            .context("starting `hac learner`")?;
        let stdout = child.stdout.take().context("the learner's stdout")?;
        let mut process = Self {
            child,
            dir: dir.to_path_buf(),
            keep,
        };
        let mut line = String::new();
        BufReader::new(stdout)
            .read_line(&mut line)
            .context("reading the learner's address")?;
        let Some(addr) = line.trim().strip_prefix("listening on ") else {
            let status = process.child.try_wait().ok().flatten();
            bail!("the learner did not start (first line {line:?}, exit {status:?})");
        };
        Ok((process, format!("http://{addr}")))
    }

    pub(crate) fn pid(&self) -> u32 {
        self.child.id()
    }

    /// Its exit status, if it has exited.
    pub(crate) fn try_wait(&mut self) -> Result<Option<ExitStatus>> {
        Ok(self.child.try_wait()?)
    }

    /// SIGTERM (through kill(1): the workspace has no unsafe code for libc), then a bounded
    /// wait; the exit status.
    pub(crate) fn terminate(&mut self) -> Result<ExitStatus> {
        if let Some(status) = self.child.try_wait()? {
            return Ok(status);
        }
        let sent = Command::new("kill")
            .args(["-TERM", &self.pid().to_string()])
            .status()
            .context("running kill")?;
        if !sent.success() {
            bail!("kill -TERM {} failed", self.pid());
        }
        let deadline = Instant::now() + Duration::from_secs(30);
        while Instant::now() < deadline {
            if let Some(status) = self.child.try_wait()? {
                return Ok(status);
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        bail!("the learner did not stop within 30 s of SIGTERM")
    }

    /// [`terminate`](Self::terminate), which must end in a clean exit.
    fn stop(mut self) -> Result<()> {
        let status = self.terminate()?;
        if !status.success() {
            bail!("the learner exited with {status}");
        }
        Ok(())
    }
}

impl Drop for LearnerProcess {
    fn drop(&mut self) {
        if self.child.try_wait().ok().flatten().is_none() {
            let _ = self.child.kill();
            let _ = self.child.wait();
        }
        if !self.keep {
            let _ = std::fs::remove_dir_all(&self.dir);
        }
    }
}

/// VmRSS, VmHWM (KiB) and Threads of a process.
pub(crate) fn read_status(pid: u32) -> Result<(u64, u64, u64)> {
    let text = std::fs::read_to_string(format!("/proc/{pid}/status"))
        .with_context(|| format!("reading /proc/{pid}/status"))?;
    let field = |name: &str| -> Result<u64> {
        text.lines()
            .find_map(|line| line.strip_prefix(name))
            .and_then(|rest| rest.split_whitespace().next())
            .and_then(|n| n.parse().ok())
            .with_context(|| format!("no {name} in /proc/{pid}/status"))
    };
    Ok((field("VmRSS:")?, field("VmHWM:")?, field("Threads:")?))
}

/// Counters shared by every simulated actor.
#[derive(Default)]
struct Counters {
    connected: AtomicU64,
    batches_acked: AtomicU64,
    skipped: AtomicU64,
}

/// One simulated actor: register, hold a weights stream, send a batch per tick.
async fn actor(
    index: usize,
    url: String,
    message: pb::TransitionBatch,
    bench: ConnectionsBench,
    stop: Arc<AtomicBool>,
    counters: Arc<Counters>,
) -> Result<()> {
    let id = format!("conn-{index}");
    let mut client = client(&url).await?;
    let incarnation = register(&mut client, &id).await?;
    let mut weights = client
        .watch_weights(pb::WatchWeightsRequest {
            actor_id: id.clone(),
            incarnation,
            min_version: 0,
        })
        .await?
        .into_inner();
    let watcher = tokio::spawn(async move { while let Ok(Some(_)) = weights.message().await {} });
    let (tx, rx) = tokio::sync::mpsc::channel::<pb::IngestRequest>(bench.window as usize);
    let mut acks = client.ingest(ReceiverStream::new(rx)).await?.into_inner();
    counters.connected.fetch_add(1, Ordering::Relaxed);
    let acked = Arc::new(AtomicU64::new(0));
    let receiver = {
        let (acked, counters) = (acked.clone(), counters.clone());
        tokio::spawn(async move {
            while let Some(ack) = acks.message().await? {
                let before = acked.swap(ack.acked_through, Ordering::Relaxed);
                counters
                    .batches_acked
                    .fetch_add(ack.acked_through.saturating_sub(before), Ordering::Relaxed);
            }
            anyhow::Ok(())
        })
    };
    // Spread the actors' ticks over the interval instead of sending in bursts.
    let offset = bench.interval.mul_f64(index as f64 / bench.actors as f64);
    let mut ticks = tokio::time::interval_at(tokio::time::Instant::now() + offset, bench.interval);
    ticks.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let mut sequence = 0u64;
    while !stop.load(Ordering::Relaxed) {
        ticks.tick().await;
        if sequence - acked.load(Ordering::Relaxed) >= bench.window {
            counters.skipped.fetch_add(1, Ordering::Relaxed);
            continue;
        }
        sequence += 1;
        let request = pb::IngestRequest {
            actor_id: id.clone(),
            incarnation,
            sequence,
            item: Some(pb::ingest_request::Item::Batch(message.clone())),
        };
        if tx.send(request).await.is_err() {
            bail!("{id}: the ingest stream closed");
        }
    }
    // Ending the request stream: the learner acknowledges the rest and closes its side.
    drop(tx);
    receiver.await.context("the ack reader panicked")??;
    watcher.abort();
    let acked = acked.load(Ordering::Relaxed);
    if acked != sequence {
        bail!("{id}: sent {sequence} batches, {acked} acknowledged");
    }
    Ok(())
}

/// Runs the bench; see the module docs.
pub fn run(bench: &ConnectionsBench) -> Result<ConnectionsReport> {
    if bench.actors == 0 || bench.batch == 0 || bench.window == 0 || bench.interval.is_zero() {
        bail!("--actors, --batch, --window and --interval-ms must be at least 1");
    }
    let dims = hac_envs::make("pendulum")?.spec().level_dims(0, 2);
    let message = encode_batch(0, 1, &level0_batch(dims, bench.batch));
    let dir = std::env::temp_dir().join(format!("hac-bench-connections-{}", std::process::id()));
    let args = [
        "--env",
        "pendulum",
        "--levels",
        "2",
        "--episodes",
        "1000000000",
    ]
    .map(String::from);
    let (learner, url) = LearnerProcess::spawn(&args, &dir, false, Stdio::null())?;
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .context("starting the bench runtime")?;
    let stop = Arc::new(AtomicBool::new(false));
    let counters = Arc::new(Counters::default());
    let tasks: Vec<_> = (0..bench.actors)
        .map(|i| {
            runtime.spawn(actor(
                i,
                url.clone(),
                message.clone(),
                bench.clone(),
                stop.clone(),
                counters.clone(),
            ))
        })
        .collect();

    let started = Instant::now();
    let mut samples = Vec::new();
    if !bench.json {
        outln!(
            "{:>8} {:>10} {:>10} {:>8} {:>10} {:>14}",
            "t (s)",
            "RSS MiB",
            "peak MiB",
            "threads",
            "actors",
            "transitions"
        );
    }
    loop {
        let at = started.elapsed();
        let (rss_kib, hwm_kib, threads) = read_status(learner.pid())?;
        let sample = Sample {
            at_s: at.as_secs_f64(),
            rss_kib,
            hwm_kib,
            threads,
            transitions_acked: counters.batches_acked.load(Ordering::Relaxed) * bench.batch as u64,
        };
        if !bench.json {
            outln!(
                "{:>8.0} {:>10.1} {:>10.1} {:>8} {:>10} {:>14}",
                sample.at_s,
                rss_kib as f64 / 1024.0,
                hwm_kib as f64 / 1024.0,
                threads,
                counters.connected.load(Ordering::Relaxed),
                sample.transitions_acked
            );
        }
        samples.push(sample);
        if at.as_secs_f64() >= bench.seconds {
            break;
        }
        let next = bench
            .sample_every
            .min(Duration::from_secs_f64(bench.seconds - at.as_secs_f64()));
        std::thread::sleep(next.max(Duration::from_millis(10)));
    }
    let connected = counters.connected.load(Ordering::Relaxed) as usize;
    stop.store(true, Ordering::Relaxed);
    let elapsed = started.elapsed().as_secs_f64();
    let mut failures = Vec::new();
    for task in tasks {
        match runtime.block_on(task) {
            Ok(Ok(())) => {}
            Ok(Err(e)) => failures.push(format!("{e:#}")),
            Err(e) => failures.push(format!("an actor task failed: {e}")),
        }
    }
    // VmHWM is updated lazily by the kernel: take the larger of it and every sample.
    let (_, hwm_kib, _) = read_status(learner.pid())?;
    let peak_rss_kib = samples
        .iter()
        .map(|s| s.rss_kib.max(s.hwm_kib))
        .fold(hwm_kib, u64::max);
    drop(runtime);
    learner.stop()?;
    if !failures.is_empty() {
        bail!(
            "{} of {} actors failed, first: {}",
            failures.len(),
            bench.actors,
            failures[0]
        );
    }
    let after_1_min = samples
        .iter()
        .find(|s| s.at_s >= 60.0)
        .or(samples.first())
        .map_or(0, |s| s.rss_kib);
    let batches_acked = counters.batches_acked.load(Ordering::Relaxed);
    Ok(ConnectionsReport {
        actors: bench.actors,
        actors_connected: connected,
        seconds: elapsed,
        batch_transitions: bench.batch,
        interval_ms: bench.interval.as_millis() as u64,
        batches_acked,
        transitions_per_s: (batches_acked * bench.batch as u64) as f64 / elapsed,
        ticks_skipped_full_window: counters.skipped.load(Ordering::Relaxed),
        peak_rss_kib,
        rss_after_1_min_kib: after_1_min,
        rss_last_kib: samples.last().map_or(0, |s| s.rss_kib),
        samples,
    })
}

/// `hac bench connections`: runs and prints the report.
pub fn run_and_print(bench: &ConnectionsBench) -> Result<()> {
    let report = run(bench)?;
    if bench.json {
        outln!("{}", serde_json::to_string(&report)?);
        return Ok(());
    }
    let mib = |kib: u64| kib as f64 / 1024.0;
    outln!(
        "{} actors ({} connected) for {:.0} s: {} batches of {} acknowledged ({:.0} transitions/s), {} ticks skipped with a full window",
        report.actors,
        report.actors_connected,
        report.seconds,
        report.batches_acked,
        report.batch_transitions,
        report.transitions_per_s,
        report.ticks_skipped_full_window
    );
    outln!(
        "learner memory: peak {:.1} MiB; resident {:.1} MiB after 1 min, {:.1} MiB at the end ({:+.1} MiB)",
        mib(report.peak_rss_kib),
        mib(report.rss_after_1_min_kib),
        mib(report.rss_last_kib),
        mib(report.rss_last_kib) - mib(report.rss_after_1_min_kib)
    );
    Ok(())
}
