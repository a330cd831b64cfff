//! [`GrpcLink`]: the actor's side of the learner service.
//!
//! The link owns a small tokio runtime (one worker thread) with two tasks: the *ingest* task keeps
//! an `Ingest` stream open while anything waits for an ack, and the *weights* task keeps a
//! `WatchWeights` stream open and publishes each snapshot into the link's own
//! [`Published`] cell. The trait's blocking methods meet them in the *outbox*: every message the
//! actor sends stays there, numbered, until the learner acknowledges it.
//!
//! # Failures
//! - The learner unreachable, or a stream broken: reconnect after an exponential backoff with
//!   jitter and resend every unacknowledged message in order (the learner stores each sequence
//!   once). After `give_up_after` without an answer, the link fails with
//!   [`LinkError::Unavailable`].
//! - `unknown_actor` or `stale_incarnation` on any call or stream, the weights watch included (the
//!   learner restarted and lost its registry, or the id registered again elsewhere): register
//!   again with the same [`Registration`], naming the incarnation the messages are numbered under
//!   (the learner answers with a number above it), check that the run's config digest is
//!   unchanged (else [`LinkError::Refused`]: the run changed), renumber the unacknowledged
//!   messages from sequence 1 under the new incarnation and resend them. Whichever task finds the
//!   refusal registers (one at a time); the renumbering starts a new *generation* of the outbox,
//!   and an ingest stream, an ack or a call of an older generation is dropped when it next looks,
//!   so no message of the old numbering is sent after the new registration.
//! - `finished`: [`LinkError::Finished`]. Any other refusal (including `unauthenticated`: a
//!   missing or wrong token): [`LinkError::Refused`].
//!
//! # Security
//! With a [`Token`] every request carries `authorization: Bearer <token>`; with [`ClientTls`]
//! the learner's URL is `https://` and its certificate must chain to the configured CA.

use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use hac_core::Rng;
use hac_proto::{
    Admission, IngestItem, IngestMessage, PreviousIncarnation, Published, Registration,
    RejectReason, WeightsSnapshot, pb,
};
use parking_lot::{Condvar, Mutex};
use prost::Message as _;
use tokio::runtime::Runtime;
use tokio::sync::{Notify, mpsc, watch};
use tokio_stream::wrappers::ReceiverStream;
use tonic::codec::{Codec, DecodeBuf, Decoder, EncodeBuf, Encoder};
use tonic::codegen::http::uri::PathAndQuery;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::Channel;
use tonic::{Code, Status};

use super::{reject_reason, until_set};
use crate::held::Held;
use crate::security::{BearerToken, ClientTls, EndpointError, Token, endpoint};
use crate::{
    ActorLink, EvaluationOf, GrantedTurn, IngestSink, LinkError, LinkStats, WeightsSource,
};

/// The link's channel: every request carries the token, if any.
type LinkChannel = InterceptedService<Channel, BearerToken>;

/// How a [`GrpcLink`] talks to the learner.
#[derive(Debug, Clone)]
pub struct GrpcLinkOptions {
    /// Most messages sent and not yet acknowledged; [`IngestSink::send`] blocks while the window
    /// is full, which is how the learner's backpressure reaches the actor.
    pub window: usize,
    /// Most messages kept until the learner says they are durable (acknowledged ones included);
    /// [`IngestSink::send`] blocks while this many are held, so that a learner whose log falls
    /// behind holds its actors back too. Bounds the ack-durable gap, with the learner's commit
    /// interval.
    pub max_held: usize,
    /// First delay before reconnecting; each failure in a row doubles it, up to `backoff_max`.
    /// Each delay is drawn uniformly from its upper half (jitter), so actors that lost the same
    /// learner do not come back in lockstep.
    pub backoff_min: Duration,
    pub backoff_max: Duration,
    /// Longest wait for a TCP connection.
    pub connect_timeout: Duration,
    /// Give up (fail with [`LinkError::Unavailable`]) after the learner has not answered for this
    /// long.
    pub give_up_after: Duration,
    /// Largest message sent or received, in bytes (weights can be large).
    pub max_message_bytes: usize,
    /// Seed of the backoff jitter.
    pub jitter_seed: u64,
    /// Sent with every request, if set.
    pub token: Option<Token>,
    /// TLS to the learner (its URL must be `https://`, or a bare `host:port`), if set.
    pub tls: Option<ClientTls>,
    /// Keep a `WatchWeights` stream open from registration on. Off for a link that only carries
    /// the control plane beside shared memory (which brings the weights); see
    /// [`GrpcLink::watch_weights`].
    pub watch_weights: bool,
}

impl Default for GrpcLinkOptions {
    fn default() -> Self {
        let nanos = SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map_or(0, |d| d.subsec_nanos());
        Self {
            window: 256,
            max_held: 4096,
            backoff_min: Duration::from_millis(50),
            backoff_max: Duration::from_secs(5),
            connect_timeout: Duration::from_secs(5),
            give_up_after: Duration::from_secs(300),
            max_message_bytes: 64 << 20,
            jitter_seed: (u64::from(std::process::id()) << 32) | u64::from(nanos),
            token: None,
            tls: None,
            watch_weights: true,
        }
    }
}

