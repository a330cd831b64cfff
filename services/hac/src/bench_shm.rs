//! The shared-memory parts of `hac bench`: ingest through real [`ShmLink`]s (registration over
//! loopback gRPC, batches over iceoryx2), and weights publication to same-host
//! [`WeightsReceiver`]s.

use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Barrier, Mutex};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use hac_learner::{Learner, Published};
use hac_proto::{ActorRole, DecodedBatch, IngestItem, Registration, WeightsSnapshot};
use hac_serve::grpc::{ServerOptions, serve};
use hac_serve::shm::{ShmServer, ShmServerOptions};
use hac_transport::grpc::GrpcLinkOptions;
use hac_transport::shm::{Namespace, ShmLink, ShmLinkOptions, ShmMode, WeightsReceiver};
use hac_transport::{ActorLink, IngestSink};

use crate::bench::{
    IngestBench, IngestReport, Measured, Transport, level0_batch, percentiles, run_senders,
};
use crate::bench_grpc::FanoutReport;

/// The learner served over loopback gRPC (registration) and shared memory; stops when dropped.
struct Served {
    /// Runs the gRPC server (registration) until dropped.
    _runtime: tokio::runtime::Runtime,
    url: String,
    shm: Option<ShmServer>,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
}

impl Served {
    fn start(learner: &Arc<Learner>, actors: usize, window: usize) -> Result<Self> {
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .enable_all()
            .build()
            .context("starting the bench runtime")?;
        let listener = runtime
            .block_on(tokio::net::TcpListener::bind("127.0.0.1:0"))
            .context("binding a loopback port")?;
        let addr = listener.local_addr()?;
        let namespace = Namespace::for_run(&learner.status().run_config_digest, addr);
        let shm = ShmServer::start(
            learner.clone(),
            namespace,
            ShmServerOptions {
                max_actors: actors + 2,
                window,
                ..ShmServerOptions::default()
            },
        )
        .context("serving shared memory")?;
        let options = ServerOptions {
            drain_timeout: Duration::from_millis(500),
            shm_offer: Some(shm.offer()),
            ..ServerOptions::default()
        };
        let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
        runtime.spawn(serve(learner.clone(), listener, options, async move {
            let _ = stopped.await;
        }));
        Ok(Self {
            _runtime: runtime,
            url: format!("http://{addr}"),
            shm: Some(shm),
            stop: Some(stop),
        })
    }
}

impl Drop for Served {
    fn drop(&mut self) {
        if let Some(shm) = self.shm.take() {
            shm.stop();
        }
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
    }
}

/// `--actors` threads, each an actor with its own [`ShmLink`] sending pre-made batches (a fresh
/// copy per send, as an actor's Adder hands them over) with up to `--window` unacknowledged;
/// latency is from `send` to the cumulative ack that covers the batch.
pub fn ingest(bench: &IngestBench, learner: &Arc<Learner>) -> Result<IngestReport> {
    let served = Served::start(learner, bench.actors, bench.window)?;
    let batch = level0_batch(learner.dims()[0], bench.batch);
    let floats = batch.states.len() * 2 + batch.actions.len() + batch.goals.len() + 2 * batch.len;
    let item = IngestItem::Batch(DecodedBatch {
        level: 0,
        weights_version: 1,
        batch,
    });
    let stop = Arc::new(AtomicBool::new(false));
    let start = Arc::new(Barrier::new(bench.actors + 1));
    let mut senders = Vec::new();
    for a in 0..bench.actors {
        let (item, stop, start) = (item.clone(), stop.clone(), start.clone());
        let url = served.url.clone();
        let options = ShmLinkOptions {
            mode: ShmMode::Require,
            window: bench.window,
            max_batch_transitions: bench.batch,
            ..ShmLinkOptions::default()
        };
        senders.push(std::thread::spawn(move || -> Result<(u64, Vec<u32>)> {
            let registered = (|| {
                let mut link = ShmLink::connect(&url, GrpcLinkOptions::default(), options)?;
                link.register(&Registration {
                    actor_id: format!("bench-{a}"),
                    role: ActorRole::Trainer,
                    hostname: String::new(),
                    transports: vec!["grpc".into(), "shm".into()],
                })?;
                anyhow::Ok(link)
            })();
            // Meet the others whatever happened, so that nobody waits for ever.
            start.wait();
            let mut link = registered.context("registering a bench actor")?;
            let mut in_flight = VecDeque::<(u64, Instant)>::with_capacity(1 << 10);
            let mut latencies = Vec::with_capacity(1 << 16);
            let mut sequence = 0u64;
            let mut record = |link: &ShmLink, in_flight: &mut VecDeque<(u64, Instant)>| {
                let acked = link.acked_through();
                let now = Instant::now();
                while in_flight.front().is_some_and(|&(s, _)| s <= acked) {
                    let (_, t0) = in_flight.pop_front().expect("checked non-empty");
                    latencies.push(now.duration_since(t0).as_micros().min(u32::MAX as u128) as u32);
                }
            };
            while !stop.load(Ordering::Relaxed) {
                sequence += 1;
                in_flight.push_back((sequence, Instant::now()));
                link.send(item.clone())?;
                record(&link, &mut in_flight);
            }
            link.flush(Duration::from_secs(30))?;
            record(&link, &mut in_flight);
            if link.acked_through() != sequence {
                bail!(
                    "bench-{a}: sent {sequence} batches, {} acknowledged",
                    link.acked_through()
                );
            }
            Ok((sequence, latencies))
        }));
    }
    let (acked_batches, mut latencies, elapsed) =
        run_senders(&start, &stop, bench.seconds, senders)?;
    let status = learner.status();
    drop(served);
    Ok(IngestReport::new(
        Transport::Shm,
        bench,
        bench.window,
        Measured {
            status: &status,
            seconds: elapsed,
            acked_batches,
            latencies_us: &mut latencies,
            floats,
        },
    ))
}

