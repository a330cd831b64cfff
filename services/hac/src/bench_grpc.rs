//! The gRPC parts of `hac bench`: ingest over real tonic streams on loopback, and weights
//! fan-out to many watchers.

use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use hac_learner::Learner;
use hac_proto::{ActorRole, Registration, encode_batch, pb};
use hac_serve::grpc::{ServerOptions, serve};
use tokio::sync::Semaphore;
use tokio_stream::wrappers::ReceiverStream;

use crate::bench::{IngestBench, IngestReport, Measured, level0_batch, percentiles};

/// A runtime and a learner server on an ephemeral loopback port; dropped = shut down.
struct Server {
    runtime: tokio::runtime::Runtime,
    url: String,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
}

impl Server {
    fn start(learner: &Arc<Learner>, workers: usize) -> Result<Self> {
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(workers)
            .enable_all()
            .build()
            .context("starting the bench runtime")?;
        let listener = runtime
            .block_on(tokio::net::TcpListener::bind("127.0.0.1:0"))
            .context("binding a loopback port")?;
        let url = format!("http://{}", listener.local_addr()?);
        let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
        let options = ServerOptions {
            drain_timeout: Duration::from_millis(500),
            ..ServerOptions::default()
        };
        runtime.spawn(serve(learner.clone(), listener, options, async move {
            let _ = stopped.await;
        }));
        Ok(Self {
            runtime,
            url,
            stop: Some(stop),
        })
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
    }
}

pub(crate) async fn client(
    url: &str,
) -> Result<pb::learner_client::LearnerClient<tonic::transport::Channel>> {
    Ok(pb::learner_client::LearnerClient::connect(url.to_string())
        .await
        .with_context(|| format!("connecting to {url}"))?
        .max_decoding_message_size(64 << 20)
        .max_encoding_message_size(64 << 20))
}

pub(crate) async fn register(
    client: &mut pb::learner_client::LearnerClient<tonic::transport::Channel>,
    id: &str,
) -> Result<u64> {
    let request = pb::RegisterRequest::from(Registration {
        actor_id: id.into(),
        role: ActorRole::Trainer,
        hostname: String::new(),
        transports: vec!["grpc".into()],
    });
    Ok(client.register(request).await?.into_inner().incarnation)
}

/// What one streaming sender saw.
struct SenderResult {
    acked_batches: u64,
    latencies_us: Vec<u32>,
}