/// Why [`GrpcLink::connect`] could not make a link.
#[derive(Debug, thiserror::Error)]
pub enum ConnectError {
    #[error("the learner's address: {0}")]
    Endpoint(#[from] EndpointError),
    #[error("the window must be at least 1")]
    ZeroWindow,
    #[error("max_held must be at least the window")]
    HeldBelowWindow,
    #[error("starting the link's runtime: {0}")]
    Runtime(#[source] std::io::Error),
}

/// Re-registrations in a row without an ack or a report getting through before the link gives
/// up: two actors sharing an id would otherwise take turns superseding each other for ever.
const MAX_REREGISTRATIONS: u32 = 5;
/// Requests queued for the ingest stream ahead of HTTP/2 flow control.
const REQUEST_QUEUE: usize = 8;
/// Reconnect warnings per stream at most this often (the rest go to debug).
const WARN_EVERY: Duration = Duration::from_secs(5);
const INGEST_PATH: &str = "/hac.v1.Learner/Ingest";

/// An [`ActorLink`] to a learner service over gRPC. Its methods block the calling thread (they
/// must not be called from async code); the network work happens on the link's own runtime,
/// which stops when the link is dropped.
#[derive(Debug)]
pub struct GrpcLink {
    shared: Arc<LinkState>,
    channel: LinkChannel,
    /// `Some` until drop.
    runtime: Option<Runtime>,
    ingest_started: bool,
    weights_started: bool,
}

#[derive(Debug)]
struct LinkState {
    options: GrpcLinkOptions,
    outbox: Mutex<Outbox>,
    /// Signalled on every ack and failure: senders waiting for room, flushes.
    changed: Condvar,
    /// Signalled when a message enters the outbox: the ingest task.
    queued: Notify,
    weights: Published<WeightsSnapshot>,
    /// Incarnation, unacknowledged messages, reconnects, the learner's newest version.
    stats: Arc<LinkStats>,
    /// Set when the link is dropped: the tasks end.
    closed: watch::Sender<bool>,
    /// One re-registration at a time (the ingest task and a report may both find the learner
    /// restarted). An async mutex: it is held across the register call.
    registering: tokio::sync::Mutex<()>,
    jitter: Mutex<Rng>,
}

/// Messages sent and not yet acknowledged, and the registration they are numbered under.
#[derive(Debug, Default)]
struct Outbox {
    registration: Option<Registration>,
    digest: String,
    /// 0 until registered.
    incarnation: u64,
    /// Bumped by every registration: a stream or call started under another generation is of an
    /// older numbering, whatever its incarnation number (a restarted learner can hand out the
    /// same number again).
    generation: u64,
    /// Every message the learner has not said is durable, acknowledged ones included, with what
    /// the learner said is durable and stored.
    held: Held<Arc<pb::IngestRequest>>,
    failure: Option<LinkError>,
    /// Re-registrations since the learner last acknowledged something.
    reregistrations: u32,
}

impl Outbox {
    /// Puts the outbox's counts into `stats`.
    fn report(&self, stats: &LinkStats) {
        stats.set_unacked(self.held.unacked());
        stats.set_undurable(self.held.undurable());
    }

    /// Applies an ack's watermarks (never past what was sent, never back); returns the
    /// transitions of the messages that became durable.
    fn acknowledge(&mut self, acked_through: u64, durable_through: u64) -> u64 {
        let mut transitions = 0;
        self.held
            .acknowledge(acked_through, durable_through, |msg| {
                transitions += transitions_of(&msg);
            });
        transitions
    }

    fn actor_id(&self) -> &str {
        self.registration
            .as_ref()
            .map_or("", |r| r.actor_id.as_str())
    }
}

impl GrpcLink {
    /// A link to the learner at `url` (`http://host:port`, `https://host:port` with
    /// `options.tls`; a bare `host:port` means either, as `options.tls` says). Connects lazily:
    /// nothing is sent before [`register`](ActorLink::register), which waits for the learner to
    /// come up (within `give_up_after`).
    pub fn connect(url: &str, options: GrpcLinkOptions) -> Result<Self, ConnectError> {
        if options.window == 0 {
            return Err(ConnectError::ZeroWindow);
        }
        if options.max_held < options.window {
            return Err(ConnectError::HeldBelowWindow);
        }
        let endpoint = endpoint(url, options.tls.as_ref())?
            .connect_timeout(options.connect_timeout)
            .tcp_nodelay(true)
            .http2_keep_alive_interval(Duration::from_secs(10))
            .keep_alive_timeout(Duration::from_secs(20))
            .keep_alive_while_idle(true);
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .thread_name("hac-link")
            .enable_all()
            .build()
            .map_err(ConnectError::Runtime)?;
        let channel = {
            let _entered = runtime.enter();
            InterceptedService::new(endpoint.connect_lazy(), BearerToken(options.token.clone()))
        };
        let shared = Arc::new(LinkState {
            jitter: Mutex::new(Rng::seed_from(options.jitter_seed)),
            options,
            outbox: Mutex::default(),
            changed: Condvar::new(),
            queued: Notify::new(),
            weights: Published::default(),
            stats: Arc::default(),
            closed: watch::Sender::new(false),
            registering: tokio::sync::Mutex::new(()),
        });
        Ok(Self {
            shared,
            channel,
            runtime: Some(runtime),
            ingest_started: false,
            weights_started: false,
        })
    }

    /// Starts the `WatchWeights` stream if it is not running (a link made with
    /// `watch_weights: false` that turns out to need it). Takes effect once registered.
    pub fn watch_weights(&mut self) {
        if self.ingest_started && !self.weights_started {
            self.weights_started = true;
            let task = weights_task(self.shared.clone(), self.channel.clone());
            self.runtime().spawn(task);
        }
    }

    /// Messages sent and not yet acknowledged.
    pub fn unacked(&self) -> usize {
        self.shared.outbox.lock().held.unacked()
    }

    /// The most messages the link holds until durable (`max_held`).
    pub fn max_held(&self) -> usize {
        self.shared.options.max_held
    }

    /// Numbers this link's next message `sequence + 1` under its incarnation, if it holds
    /// nothing: it goes on with a numbering begun elsewhere (the shared-memory link falling back
    /// to gRPC after the learner kept its incarnation, with everything through `sequence`
    /// durable).
    pub(crate) fn continue_after(&self, sequence: u64) {
        let mut outbox = self.shared.outbox.lock();
        outbox.held.continue_after(sequence);
        outbox.report(&self.shared.stats);
    }

    /// Messages kept until the learner says they are durable (acknowledged ones included).
    pub fn held(&self) -> usize {
        self.shared.outbox.lock().held.len()
    }

    /// The incarnation messages are numbered under now (0 before registration).
    pub fn incarnation(&self) -> u64 {
        self.shared.outbox.lock().incarnation
    }

    fn runtime(&self) -> &Runtime {
        self.runtime.as_ref().expect("the runtime lives until drop")
    }
}

impl Drop for GrpcLink {
    fn drop(&mut self) {
        self.shared.closed.send_replace(true);
        if let Some(runtime) = self.runtime.take() {
            runtime.shutdown_background();
        }
    }
}

impl GrpcLink {
    /// [`register`](ActorLink::register), naming the incarnation the caller's messages are
    /// numbered under, if any (`previous`): a learner that holds every one of them before
    /// `previous.resend_from` keeps that incarnation, any other answers with a fresh one above
    /// it. For a link that numbers messages of its own, the shared-memory link whose control
    /// plane this is; this link's own outbox is numbered under the admission either way.
    pub(crate) fn register_naming(
        &mut self,
        registration: &Registration,
        previous: Option<PreviousIncarnation>,
    ) -> Result<Admission, LinkError> {
        let shared = self.shared.clone();
        let channel = self.channel.clone();
        let mut request = pb::RegisterRequest::from(registration.clone());
        if let Some(previous) = previous {
            previous.into_request(&mut request);
        }
        let admission = self
            .runtime()
            .block_on(register_until_admitted(&shared, &channel, request))?;
        {
            let mut outbox = shared.outbox.lock();
            outbox.registration = Some(registration.clone());
            outbox.digest = admission.run_config_digest.clone();
            renumber(&mut outbox, &shared.stats, admission.incarnation);
        }
        shared.stats.learner_version.store(0, Ordering::Relaxed);
        if !self.ingest_started {
            self.ingest_started = true;
            self.runtime()
                .spawn(ingest_task(shared.clone(), channel.clone()));
            if shared.options.watch_weights {
                self.watch_weights();
            }
        }
        Ok(admission)
    }
}

impl IngestSink for GrpcLink {
    fn send(&mut self, item: IngestItem) -> Result<(), LinkError> {
        // Encode outside the lock; the numbering is filled in under it.
        let mut msg = pb::IngestRequest::from(IngestMessage {
            actor_id: String::new(),
            incarnation: 0,
            sequence: 0,
            item,
        });
        let shared = &self.shared;
        let mut outbox = shared.outbox.lock();
        loop {
            if let Some(e) = &outbox.failure {
                return Err(e.clone());
            }
            if outbox.incarnation == 0 {
                return Err(LinkError::Refused("send before register".into()));
            }
            if outbox
                .held
                .has_room(shared.options.window, shared.options.max_held)
            {
                break;
            }
            shared
                .changed
                .wait_for(&mut outbox, Duration::from_millis(500));
        }
        msg.actor_id = outbox.actor_id().to_string();
        msg.incarnation = outbox.incarnation;
        msg.sequence = outbox.held.next_sequence();
        let transitions = transitions_of(&msg);
        outbox.held.push(Arc::new(msg));
        outbox.report(&shared.stats);
        shared
            .stats
            .sent_transitions
            .fetch_add(transitions, Ordering::Relaxed);
        drop(outbox);
        shared.queued.notify_one();
        Ok(())
    }

    fn flush(&mut self, timeout: Duration) -> Result<(), LinkError> {
        let deadline = Instant::now() + timeout;
        let mut outbox = self.shared.outbox.lock();
        loop {
            if let Some(e) = &outbox.failure {
                return Err(e.clone());
            }
            if outbox.held.unacked() == 0 {
                return Ok(());
            }
            if self
                .shared
                .changed
                .wait_until(&mut outbox, deadline)
                .timed_out()
                && outbox.held.unacked() != 0
            {
                return Err(LinkError::TimedOut(outbox.held.unacked()));
            }
        }
    }

    fn flush_durable(&mut self, timeout: Duration) -> Result<(), LinkError> {
        let deadline = Instant::now() + timeout;
        let mut outbox = self.shared.outbox.lock();
        loop {
            if let Some(e) = &outbox.failure {
                return Err(e.clone());
            }
            if outbox.held.is_empty() {
                return Ok(());
            }
            if self
                .shared
                .changed
                .wait_until(&mut outbox, deadline)
                .timed_out()
                && !outbox.held.is_empty()
            {
                return Err(LinkError::TimedOut(outbox.held.len()));
            }
        }
    }
}

impl WeightsSource for GrpcLink {
    fn weights(&self) -> &Published<WeightsSnapshot> {
        &self.shared.weights
    }

    fn learner_version(&self) -> u64 {
        self.shared.stats.learner_version()
    }
}

impl ActorLink for GrpcLink {
    fn register(&mut self, registration: &Registration) -> Result<Admission, LinkError> {
        self.register_naming(registration, None)
    }

    fn stats(&self) -> Option<Arc<LinkStats>> {
        Some(self.shared.stats.clone())
    }

    fn transport(&self) -> &'static str {
        "grpc"
    }

    fn await_turn(&mut self, wait: Duration) -> Result<Option<GrantedTurn>, LinkError> {
        let shared = self.shared.clone();
        let channel = self.channel.clone();
        let wait_ms = u32::try_from(wait.as_millis()).unwrap_or(u32::MAX);
        self.runtime().block_on(async move {
            let mut client = learner_client(&shared, &channel);
            let mut retry = Retry::new(&shared, "turn request");
            loop {
                let (actor_id, incarnation, generation) = {
                    let outbox = shared.outbox.lock();
                    let id = outbox.actor_id().to_string();
                    (id, outbox.incarnation, outbox.generation)
                };
                let mut request = tonic::Request::new(pb::TurnRequest {
                    actor_id,
                    incarnation,
                    wait_ms,
                });
                // The learner answers within its own cap on the wait; a dead connection must
                // not hold the actor longer than that.
                request.set_timeout(wait + Duration::from_secs(15));
                let status = match client.await_turn(request).await {
                    Ok(reply) => {
                        let reply = reply.into_inner();
                        return Ok(reply.granted.then_some(GrantedTurn {
                            trained: reply.episodes,
                            episode: reply.episode,
                        }));
                    }
                    Err(status) => status,
                };
                match Failure::of(&status) {
                    Failure::Retry => retry.wait(&status).await?,
                    Failure::Reregister => {
                        reregister(&shared, &channel, generation).await?;
                        return Ok(None);
                    }
                    Failure::Finished => return Err(LinkError::Finished),
                    Failure::Refused => return Err(LinkError::Refused(status.message().into())),
                }
            }
        })
    }

    fn report_evaluation(&mut self, report: &EvaluationOf) -> Result<bool, LinkError> {
        let shared = self.shared.clone();
        let channel = self.channel.clone();
        let report = *report;
        self.runtime().block_on(async move {
            let mut client = learner_client(&shared, &channel);
            let mut retry = Retry::new(&shared, "evaluation report");
            loop {
                let (actor_id, incarnation, generation) = {
                    let outbox = shared.outbox.lock();
                    let id = outbox.actor_id().to_string();
                    (id, outbox.incarnation, outbox.generation)
                };
                let message = pb::EvaluationReport {
                    actor_id,
                    incarnation,
                    weights_version: report.weights_version,
                    episodes: report.episodes,
                    successes: report.successes,
                    learner_start: report.learner_start,
                };
                let status = match client.report_evaluation(message).await {
                    Ok(_) => {
                        shared.outbox.lock().reregistrations = 0;
                        return Ok(true);
                    }
                    Err(status) => status,
                };
                if reject_reason(&status) == Some(RejectReason::StaleWeights) {
                    tracing::warn!(
                        weights_version = report.weights_version,
                        "the learner restarted since these weights were published: dropping \
                         their evaluation"
                    );
                    return Ok(false);
                }
                match Failure::of(&status) {
                    Failure::Retry => retry.wait(&status).await?,
                    // The learner forgot this actor (it restarted): register again and
                    // report again. Weights of the learner before the restart are refused as
                    // stale (above); the restarted learner's own are recorded.
                    Failure::Reregister => reregister(&shared, &channel, generation).await?,
                    Failure::Finished => return Err(LinkError::Finished),
                    Failure::Refused => return Err(LinkError::Refused(status.message().into())),
                }
            }
        })
    }
}

/// What to do about a failed call or stream.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Failure {
    /// The learner is unreachable, restarting or shutting down: try again after a backoff.
    Retry,
    /// The learner does not know this incarnation: register again.
    Reregister,
    Finished,
    /// The learner refused what the actor sent: retrying cannot help.
    Refused,
}