/// `watchers` same-host actors subscribed to the weights over shared memory; the learner
/// republishes its weights `versions` times, `interval` apart; the delay is from publication to
/// the snapshot being in each actor's weights cell (where the actor loop takes it).
pub fn fanout(
    learner: &Arc<Learner>,
    watchers: usize,
    versions: u64,
    interval: Duration,
) -> Result<FanoutReport> {
    let served = Served::start(learner, watchers, 8)?;
    let first = learner
        .weights()
        .latest()
        .context("the learner has published nothing")?;
    let snapshot_bytes = first.levels.iter().map(Vec::len).sum();
    let last_version = first.version + versions;
    let namespace = Namespace::parse(&served.shm.as_ref().expect("serving").offer().namespace)?;
    let connected = Arc::new(Barrier::new(watchers + 1));
    let mut tasks = Vec::new();
    for _ in 0..watchers {
        let cell = Arc::new(Published::<WeightsSnapshot>::default());
        let receiver =
            WeightsReceiver::start(&namespace, cell.clone(), Arc::new(AtomicU64::new(0)))
                .context("subscribing to the weights")?;
        let connected = connected.clone();
        tasks.push(std::thread::spawn(
            move || -> Result<Vec<(u64, Instant)>> {
                // The current version comes from the history: connected.
                let current = cell.wait_for(Duration::from_secs(30), |_| true);
                connected.wait();
                let current = current.context("no current weights")?;
                let mut received = vec![(current.version, Instant::now())];
                let mut last = current.version;
                while last < last_version {
                    let Some(w) = cell.wait_for(Duration::from_secs(30), |w| w.version > last)
                    else {
                        bail!("weights version {} never arrived", last + 1);
                    };
                    received.push((w.version, Instant::now()));
                    last = w.version;
                }
                drop(receiver);
                Ok(received)
            },
        ));
    }
    connected.wait();
    let published: Mutex<Vec<(u64, Instant)>> = Mutex::default();
    for _ in 0..versions {
        std::thread::sleep(interval);
        let t0 = Instant::now();
        let version = learner.republish();
        published
            .lock()
            .expect("no panics while held")
            .push((version, t0));
    }
    let published = published.into_inner().expect("no panics while held");
    let mut delays = Vec::new();
    for task in tasks {
        for (version, at) in task.join().expect("a watcher panicked")? {
            if let Some(&(_, t0)) = published.iter().find(|(v, _)| *v == version) {
                delays.push(
                    at.saturating_duration_since(t0)
                        .as_micros()
                        .min(u32::MAX as u128) as u32,
                );
            }
        }
    }
    drop(served);
    let deliveries = delays.len();
    let max = delays.iter().copied().max().unwrap_or(0) as f64;
    let (p50, p99) = percentiles(&mut delays);
    Ok(FanoutReport {
        watchers,
        versions,
        snapshot_bytes,
        deliveries,
        expected_deliveries: watchers * versions as usize,
        delay_p50_us: p50,
        delay_p99_us: p99,
        delay_max_us: max,
    })
}