/// `--actors` streams, each keeping `--window` batches in flight; latency is from handing a
/// message to the stream until the cumulative ack covering it.
pub fn ingest(bench: &IngestBench, learner: &Arc<Learner>) -> Result<IngestReport> {
    let server = Server::start(learner, 2)?;
    let batch = level0_batch(learner.dims()[0], bench.batch);
    let floats = batch.states.len() * 2 + batch.actions.len() + batch.goals.len() + 2 * batch.len;
    let message = encode_batch(0, 1, &batch);
    let stop = Arc::new(AtomicBool::new(false));
    let started = Arc::new(Mutex::new(None::<Instant>));
    let ready = Arc::new(tokio::sync::Barrier::new(bench.actors + 1));
    let mut tasks = Vec::new();
    for a in 0..bench.actors {
        let (url, message, stop, ready) = (
            server.url.clone(),
            message.clone(),
            stop.clone(),
            ready.clone(),
        );
        let window = bench.window;
        tasks.push(server.runtime.spawn(async move {
            let id = format!("bench-{a}");
            let mut client = client(&url).await?;
            let incarnation = register(&mut client, &id).await?;
            let (tx, rx) = tokio::sync::mpsc::channel::<pb::IngestRequest>(window);
            let mut acks = client.ingest(ReceiverStream::new(rx)).await?.into_inner();
            let permits = Arc::new(Semaphore::new(window));
            let in_flight = Arc::new(Mutex::new(VecDeque::<(u64, Instant)>::with_capacity(
                window,
            )));
            let sent = Arc::new(AtomicU64::new(0));
            let sender = {
                let (permits, in_flight, sent) = (permits.clone(), in_flight.clone(), sent.clone());
                let id = id.clone();
                async move {
                    ready.wait().await;
                    let mut sequence = 0u64;
                    while !stop.load(Ordering::Relaxed) {
                        permits.acquire().await?.forget();
                        sequence += 1;
                        in_flight
                            .lock()
                            .expect("no panics while held")
                            .push_back((sequence, Instant::now()));
                        let request = pb::IngestRequest {
                            actor_id: id.clone(),
                            incarnation,
                            sequence,
                            item: Some(pb::ingest_request::Item::Batch(message.clone())),
                        };
                        if tx.send(request).await.is_err() {
                            bail!("the ingest stream closed");
                        }
                        sent.store(sequence, Ordering::Relaxed);
                    }
                    // Dropping `tx` ends the request stream once everything is sent.
                    anyhow::Ok(sequence)
                }
            };
            let receiver = async {
                let mut latencies = Vec::with_capacity(1 << 16);
                let mut acked = 0u64;
                while let Some(ack) = acks.message().await? {
                    let now = Instant::now();
                    let mut queue = in_flight.lock().expect("no panics while held");
                    while queue.front().is_some_and(|&(s, _)| s <= ack.acked_through) {
                        let (_, t0) = queue.pop_front().expect("checked non-empty");
                        latencies
                            .push(now.duration_since(t0).as_micros().min(u32::MAX as u128) as u32);
                        permits.add_permits(1);
                    }
                    acked = ack.acked_through;
                }
                anyhow::Ok((acked, latencies))
            };
            let (last, (acked, latencies_us)) = tokio::try_join!(sender, receiver)?;
            if acked != last {
                bail!("{id}: sent {last} batches, {acked} acknowledged");
            }
            anyhow::Ok(SenderResult {
                acked_batches: acked,
                latencies_us,
            })
        }));
    }
    server.runtime.block_on(async {
        ready.wait().await;
    });
    *started.lock().expect("no panics while held") = Some(Instant::now());
    let t0 = Instant::now();
    std::thread::sleep(Duration::from_secs_f64(bench.seconds));
    stop.store(true, Ordering::Relaxed);
    let mut acked_batches = 0;
    let mut latencies = Vec::new();
    for task in tasks {
        let result = server
            .runtime
            .block_on(task)
            .context("a bench sender panicked")??;
        acked_batches += result.acked_batches;
        latencies.extend(result.latencies_us);
    }
    let elapsed = t0.elapsed().as_secs_f64();
    let status = learner.status();
    drop(server);
    Ok(IngestReport::new(
        crate::bench::Transport::Grpc,
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

/// `hac bench weights` result.
#[derive(Debug, Clone, serde::Serialize)]
pub struct FanoutReport {
    pub watchers: usize,
    pub versions: u64,
    pub snapshot_bytes: usize,
    pub deliveries: usize,
    pub expected_deliveries: usize,
    pub delay_p50_us: f64,
    pub delay_p99_us: f64,
    pub delay_max_us: f64,
}

/// `watchers` gRPC weights streams; the learner republishes its weights `versions` times,
/// `interval` apart; the delay is from publication to each watcher's receipt of that version.
pub fn fanout(
    learner: &Arc<Learner>,
    watchers: usize,
    versions: u64,
    interval: Duration,
) -> Result<FanoutReport> {
    let server = Server::start(learner, 2)?;
    let published: Arc<Mutex<Vec<(u64, Instant)>>> = Arc::default();
    let first = learner
        .weights()
        .latest()
        .context("the learner has published nothing")?;
    let snapshot_bytes = first.levels.iter().map(Vec::len).sum();
    let last_version = first.version + versions;
    let connected = Arc::new(tokio::sync::Barrier::new(watchers + 1));
    let mut tasks = Vec::new();
    for w in 0..watchers {
        let (url, connected) = (server.url.clone(), connected.clone());
        tasks.push(server.runtime.spawn(async move {
            let mut client = client(&url).await?;
            let id = format!("watch-{w}");
            let incarnation = register(&mut client, &id).await?;
            let mut stream = client
                .watch_weights(pb::WatchWeightsRequest {
                    actor_id: id,
                    incarnation,
                    min_version: 0,
                })
                .await?
                .into_inner();
            // The current version arrives at once: connected.
            let current = stream.message().await?.context("no current weights")?;
            connected.wait().await;
            let mut received = vec![(current.version, Instant::now())];
            while let Some(weights) = stream.message().await? {
                received.push((weights.version, Instant::now()));
                if weights.version >= last_version {
                    break;
                }
            }
            anyhow::Ok(received)
        }));
    }
    server.runtime.block_on(connected.wait());
    for _ in 0..versions {
        std::thread::sleep(interval);
        let t0 = Instant::now();
        let version = learner.republish();
        published
            .lock()
            .expect("no panics while held")
            .push((version, t0));
    }
    let published = published.lock().expect("no panics while held").clone();
    let mut delays = Vec::new();
    for task in tasks {
        let received = server
            .runtime
            .block_on(task)
            .context("a watcher panicked")??;
        for (version, at) in received {
            if let Some(&(_, t0)) = published.iter().find(|(v, _)| *v == version) {
                delays.push(
                    at.saturating_duration_since(t0)
                        .as_micros()
                        .min(u32::MAX as u128) as u32,
                );
            }
        }
    }
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