impl Failure {
    fn of(status: &Status) -> Self {
        match reject_reason(status) {
            Some(RejectReason::Finished) => Self::Finished,
            // A gap: a restarted learner lacks messages this link no longer holds (it said they
            // were durable). Registering again gets a fresh incarnation, and everything held is
            // resent under it.
            Some(
                RejectReason::UnknownActor
                | RejectReason::StaleIncarnation
                | RejectReason::SequenceGap,
            ) => Self::Reregister,
            Some(_) => Self::Refused,
            // No reason: tonic, hyper or the network speaking, not the learner.
            None => match status.code() {
                Code::Unavailable
                | Code::Unknown
                | Code::Internal
                | Code::Cancelled
                | Code::DeadlineExceeded
                | Code::Aborted
                | Code::ResourceExhausted => Self::Retry,
                _ => Self::Refused,
            },
        }
    }
}

/// Backoff, give-up deadline and rate-limited warnings for one kind of call.
struct Retry<'a> {
    shared: &'a LinkState,
    what: &'static str,
    delay: Duration,
    attempts: u64,
    failing_since: Option<Instant>,
    last_warning: Option<Instant>,
    closed: watch::Receiver<bool>,
}

impl<'a> Retry<'a> {
    fn new(shared: &'a LinkState, what: &'static str) -> Self {
        Self {
            shared,
            what,
            delay: shared.options.backoff_min,
            attempts: 0,
            failing_since: None,
            last_warning: None,
            closed: shared.closed.subscribe(),
        }
    }

