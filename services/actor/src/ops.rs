//! The actor daemon's operations side: its flags ([`OpsArgs`], flattened into
//! [`ActorArgs`](crate::ActorArgs)), the [`Board`] every status and metrics answer is read from,
//! the [`Observed`] link that keeps the board current, and the status and metrics servers
//! ([`OpsServers`]) on a small runtime of their own.

use std::net::SocketAddr;
use std::sync::atomic::{AtomicBool, AtomicU8, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, OnceLock};
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use hac_core::rates::{RATES_WINDOW, RateWindow};
use hac_proto::{Admission, IngestItem, Published, Registration, WeightsSnapshot, pb};
use hac_run::security::{ClientTlsArgs, ServerTlsArgs, TokenArgs};
use hac_transport::grpc::{
    ActorNodeStatus, Health, STATUS_SERVICE, ServerSecurity, StatusSource, serve_status,
};
use hac_transport::metrics::{actor_metrics, serve_metrics};
use hac_transport::security::{ClientTls, Token};
use hac_transport::{
    ActorLink, EvaluationOf, GrantedTurn, IngestSink, LinkError, LinkStats, WeightsSource,
};
use tokio::net::TcpListener;
use tokio::sync::watch;

/// Status, metrics and security of the actor daemon.
#[derive(Debug, Clone, Default, clap::Args)]
pub struct OpsArgs {
    /// Serve this actor's own status (hac.v1.Status, health, reflection) over gRPC on ADDR
    /// (port 0 picks a free port; printed on stdout as `status on <addr>`) [default: off].
    #[arg(long, env = "HAC_STATUS_LISTEN", value_name = "ADDR")]
    pub status_listen: Option<SocketAddr>,
    /// Serve Prometheus metrics at http://ADDR/metrics (printed on stdout as
    /// `metrics on <addr>`) [default: off].
    #[arg(long, env = "HAC_METRICS_LISTEN", value_name = "ADDR")]
    pub metrics_listen: Option<SocketAddr>,
    #[command(flatten)]
    pub token: TokenArgs,
    #[command(flatten)]
    pub client_tls: ClientTlsArgs,
    #[command(flatten)]
    pub server_tls: ServerTlsArgs,
}

/// What the flags resolve to, checked before anything connects or binds.
#[derive(Debug)]
pub struct Ops {
    pub token: Option<Token>,
    pub client_tls: Option<ClientTls>,
    server: ServerSecurity,
    status_listen: Option<SocketAddr>,
    metrics_listen: Option<SocketAddr>,
}

impl OpsArgs {
    pub fn resolve(&self) -> Result<Ops> {
        let token = self.token.token()?;
        Ok(Ops {
            client_tls: self.client_tls.client_tls()?,
            server: ServerSecurity {
                token: token.clone(),
                tls: self.server_tls.server_tls()?,
            },
            token,
            status_listen: self.status_listen,
            metrics_listen: self.metrics_listen,
        })
    }
}

const CONNECTING: u8 = 0;
const RUNNING: u8 = 1;
const STOPPING: u8 = 2;

/// The actor's live state, written by the actor loop (through [`Observed`]) and read by the
/// status and metrics servers. Counters are atomics; nothing is locked across the actor's work.
#[derive(Debug)]
pub struct Board {
    actor_id: String,
    role: &'static str,
    hostname: String,
    learner: String,
    started: Instant,
    state: AtomicU8,
    transport: OnceLock<&'static str>,
    link: OnceLock<Arc<LinkStats>>,
    episodes: AtomicU64,
    successes: AtomicU64,
    env_steps: AtomicU64,
    evaluations: AtomicU64,
    weights_version: AtomicU64,
    rates: Mutex<RateWindow>,
    /// SIGINT/SIGTERM seen: the actor is stopping.
    interrupt: Arc<AtomicBool>,
}

impl Board {
    pub fn new(
        actor_id: String,
        role: &'static str,
        hostname: String,
        learner: String,
        interrupt: Arc<AtomicBool>,
    ) -> Self {
        let started = Instant::now();
        Self {
            actor_id,
            role,
            hostname,
            learner,
            started,
            state: AtomicU8::new(CONNECTING),
            transport: OnceLock::new(),
            link: OnceLock::new(),
            episodes: AtomicU64::default(),
            successes: AtomicU64::default(),
            env_steps: AtomicU64::default(),
            evaluations: AtomicU64::default(),
            weights_version: AtomicU64::default(),
            rates: Mutex::new(RateWindow::new(started, 1, RATES_WINDOW)),
            interrupt,
        }
    }

