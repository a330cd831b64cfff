//! `hac bench update`: how fast one level's learner updates, on 1..N threads, against this
//! machine's own single-core `sgemm` on the same shapes: what sizing a learner host needs.
//!
//! The level's learner is built from the environment's default configuration for the chosen
//! number of levels (batch size and hidden layers, overridable), as the learner service builds
//! it; a fixed random minibatch is learned from repeatedly. Each thread count starts from the
//! same initial learner (a clone, with its own worker threads), warms up, then updates for
//! `--seconds`. The update's work is counted from the layer shapes
//! ([`hac_nn::LearnerConfig::update_flops`]); the `sgemm` peak is measured in the same
//! invocation on the hidden layers' three products ([`hac_nn::hidden_layer_sgemm_gflops`]), and
//! for each thread count above 1 as that many independent copies at once: the cores' own
//! scaling on work that shares nothing, the ceiling of the update's. Around each of those
//! rows it also times one cache line's round trip between two threads: how far apart the host
//! has put the cores, which on a virtual machine can change from one second to the next.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::Instant;

use anyhow::{Result, bail};
use hac_core::{Batch, EnvSpec, Rng};
use hac_nn::{LearnerConfig, LevelLearner};
use serde::Serialize;

/// `hac bench update` settings.
#[derive(Debug, Clone)]
pub struct UpdateBench {
    pub env: String,
    pub levels: usize,
    pub level: usize,
    /// Minibatch size; `None`: the environment's default.
    pub batch: Option<usize>,
    /// Hidden layer widths; `None`: the environment's default.
    pub hidden: Option<Vec<usize>>,
    /// Thread counts to measure; empty: 1 to the cores available.
    pub threads: Vec<usize>,
    pub seconds: f64,
    pub json: bool,
}

/// One thread count's measurement.
#[derive(Debug, Clone, Serialize)]
pub struct ThreadsRow {
    pub threads: usize,
    pub updates: u64,
    pub ms_per_update: f64,
    pub gflops: f64,
    /// `gflops` over the single-core `sgemm` peak.
    pub of_sgemm_peak: f64,
    /// Updates per second over those of the first row.
    pub speedup: f64,
    /// What this many cores deliver together on independent work of the update's shapes:
    /// `threads` copies of the single-core `sgemm` run at once, each on its own thread, their
    /// summed GFLOP/s over one copy's alone (measured just before). The update's `speedup`
    /// cannot beat it by more than the machine's drift.
    pub sgemm_scaling: f64,
    /// Microseconds per update outside the chunk parts the threads share, which no second
    /// thread takes (the minibatch copied in, the chunks' statistics, the two optimiser steps,
    /// which every thread takes whole on its own copy of the networks, and the target
    /// networks' Polyak step): with `ms_per_update` at one thread, Amdahl's bound on more
    /// threads.
    pub serial_us: f64,
    /// Microseconds per update the calling thread waits for the workers after its own share
    /// (0 on one thread): threads that finish unevenly, or cores that slow each other down.
    pub waiting_us: f64,
    /// Microseconds per update in the two optimiser steps (the chunk gradients summed, Adam,
    /// the kept transposes refreshed), part of `serial_us`.
    pub steps_us: f64,
    /// Nanoseconds for one cache line to go from one thread to another and back, measured
    /// just before and just after this row (null on one thread): about 65 ns between cores
    /// that share a cache on the AMD EPYC hosts of docs/RESULTS.md, 300-400 ns when the host
    /// put the virtual machine's two cores far apart. The threads of an update read each other's
    /// chunk gradients every step, so that distance is paid many times per update.
    pub round_trip_ns: Option<[f64; 2]>,
}

/// `hac bench update` result.
#[derive(Debug, Clone, Serialize)]
pub struct UpdateReport {
    pub env: String,
    pub levels: usize,
    pub level: usize,
    pub state: usize,
    pub goal: usize,
    pub action: usize,
    pub batch: usize,
    pub hidden: Vec<usize>,
    /// Cores available to this process.
    pub cores: usize,
    /// Chunks the minibatch is cut into: the most threads one update can use.
    pub chunks: usize,
    pub flops_per_update: u64,
    /// Single-core GFLOP/s of `sgemm` on the widest hidden layer's products at this batch.
    pub sgemm_peak_gflops: f64,
    /// The SIMD extension the kernels run on here (`avx512`, `avx2` or `baseline`).
    pub simd: String,
    pub rows: Vec<ThreadsRow>,
}