    /// The learner answered: start over with the shortest delay.
    fn succeeded(&mut self) {
        if self.attempts > 0 {
            tracing::info!(
                stream = self.what,
                attempts = self.attempts,
                "learner reachable again"
            );
        }
        self.delay = self.shared.options.backoff_min;
        self.attempts = 0;
        self.failing_since = None;
        self.last_warning = None;
    }

    /// The learner answered, though nothing went through yet: the give-up clock starts over
    /// (the backoff does not).
    fn answered(&mut self) {
        self.failing_since = None;
    }

    /// Sleeps before the next attempt; fails once the learner has been silent for
    /// `give_up_after`, or if the link closes meanwhile. After the final weights the learner
    /// is expected to go away: then the answer is [`LinkError::Finished`] at once.
    async fn wait(&mut self, status: &Status) -> Result<(), LinkError> {
        if self.shared.weights.latest().is_some_and(|w| w.run_finished) {
            return Err(LinkError::Finished);
        }
        let options = &self.shared.options;
        let since = *self.failing_since.get_or_insert_with(Instant::now);
        if since.elapsed() >= options.give_up_after {
            return Err(LinkError::Unavailable(format!(
                "no answer from the learner for {:?}: {}",
                options.give_up_after,
                status.message()
            )));
        }
        self.attempts += 1;
        self.shared.stats.reconnects.fetch_add(1, Ordering::Relaxed);
        let upper = self.delay;
        self.delay = (upper * 2).min(options.backoff_max);
        let delay = upper.mul_f64(0.5 + 0.5 * self.shared.jitter.lock().unit_f64());
        if self
            .last_warning
            .is_none_or(|at| at.elapsed() >= WARN_EVERY)
        {
            self.last_warning = Some(Instant::now());
            tracing::warn!(
                stream = self.what,
                attempts = self.attempts,
                retry_in = ?delay,
                code = ?status.code(),
                error = status.message(),
                "learner unreachable; retrying"
            );
        } else {
            tracing::debug!(stream = self.what, attempts = self.attempts, retry_in = ?delay, error = status.message(), "retrying");
        }
        tokio::select! {
            () = tokio::time::sleep(delay) => Ok(()),
            () = until_set(&mut self.closed) => Err(LinkError::Closed),
        }
    }
}