    /// The actor is done acting (finished, interrupted or failed).
    pub fn stopping(&self) {
        self.state.store(STOPPING, Ordering::Relaxed);
    }

    fn state(&self) -> u8 {
        if self.interrupt.load(Ordering::Relaxed) {
            STOPPING
        } else {
            self.state.load(Ordering::Relaxed)
        }
    }

    /// Registered and acting: ready in the health service's terms.
    fn ready(&self) -> bool {
        self.state() == RUNNING
    }

    pub fn snapshot(&self) -> ActorNodeStatus {
        let now = Instant::now();
        let env_steps = self.env_steps.load(Ordering::Relaxed);
        let (window, rate) = self
            .rates
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner())
            .rates(now, &[env_steps]);
        let link = self.link.get();
        let stat = |f: fn(&LinkStats) -> u64| link.map_or(0, |l| f(l));
        ActorNodeStatus {
            actor_id: self.actor_id.clone(),
            role: self.role,
            hostname: self.hostname.clone(),
            state: match self.state() {
                CONNECTING => "connecting",
                RUNNING => "running",
                _ => "stopping",
            },
            learner: self.learner.clone(),
            transport: self.transport.get().copied().unwrap_or(""),
            incarnation: stat(LinkStats::incarnation),
            uptime: now.saturating_duration_since(self.started),
            episodes: self.episodes.load(Ordering::Relaxed),
            successes: self.successes.load(Ordering::Relaxed),
            env_steps,
            env_steps_per_s: rate[0],
            rates_window: window,
            evaluations: self.evaluations.load(Ordering::Relaxed),
            weights_version: self.weights_version.load(Ordering::Relaxed),
            learner_weights_version: stat(LinkStats::learner_version),
            unacked: stat(LinkStats::unacked),
            reconnects: stat(LinkStats::reconnects),
            undurable: stat(LinkStats::undurable),
            sent_transitions: stat(LinkStats::sent_transitions),
            durable_transitions: stat(LinkStats::durable_transitions),
        }
    }
}

impl StatusSource for Board {
    fn node_status(&self, _max_evaluations: usize) -> pb::NodeStatus {
        (&self.snapshot()).into()
    }
}

/// An [`ActorLink`] that keeps a [`Board`] current with what passes through it: registrations,
/// episodes sent, evaluations reported.
pub struct Observed<'a> {
    inner: &'a mut dyn ActorLink,
    board: &'a Board,
}

impl std::fmt::Debug for Observed<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Observed")
            .field("board", self.board)
            .finish_non_exhaustive()
    }
}

impl<'a> Observed<'a> {
    pub fn new(inner: &'a mut dyn ActorLink, board: &'a Board) -> Self {
        let _ = board.transport.set(inner.transport());
        if let Some(stats) = inner.stats() {
            let _ = board.link.set(stats);
        }
        Self { inner, board }
    }
}

impl IngestSink for Observed<'_> {
    fn send(&mut self, item: IngestItem) -> Result<(), LinkError> {
        let episode = match &item {
            IngestItem::Episode {
                env_steps,
                success,
                weights_version,
            } => Some((*env_steps, *success, *weights_version)),
            IngestItem::Batch(_) => None,
        };
        self.inner.send(item)?;
        if let Some((env_steps, success, version)) = episode {
            let b = self.board;
            b.episodes.fetch_add(1, Ordering::Relaxed);
            b.successes.fetch_add(u64::from(success), Ordering::Relaxed);
            b.env_steps.fetch_add(env_steps, Ordering::Relaxed);
            b.weights_version.fetch_max(version, Ordering::Relaxed);
        }
        Ok(())
    }

    fn flush(&mut self, timeout: Duration) -> Result<(), LinkError> {
        self.inner.flush(timeout)
    }

    fn flush_durable(&mut self, timeout: Duration) -> Result<(), LinkError> {
        self.inner.flush_durable(timeout)
    }
}

impl WeightsSource for Observed<'_> {
    fn weights(&self) -> &Published<WeightsSnapshot> {
        self.inner.weights()
    }

    fn learner_version(&self) -> u64 {
        self.inner.learner_version()
    }
}

impl ActorLink for Observed<'_> {
    fn register(&mut self, registration: &Registration) -> Result<Admission, LinkError> {
        let admission = self.inner.register(registration)?;
        self.board.state.store(RUNNING, Ordering::Relaxed);
        Ok(admission)
    }

    fn await_turn(&mut self, wait: Duration) -> Result<Option<GrantedTurn>, LinkError> {
        self.inner.await_turn(wait)
    }

    fn report_evaluation(&mut self, report: &EvaluationOf) -> Result<bool, LinkError> {
        let recorded = self.inner.report_evaluation(report)?;
        if recorded {
            self.board.evaluations.fetch_add(1, Ordering::Relaxed);
            self.board
                .weights_version
                .fetch_max(report.weights_version, Ordering::Relaxed);
        }
        Ok(recorded)
    }

    fn stats(&self) -> Option<Arc<LinkStats>> {
        self.inner.stats()
    }

    fn transport(&self) -> &'static str {
        self.inner.transport()
    }
}