/// A minibatch of uniform states, goals and actions; a fifth of the samples reached their goal.
fn random_batch(config: &LearnerConfig, len: usize, rng: &mut Rng) -> Batch {
    let mut b = Batch::zeros(config.dims, len);
    for field in [
        &mut b.states,
        &mut b.next_states,
        &mut b.goals,
        &mut b.actions,
    ] {
        field.iter_mut().for_each(|v| *v = rng.uniform(-1.0, 1.0));
    }
    for (r, t) in b.rewards.iter_mut().zip(&mut b.terminals) {
        (*r, *t) = if rng.bernoulli(0.2) {
            (0.0, 1.0)
        } else {
            (-1.0, 0.0)
        };
    }
    b
}

/// The summed GFLOP/s of `threads` copies of [`hac_nn::hidden_layer_sgemm_gflops`] run at
/// once, each on its own thread for at least `seconds`.
fn concurrent_sgemm_gflops(width: usize, batch: usize, threads: usize, seconds: f64) -> f64 {
    std::thread::scope(|scope| {
        let copies: Vec<_> = (0..threads)
            .map(|_| scope.spawn(move || hac_nn::hidden_layer_sgemm_gflops(width, batch, seconds)))
            .collect();
        copies
            .into_iter()
            .map(|copy| copy.join().expect("sgemm thread panicked"))
            .sum()
    })
}

/// A cache line on its own, so that nothing else shares it.
#[repr(align(128))]
struct Line(AtomicU64);

/// Nanoseconds per round trip of one cache line between two threads, over at least
/// `seconds`: this thread writes an odd number, the other answers with the next one, this
/// thread waits for it. Both spin, so it needs two cores; on a busy machine a trip may wait for
/// a time slice, so the clock is read every 100 trips, not every 1000.
fn core_round_trip_ns(seconds: f64) -> f64 {
    let line = Line(AtomicU64::new(0));
    let stop = AtomicBool::new(false);
    std::thread::scope(|scope| {
        scope.spawn(|| {
            let mut expected = 1;
            while !stop.load(Ordering::Relaxed) {
                if line.0.load(Ordering::Acquire) == expected {
                    line.0.store(expected + 1, Ordering::Release);
                    expected += 2;
                }
                std::hint::spin_loop();
            }
        });
        let start = Instant::now();
        let mut trips = 0u64;
        let mut value = 1;
        while trips == 0 || start.elapsed().as_secs_f64() < seconds {
            for _ in 0..100 {
                line.0.store(value, Ordering::Release);
                while line.0.load(Ordering::Acquire) != value + 1 {
                    std::hint::spin_loop();
                }
                value += 2;
            }
            trips += 100;
        }
        let ns = start.elapsed().as_secs_f64() * 1e9 / trips as f64;
        stop.store(true, Ordering::Relaxed);
        ns
    })
}