fn learner_client(
    shared: &LinkState,
    channel: &LinkChannel,
) -> pb::learner_client::LearnerClient<LinkChannel> {
    let max = shared.options.max_message_bytes;
    pb::learner_client::LearnerClient::new(channel.clone())
        .max_decoding_message_size(max)
        .max_encoding_message_size(max)
}

async fn register_until_admitted(
    shared: &LinkState,
    channel: &LinkChannel,
    request: pb::RegisterRequest,
) -> Result<Admission, LinkError> {
    let mut client = learner_client(shared, channel);
    let mut retry = Retry::new(shared, "register");
    loop {
        let status = match client.register(request.clone()).await {
            Ok(response) => {
                return Admission::try_from(response.into_inner()).map_err(|e| {
                    LinkError::Refused(format!("the learner's admission is invalid: {e}"))
                });
            }
            Err(status) => status,
        };
        match Failure::of(&status) {
            Failure::Retry => retry.wait(&status).await?,
            Failure::Finished => return Err(LinkError::Finished),
            Failure::Reregister | Failure::Refused => {
                return Err(LinkError::Refused(status.message().into()));
            }
        }
    }
}

/// Numbers the outbox's messages from sequence 1 under `incarnation`, a new generation: streams
/// and calls of the old one end when they next look.
fn renumber(outbox: &mut Outbox, stats: &LinkStats, incarnation: u64) {
    outbox.incarnation = incarnation;
    outbox.generation += 1;
    stats.incarnation.store(incarnation, Ordering::Relaxed);
    outbox.held.renumber();
    for (sequence, msg) in outbox.held.numbered_mut() {
        // Copies only a message still queued in a stream being torn down.
        let msg = Arc::make_mut(msg);
        msg.incarnation = incarnation;
        msg.sequence = sequence;
    }
}