/// The actor's status and metrics servers, on a runtime of their own; [`stop`](Self::stop)
/// shuts them down.
#[derive(Debug)]
pub struct OpsServers {
    runtime: tokio::runtime::Runtime,
    stop: watch::Sender<bool>,
    tasks: Vec<tokio::task::JoinHandle<()>>,
}

/// Polls the board this often to move health to NOT_SERVING once the actor stops.
const HEALTH_POLL: Duration = Duration::from_millis(100);
/// How long a status connection may stay open once the actor stops.
const DRAIN_TIMEOUT: Duration = Duration::from_secs(2);

impl OpsServers {
    /// Binds `--status-listen` and `--metrics-listen` (whichever are set), prints their
    /// addresses on stdout and serves `board`; `None` if neither is set.
    pub fn start(ops: &Ops, board: Arc<Board>) -> Result<Option<Self>> {
        if ops.status_listen.is_none() && ops.metrics_listen.is_none() {
            return Ok(None);
        }
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .thread_name("hac-actor-ops")
            .enable_all()
            .build()
            .context("starting the status runtime")?;
        let (stop, _) = watch::channel(false);
        let mut tasks = Vec::new();
        let until_stop = |mut stop: watch::Receiver<bool>| async move {
            let _ = stop.wait_for(|&stop| stop).await;
        };
        if let Some(addr) = ops.status_listen {
            let listener = runtime
                .block_on(TcpListener::bind(addr))
                .with_context(|| format!("binding --status-listen {addr}"))?;
            let bound = listener.local_addr().context("reading the bound address")?;
            println!("status on {bound}");
            tracing::info!(addr = %bound, tls = ops.server.tls.is_some(), "status service listening");
            let health = runtime.block_on(Health::new(STATUS_SERVICE));
            tasks.push(runtime.spawn(report_health(
                health.clone(),
                board.clone(),
                stop.subscribe(),
            )));
            let security = ops.server.clone();
            let source: Arc<dyn StatusSource> = board.clone();
            let shutdown = until_stop(stop.subscribe());
            tasks.push(runtime.spawn(async move {
                let served =
                    serve_status(source, listener, &security, health, DRAIN_TIMEOUT, shutdown)
                        .await;
                if let Err(e) = served {
                    tracing::error!(error = %e, "status service failed");
                }
            }));
        }
        if let Some(addr) = ops.metrics_listen {
            let listener = runtime
                .block_on(TcpListener::bind(addr))
                .with_context(|| format!("binding --metrics-listen {addr}"))?;
            let bound = listener.local_addr().context("reading the bound address")?;
            println!("metrics on {bound}");
            tracing::info!(addr = %bound, path = "/metrics", "prometheus metrics served");
            let board = board.clone();
            let shutdown = until_stop(stop.subscribe());
            tasks.push(runtime.spawn(async move {
                let render = Arc::new(move || actor_metrics(&board.snapshot()));
                if let Err(e) = serve_metrics(listener, render, shutdown).await {
                    tracing::error!(error = %e, "metrics server failed");
                }
            }));
        }
        Ok(Some(Self {
            runtime,
            stop,
            tasks,
        }))
    }

    /// Reports NOT_SERVING, ends the status streams and stops both servers.
    pub fn stop(self) {
        self.stop.send_replace(true);
        let tasks = self.tasks;
        self.runtime.block_on(async move {
            for task in tasks {
                let _ = tokio::time::timeout(DRAIN_TIMEOUT * 2, task).await;
            }
        });
        self.runtime.shutdown_timeout(Duration::from_secs(1));
    }
}

/// Health follows the board: SERVING once registered, NOT_SERVING once stopping (for good).
async fn report_health(health: Health, board: Arc<Board>, mut stop: watch::Receiver<bool>) {
    let mut serving = false;
    loop {
        let ready = board.ready();
        if ready != serving {
            health.set_serving(ready).await;
            serving = ready;
        }
        if board.state() == STOPPING {
            return;
        }
        tokio::select! {
            () = tokio::time::sleep(HEALTH_POLL) => {}
            _ = stop.wait_for(|&stop| stop) => return,
        }
    }
}