/// Runs the bench.
pub fn run(bench: &UpdateBench) -> Result<UpdateReport> {
    let env = hac_envs::make(&bench.env)?;
    if bench.levels == 0 || bench.level >= bench.levels {
        bail!(
            "--level {} is not a level of a {}-level hierarchy",
            bench.level,
            bench.levels
        );
    }
    let mut agent = env.default_config(bench.levels);
    if let Some(batch) = bench.batch {
        agent.batch_size = batch;
    }
    if let Some(hidden) = &bench.hidden {
        agent.hidden_layers.clone_from(hidden);
    }
    if agent.batch_size == 0 || agent.hidden_layers.contains(&0) {
        bail!("the batch and every hidden layer need at least one unit");
    }
    let spec: &EnvSpec = env.spec();
    let config = LearnerConfig::for_level(&agent, spec, bench.level);
    let cores = hac_learner::available_threads();
    let threads = if bench.threads.is_empty() {
        (1..=cores).collect()
    } else {
        bench.threads.clone()
    };
    if threads
        .iter()
        .any(|&t| t == 0 || t > hac_nn::GRADIENT_CHUNKS)
    {
        bail!(
            "--threads: each count must be 1 to {} (an update's chunks)",
            hac_nn::GRADIENT_CHUNKS
        );
    }
    let batch_size = agent.batch_size;
    let widest = agent.hidden_layers.iter().copied().max().unwrap_or(0);
    let sgemm_peak_gflops = if widest >= 6 && batch_size >= 6 {
        hac_nn::hidden_layer_sgemm_gflops(widest, batch_size, bench.seconds.min(2.0))
    } else {
        f64::NAN
    };
    let flops = config.update_flops(batch_size);
    let mut rng = Rng::seed_from(1);
    let fresh = LevelLearner::new(config.clone(), &mut rng);
    let batch = random_batch(&config, batch_size, &mut rng);
    let mut rows: Vec<ThreadsRow> = Vec::new();
    let round_trip = |t: usize| (t > 1 && cores > 1).then(|| core_round_trip_ns(0.2));
    for &t in &threads {
        let mut learner = fresh.clone();
        learner.set_threads(t);
        let trip_before = round_trip(t);
        let warm_up = Instant::now();
        while warm_up.elapsed().as_secs_f64() < 0.2 {
            learner.update(&batch);
        }
        learner.reset_timing();
        let start = Instant::now();
        let mut updates = 0u64;
        while updates == 0 || start.elapsed().as_secs_f64() < bench.seconds {
            std::hint::black_box(learner.update(&batch));
            updates += 1;
        }
        let seconds = start.elapsed().as_secs_f64();
        let trip_after = round_trip(t);
        let timing = learner.timing();
        let per_update_us = |d: std::time::Duration| d.as_secs_f64() * 1e6 / updates as f64;
        let per_second = updates as f64 / seconds;
        let gflops = flops as f64 * per_second / 1e9;
        let speedup = rows
            .first()
            .map_or(1.0, |first| per_second * first.ms_per_update / 1e3);
        // One copy alone, then `t` at once, back to back: the machine's speed drifts over
        // seconds, so the ratio compares the two under the same conditions.
        let sgemm_scaling = if t == 1 || sgemm_peak_gflops.is_nan() {
            1.0
        } else {
            let seconds = bench.seconds.min(2.0);
            let alone = concurrent_sgemm_gflops(widest, batch_size, 1, seconds);
            concurrent_sgemm_gflops(widest, batch_size, t, seconds) / alone
        };
        rows.push(ThreadsRow {
            threads: t,
            updates,
            ms_per_update: 1e3 / per_second,
            gflops,
            of_sgemm_peak: gflops / sgemm_peak_gflops,
            speedup,
            sgemm_scaling,
            serial_us: per_update_us(timing.serial()),
            waiting_us: per_update_us(timing.waiting),
            steps_us: per_update_us(timing.steps),
            round_trip_ns: trip_before.zip(trip_after).map(|(a, b)| [a, b]),
        });
    }
    Ok(UpdateReport {
        env: bench.env.clone(),
        levels: bench.levels,
        level: bench.level,
        state: config.dims.state,
        goal: config.dims.goal,
        action: config.dims.action,
        batch: batch_size,
        hidden: agent.hidden_layers.clone(),
        cores,
        chunks: (batch_size / hac_nn::MIN_CHUNK_SAMPLES).clamp(1, hac_nn::GRADIENT_CHUNKS),
        flops_per_update: flops,
        sgemm_peak_gflops,
        simd: hac_nn::simd_extension().to_string(),
        rows,
    })
}

/// Runs the bench and prints its report (one JSON object with `json`).
pub fn run_and_print(bench: &UpdateBench) -> Result<()> {
    let r = run(bench)?;
    if bench.json {
        outln!("{}", serde_json::to_string(&r)?);
        return Ok(());
    }
    let hidden: Vec<String> = r.hidden.iter().map(usize::to_string).collect();
    outln!(
        "{} level {} of {} (state {}, goal {}, action {}), batch {}, hidden {}: {:.1} MFLOP per \
         update (matrix products) in {} chunks; single-core sgemm on the same shapes: {:.1} \
         GFLOP/s; kernels {}; {} cores",
        r.env,
        r.level,
        r.levels,
        r.state,
        r.goal,
        r.action,
        r.batch,
        hidden.join("x"),
        r.flops_per_update as f64 / 1e6,
        r.chunks,
        r.sgemm_peak_gflops,
        r.simd,
        r.cores
    );
    outln!(
        "| threads | ms/update | updates/s | GFLOP/s | of 1-core sgemm | speedup | sgemm copies at once | serial us | waiting us | steps us | core round trip ns, before / after |"
    );
    outln!("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |");
    for row in &r.rows {
        let trip = row
            .round_trip_ns
            .map_or("-".to_string(), |[a, b]| format!("{a:.0} / {b:.0}"));
        outln!(
            "| {} | {:.3} | {:.0} | {:.1} | {:.2} | {:.2}x | {:.2}x | {:.0} | {:.0} | {:.0} | {} |",
            row.threads,
            row.ms_per_update,
            1e3 / row.ms_per_update,
            row.gflops,
            row.of_sgemm_peak,
            row.speedup,
            row.sgemm_scaling,
            row.serial_us,
            row.waiting_us,
            row.steps_us,
            trip
        );
    }
    outln!(
        "(sgemm copies at once: that many independent single-core sgemm runs at the same time, \
         their summed rate over one alone: what the cores give together, the ceiling of the \
         speedup; serial: per update, the part no second thread shares (minibatch copy, the \
         chunks' statistics, optimiser and Polyak steps); waiting: per update, the calling \
         thread idle after its own share of the chunks until the workers finish theirs; steps: \
         per update, of serial, the two optimiser steps (gradient sums, Adam, transposes), \
         which every thread takes whole on its own copy of the networks; core round trip: one \
         cache line from one thread to another and back, just before and after the row: how \
         far apart the cores are)"
    );
    Ok(())
}