/// Registers again after the learner refused a call or stream of generation `failed` as unknown
/// or stale, unless another task already did; renumbers the outbox under the new incarnation (a
/// new generation). The registration names the current incarnation, so the learner answers with
/// a number above it: messages of the old numbering still in flight on a stream being torn down
/// are refused as stale, never taken for the new incarnation's.
async fn reregister(
    shared: &LinkState,
    channel: &LinkChannel,
    failed: u64,
) -> Result<(), LinkError> {
    let _one_at_a_time = shared.registering.lock().await;
    let (request, digest) = {
        let mut outbox = shared.outbox.lock();
        if outbox.generation != failed {
            return Ok(());
        }
        outbox.reregistrations += 1;
        if outbox.reregistrations > MAX_REREGISTRATIONS {
            return Err(LinkError::Refused(format!(
                "registered {MAX_REREGISTRATIONS} times in a row without getting anything through: \
                 is another actor using the id `{}`?",
                outbox.actor_id()
            )));
        }
        let registration = outbox
            .registration
            .clone()
            .ok_or_else(|| LinkError::Refused("send before register".into()))?;
        let mut request = pb::RegisterRequest::from(registration);
        PreviousIncarnation {
            incarnation: outbox.incarnation,
            resend_from: outbox.held.durable_through() + 1,
        }
        .into_request(&mut request);
        (request, outbox.digest.clone())
    };
    let admission = register_until_admitted(shared, channel, request.clone()).await?;
    if admission.run_config_digest != digest {
        return Err(LinkError::Refused(format!(
            "the learner runs a different config now (digest {}, registered under {digest}): \
             restart the actor",
            admission.run_config_digest
        )));
    }
    let (resent, kept) = {
        let mut outbox = shared.outbox.lock();
        let kept = admission.incarnation == outbox.incarnation;
        if kept {
            // A resumed learner that recovered this incarnation: the same numbering, resent from
            // the oldest message not durable (it acknowledges what it has as duplicates).
            outbox.generation += 1;
            outbox.held.rewind();
        } else {
            renumber(&mut outbox, &shared.stats, admission.incarnation);
        }
        outbox.report(&shared.stats);
        (outbox.held.len(), kept)
    };
    // An ingest stream open under the old incarnation (another task registered again) starts
    // over once woken.
    shared.queued.notify_one();
    shared.stats.learner_version.store(0, Ordering::Relaxed);
    tracing::info!(
        actor = %request.actor_id,
        incarnation = admission.incarnation,
        kept,
        resent,
        "registered again with the learner"
    );
    Ok(())
}

impl LinkState {
    fn fail(&self, error: LinkError) {
        let mut outbox = self.outbox.lock();
        if outbox.failure.is_none() {
            if matches!(error, LinkError::Finished) {
                tracing::info!("the learner says the run is finished");
            } else {
                tracing::warn!(%error, "link failed");
            }
            outbox.failure = Some(error);
        }
        drop(outbox);
        self.changed.notify_all();
    }

    /// Applies an ack of a stream of `generation`; false (and nothing applied) if the outbox was
    /// renumbered since: the ack counts messages of the old numbering.
    fn on_ack(&self, generation: u64, ack: &pb::IngestAck) -> bool {
        let mut outbox = self.outbox.lock();
        if outbox.generation != generation {
            return false;
        }
        let transitions = outbox.acknowledge(ack.acked_through, ack.durable_through);
        outbox.report(&self.stats);
        self.stats
            .durable_transitions
            .fetch_add(transitions, Ordering::Relaxed);
        outbox.reregistrations = 0;
        drop(outbox);
        self.stats
            .learner_version
            .store(ack.weights_version, Ordering::Relaxed);
        self.changed.notify_all();
        true
    }
}

/// The transitions an ingest message carries (0 for an episode summary).
fn transitions_of(msg: &pb::IngestRequest) -> u64 {
    match &msg.item {
        Some(pb::ingest_request::Item::Batch(batch)) => u64::from(batch.count),
        _ => 0,
    }
}

/// Why one ingest stream ended.
enum StreamEnd {
    Closed,
    /// The stream, of this generation, failed.
    Failed(Status, u64),
    /// Another task registered again and renumbered the outbox: what the stream sent is
    /// numbered under the old incarnation, so a new stream starts from the oldest message.
    Renumbered,
}

/// Keeps an ingest stream open while anything waits for an ack; reconnects, re-registers and
/// resends as the module docs say.
async fn ingest_task(shared: Arc<LinkState>, channel: LinkChannel) {
    let mut closed = shared.closed.subscribe();
    let mut retry = Retry::new(&shared, "ingest");
    loop {
        // Open a stream only when there is something to send.
        loop {
            if shared.outbox.lock().held.is_empty() {
                tokio::select! {
                    () = shared.queued.notified() => {}
                    () = until_set(&mut closed) => return,
                }
            } else {
                break;
            }
        }
        let (status, generation) = match ingest_stream(&shared, &channel, &mut retry).await {
            StreamEnd::Closed => return,
            StreamEnd::Renumbered => continue,
            StreamEnd::Failed(status, generation) => (status, generation),
        };
        let outcome = match Failure::of(&status) {
            Failure::Retry => retry.wait(&status).await,
            Failure::Reregister => reregister(&shared, &channel, generation).await,
            Failure::Finished => Err(LinkError::Finished),
            Failure::Refused => Err(LinkError::Refused(status.message().into())),
        };
        match outcome {
            Ok(()) => {}
            Err(LinkError::Closed) => return,
            Err(e) => return shared.fail(e),
        }
    }
}

/// One ingest stream: sends every unacknowledged message from the oldest on, then each new one;
/// applies acks as they come; returns when the stream fails, the outbox is renumbered (another
/// task registered again) or the link closes. The stream belongs to the generation current when
/// it opened: it sends only messages numbered under it, and checks that under the outbox's lock
/// each time it takes one, so a registration, its renumbering and the start of the next stream
/// are one step as far as the learner can tell.
async fn ingest_stream(
    shared: &LinkState,
    channel: &LinkChannel,
    retry: &mut Retry<'_>,
) -> StreamEnd {
    let mut closed = shared.closed.subscribe();
    let opened_under = shared.outbox.lock().generation;
    let max = shared.options.max_message_bytes;
    let mut grpc = tonic::client::Grpc::new(channel.clone())
        .max_decoding_message_size(max)
        .max_encoding_message_size(max);
    let (tx, rx) = mpsc::channel::<Arc<pb::IngestRequest>>(REQUEST_QUEUE);
    let opened = async {
        grpc.ready()
            .await
            .map_err(|e| Status::unavailable(e.to_string()))?;
        grpc.streaming(
            tonic::Request::new(ReceiverStream::new(rx)),
            PathAndQuery::from_static(INGEST_PATH),
            IngestCodec,
        )
        .await
    };
    let response = tokio::select! {
        response = opened => response,
        () = until_set(&mut closed) => return StreamEnd::Closed,
    };
    let mut acks = match response {
        Ok(response) => response.into_inner(),
        Err(status) => return StreamEnd::Failed(status, opened_under),
    };
    retry.answered();
    let (mut sent_through, generation) = {
        let outbox = shared.outbox.lock();
        if outbox.generation != opened_under {
            // Registered again while the stream opened: start over under the new numbering.
            return StreamEnd::Renumbered;
        }
        // From the oldest message not durable: a restarted learner may have lost what it
        // acknowledged after its log's last commit (one that did not acknowledges duplicates).
        (outbox.held.durable_through(), outbox.generation)
    };
    loop {
        let next = {
            let outbox = shared.outbox.lock();
            if outbox.generation != generation {
                return StreamEnd::Renumbered;
            }
            outbox.held.has_after(sent_through)
        };
        tokio::select! {
            biased;
            () = until_set(&mut closed) => return StreamEnd::Closed,
            ack = acks.message() => match ack {
                Ok(Some(ack)) => {
                    retry.succeeded();
                    if !shared.on_ack(generation, &ack) {
                        return StreamEnd::Renumbered;
                    }
                }
                Ok(None) => {
                    return StreamEnd::Failed(Status::unavailable("the learner ended the ingest stream"), generation);
                }
                Err(status) => return StreamEnd::Failed(status, generation),
            },
            permit = tx.reserve(), if next => {
                let Ok(permit) = permit else {
                    return StreamEnd::Failed(Status::unavailable("the ingest stream closed"), generation);
                };
                // Taken and sent under the lock: never a message of another numbering.
                let outbox = shared.outbox.lock();
                if outbox.generation != generation {
                    return StreamEnd::Renumbered;
                }
                if let Some(msg) = outbox.held.after(sent_through).cloned() {
                    sent_through = msg.sequence;
                    permit.send(msg);
                }
            }
            () = shared.queued.notified(), if !next => {}
        }
    }
}

/// Keeps a weights stream open and publishes every snapshot it brings. Asks for the learner's
/// current version each time (`min_version` 0): after a restart, versions start again lower, and
/// the link takes them as they come.
async fn weights_task(shared: Arc<LinkState>, channel: LinkChannel) {
    let mut closed = shared.closed.subscribe();
    let mut retry = Retry::new(&shared, "weights");
    let mut client = learner_client(&shared, &channel);
    loop {
        let (request, generation) = {
            let outbox = shared.outbox.lock();
            let request = pb::WatchWeightsRequest {
                actor_id: outbox.actor_id().to_string(),
                incarnation: outbox.incarnation,
                min_version: 0,
            };
            (request, outbox.generation)
        };
        let watched = async {
            let mut stream = client.watch_weights(request).await?.into_inner();
            retry.answered();
            loop {
                let Some(msg) = stream.message().await? else {
                    return Err(Status::unavailable("the learner ended the weights stream"));
                };
                let snapshot = WeightsSnapshot::try_from(msg).map_err(|e| {
                    Status::unavailable(format!("invalid weights from the learner: {e}"))
                })?;
                retry.succeeded();
                let previous = shared.weights.latest().map_or(0, |w| w.version);
                if snapshot.version < previous {
                    // Versions only grow within one learner: this is a restarted one. Its acks
                    // will say the same, but an actor with nothing to send sees no acks, and
                    // would wait for versions the new learner has not reached.
                    tracing::info!(
                        version = snapshot.version,
                        previous,
                        "weights versions start again: the learner restarted"
                    );
                    shared
                        .stats
                        .learner_version
                        .store(snapshot.version, Ordering::Relaxed);
                }
                let last = snapshot.run_finished;
                shared.weights.publish(Arc::new(snapshot));
                if last {
                    return Ok(());
                }
            }
        };
        let status = tokio::select! {
            result = watched => match result {
                Ok(()) => return,
                Err(status) => status,
            },
            () = until_set(&mut closed) => return,
        };
        let outcome = match Failure::of(&status) {
            Failure::Retry => retry.wait(&status).await,
            // Weights go to registered actors only: a learner that restarted (or an id that
            // registered elsewhere) is answered by registering again, as the ingest task does;
            // an actor with nothing to send would otherwise wait for weights for ever.
            Failure::Reregister => reregister(&shared, &channel, generation).await,
            Failure::Finished => return,
            Failure::Refused => Err(LinkError::Refused(status.message().into())),
        };
        match outcome {
            Ok(()) => {}
            // Actors waiting for weights time out by their own rules; the outbox learns of it.
            Err(LinkError::Closed) => return,
            Err(e) => return shared.fail(e),
        }
    }
}

/// The ingest stream's codec: requests are shared with the outbox (kept until acknowledged, so
/// resending copies nothing), acks are plain prost messages.
#[derive(Debug, Clone, Copy)]
struct IngestCodec;

#[derive(Debug, Clone, Copy)]
struct SharedRequestEncoder;

#[derive(Debug, Clone, Copy)]
struct AckDecoder;

impl Codec for IngestCodec {
    type Encode = Arc<pb::IngestRequest>;
    type Decode = pb::IngestAck;
    type Encoder = SharedRequestEncoder;
    type Decoder = AckDecoder;

    fn encoder(&mut self) -> Self::Encoder {
        SharedRequestEncoder
    }

    fn decoder(&mut self) -> Self::Decoder {
        AckDecoder
    }
}

impl Encoder for SharedRequestEncoder {
    type Item = Arc<pb::IngestRequest>;
    type Error = Status;

    fn encode(&mut self, item: Self::Item, dst: &mut EncodeBuf<'_>) -> Result<(), Status> {
        item.encode(dst)
            .map_err(|e| Status::internal(format!("encoding an ingest request: {e}")))
    }
}

impl Decoder for AckDecoder {
    type Item = pb::IngestAck;
    type Error = Status;

    fn decode(&mut self, src: &mut DecodeBuf<'_>) -> Result<Option<pb::IngestAck>, Status> {
        pb::IngestAck::decode(src)
            .map(Some)
            .map_err(|e| Status::internal(e.to_string()))
    }
}
