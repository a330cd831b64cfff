//! [`LearnerGrpc`]: the `hac.v1.Learner` service over a shared [`Learner`], and [`serve`], which
//! serves it with status, health and reflection, behind the token check and TLS if configured.
//!
//! Each ingest stream runs in a task of its own: it reads one message, validates it, waits for
//! room in the learner (the backpressure: the ack is withheld meanwhile, and since the task reads
//! nothing more, HTTP/2 flow control soon holds the actor's sender too), stores it and queues a
//! cumulative ack. Acks wait in a short queue; while the actor does not read them, later ones
//! replace the queued one instead of piling up. With a per-actor message rate limit, the task
//! also sleeps for what [`Learner::throttle`] says before taking a message: the same
//! backpressure, so nothing is refused.
//!
//! Every refusal is counted under its reason and reported to a [`RefusalLog`] (the first per
//! reason and actor in an interval is logged, the rest summarized). A request tonic cannot decode
//! never reaches a handler: [`RefuseUndecodable`] turns tonic's `INTERNAL` answer into the same
//! `INVALID_ARGUMENT`/`malformed` refusal a bad ingest message gets.

use std::error::Error as _;
use std::future::Future;
use std::sync::Arc;
use std::time::Duration;

use hac_learner::{IngestError, Learner, RegisterError, RoomError};
use hac_proto::{
    Clipped, ECHO_BYTES, Evaluation, MAX_ACTOR_ID_BYTES, PreviousIncarnation, Registration,
    ShmOffer, WeightsWatch, WireError, check_actor_id, decode_ingest, pb,
};
use hac_proto::{Published, RejectReason};
use hac_transport::grpc::{
    Health, LEARNER_SERVICE, OnMalformed, RefuseUndecodable, STATUS_SERVICE, ServerSecurity,
    StatusGrpc, refusal_status, router, serve_router, until_set,
};
use hac_transport::refusal_log::{RefusalLog, SUMMARY_INTERVAL};
use tokio::net::TcpListener;
use tokio::sync::{mpsc, watch};
use tokio_stream::wrappers::ReceiverStream;
use tonic::{Code, Request, Response, Status, Streaming};

use super::status::LearnerSource;

/// Transport settings of the learner's gRPC server.
#[derive(Debug, Clone)]
pub struct ServerOptions {
    /// Largest message accepted, in bytes (after decompression); larger ones are refused with
    /// `RESOURCE_EXHAUSTED` and counted as `oversized`. Also the largest weights message sent.
    pub max_message_bytes: usize,
    /// How long [`serve`] waits, once shut down, for connections to close before returning.
    pub drain_timeout: Duration,
    /// The bearer token and TLS (default: neither).
    pub security: ServerSecurity,
    /// Shared memory served beside gRPC ([`ShmServer::offer`](crate::shm::ShmServer::offer)):
    /// announced at registration to actors that list the `shm` transport.
    pub shm_offer: Option<ShmOffer>,
}

impl Default for ServerOptions {
    fn default() -> Self {
        Self {
            max_message_bytes: 64 << 20,
            drain_timeout: Duration::from_secs(5),
            security: ServerSecurity::default(),
            shm_offer: None,
        }
    }
}

/// This transport's name in status.
const TRANSPORT: &str = "grpc";
/// Acks queued per ingest stream before later ones replace the last queued one.
const ACK_QUEUE: usize = 4;
/// Weights messages queued per watcher (each is a whole model).
const WEIGHTS_QUEUE: usize = 2;
/// One blocking wait for room; the stream checks for shutdown between waits.
const ROOM_WAIT: Duration = Duration::from_millis(250);

/// The `hac.v1.Learner` service over a shared [`Learner`]. Cheap to clone; every clone serves the
/// same learner and is ended by the same [`close`](Self::close).
#[derive(Debug, Clone)]
pub struct LearnerGrpc {
    learner: Arc<Learner>,
    closing: Arc<watch::Sender<bool>>,
    shm_offer: Option<Arc<ShmOffer>>,
    refusals: Arc<RefusalLog>,
}

impl LearnerGrpc {
    /// Serves `learner`, with no shared memory offered.
    pub fn new(learner: Arc<Learner>) -> Self {
        Self {
            learner,
            closing: Arc::new(watch::Sender::new(false)),
            shm_offer: None,
            refusals: Arc::new(RefusalLog::new(SUMMARY_INTERVAL)),
        }
    }

    /// Announces `offer` at registration to every actor that lists the `shm` transport.
    pub fn with_shm_offer(mut self, offer: Option<ShmOffer>) -> Self {
        self.shm_offer = offer.map(Arc::new);
        self
    }

    /// Ends every open stream (ingest streams with `UNAVAILABLE`, or `finished` if the run is
    /// over; weights streams after the snapshot they are sending) and every stream opened later,
    /// so that a graceful server shutdown does not wait for actors to hang up.
    pub fn close(&self) {
        self.closing.send_replace(true);
    }

    /// The tonic service with the message size limits of `options`, refusing undecodable
    /// requests as `malformed` (counted).
    pub fn into_service(
        self,
        options: &ServerOptions,
    ) -> RefuseUndecodable<pb::learner_server::LearnerServer<Self>> {
        let on_malformed = self.on_malformed();
        let server = pb::learner_server::LearnerServer::new(self)
            .max_decoding_message_size(options.max_message_bytes)
            .max_encoding_message_size(options.max_message_bytes);
        RefuseUndecodable::new(server, Some(on_malformed))
    }

    /// What a request that does not decode costs: a count and a (rate-limited) line.
    fn on_malformed(&self) -> OnMalformed {
        let (learner, refusals) = (self.learner.clone(), self.refusals.clone());
        Arc::new(move |message: &str| {
            learner.count_rejection(RejectReason::Malformed);
            refusals.refused("request", RejectReason::Malformed, "", &message);
        })
    }

    /// A status for a refusal of `actor`'s `what` found here, counted under its reason and logged.
    fn refuse(&self, what: &'static str, actor: &str, refusal: Refusal) -> Status {
        self.learner.count_rejection(refusal.reason);
        self.refused(what, actor, refusal)
    }

    /// The actor id of a request, checked before the conversion that consumes the request
    /// (which checks it again), so that a refusal of the rest can name the actor: a copy of at
    /// most `MAX_ACTOR_ID_BYTES`, for rare requests only (not ingest messages).
    fn checked_id(
        &self,
        what: &'static str,
        field: &'static str,
        id: &str,
    ) -> Result<String, Status> {
        check_actor_id(field, id).map_err(|e| self.refuse(what, id, e.into()))?;
        Ok(id.to_string())
    }

    /// A status for a refusal the learner found (and counted), logged.
    fn refused(&self, what: &'static str, actor: &str, refusal: impl Into<Refusal>) -> Status {
        let refusal = refusal.into();
        self.refusals
            .refused(what, refusal.reason, actor, &refusal.message);
        refusal.into()
    }
}

/// Serves `learner` on `listener` until `shutdown` completes: `hac.v1.Learner`, `hac.v1.Status`,
/// health and reflection, behind `options.security`. Health is `SERVING` from the start (and
/// `NOT_SERVING` while [`Learner::trouble`] says why) until the run is finished (the learner
/// then serves only its final weights) or `shutdown` completes. Then ends every open stream, stops accepting connections and waits up to
/// `options.drain_timeout` for the open ones to close.
pub async fn serve(
    learner: Arc<Learner>,
    listener: TcpListener,
    options: ServerOptions,
    shutdown: impl Future<Output = ()>,
) -> Result<(), tonic::transport::Error> {
    let service = LearnerGrpc::new(learner.clone()).with_shm_offer(options.shm_offer.clone());
    let health = Health::new(LEARNER_SERVICE).await;
    let on_malformed = service.on_malformed();
    let status = StatusGrpc::new(
        Arc::new(LearnerSource(learner.clone())),
        service.closing.subscribe(),
    );
    let counter = learner.clone();
    let on_refused: Arc<dyn Fn() + Send + Sync> =
        Arc::new(move || counter.count_rejection(RejectReason::Unauthenticated));
    let router = router(
        &options.security,
        Some(on_refused),
        &health,
        &[LEARNER_SERVICE, STATUS_SERVICE],
    )?
    .add_service(RefuseUndecodable::new(
        status.into_service(),
        Some(on_malformed),
    ))
    .add_service(service.clone().into_service(&options));

    // Serving before the first request can be read: a client that saw the address never
    // meets NOT_SERVING from a task not yet scheduled.
    health.set_serving(true).await;
    let (stopping_tx, mut stopping) = watch::channel(false);
    let reporter = {
        let health = health.clone();
        let mut weights = learner.weights().subscribe();
        let mut trouble = learner.trouble().subscribe();
        async move {
            loop {
                let healthy = tokio::select! {
                    // An error: the weights cell is gone, so is the run.
                    () = async {
                        let _ = weights.wait_for(|w| w.as_ref().is_some_and(|w| w.run_finished)).await;
                    } => break,
                    () = until_set(&mut stopping) => break,
                    // A failing level (its updates diverge and are undone): not serving until
                    // it recovers. Its reason is in status.
                    changed = trouble.changed() => {
                        if changed.is_err() {
                            break;
                        }
                        trouble.borrow_and_update().as_deref().is_none_or(Option::is_none)
                    }
                };
                health.set_serving(healthy).await;
            }
            health.set_serving(false).await;
        }
    };
    let reporter = tokio::spawn(reporter);
    // The summary of a burst of refusals is logged when its interval ends, even if the burst
    // ended with it.
    let summaries = {
        let refusals = service.refusals.clone();
        tokio::spawn(async move {
            let mut every = tokio::time::interval(SUMMARY_INTERVAL);
            loop {
                every.tick().await;
                refusals.flush();
            }
        })
    };
    let signal = async move {
        shutdown.await;
        stopping_tx.send_replace(true);
        health.set_serving(false).await;
        service.close();
    };
    let served = serve_router(router, listener, options.drain_timeout, signal).await;
    reporter.abort();
    summaries.abort();
    served
}

/// A refusal before it becomes a [`Status`]: the only place that picks status codes.
#[derive(Debug)]
struct Refusal {
    reason: RejectReason,
    code: Code,
    message: String,
}

impl From<IngestError> for Refusal {
    fn from(e: IngestError) -> Self {
        let (code, actor) = match &e {
            IngestError::Invalid(_) | IngestError::UnknownWeightsVersion(_) => {
                (Code::InvalidArgument, None)
            }
            IngestError::OutOfRange { actor, .. } | IngestError::EpisodeTooLong { actor, .. } => {
                (Code::InvalidArgument, Some(actor))
            }
            IngestError::UnknownActor(actor) => (Code::NotFound, Some(actor)),
            IngestError::StaleIncarnation { actor, .. } => (Code::FailedPrecondition, Some(actor)),
            IngestError::StaleWeights { .. } | IngestError::Finished => {
                (Code::FailedPrecondition, None)
            }
            IngestError::SequenceGap { actor, .. } => (Code::OutOfRange, Some(actor)),
            IngestError::WrongRole(actor) | IngestError::TrainerEvaluation(actor) => {
                (Code::PermissionDenied, Some(actor))
            }
        };
        // The learner's messages quote the actor id whole; the wire limits it, and the echo is
        // clipped further, as everywhere an id is echoed.
        let mut message = e.to_string();
        if let Some(actor) = actor.filter(|a| a.len() > ECHO_BYTES) {
            message = message.replacen(actor.as_str(), &Clipped(actor).to_string(), 1);
        }
        Self {
            reason: e.reason(),
            code,
            message,
        }
    }
}

impl From<WireError> for Refusal {
    fn from(e: WireError) -> Self {
        IngestError::Invalid(e).into()
    }
}

impl From<RegisterError> for Refusal {
    fn from(e: RegisterError) -> Self {
        match e {
            RegisterError::EmptyActorId => WireError::missing("register_request.actor_id").into(),
            RegisterError::Finished => IngestError::Finished.into(),
        }
    }
}

/// The refusal of bytes that do not decode as the expected message (as
/// [`RefuseUndecodable`] answers on every other RPC).
fn malformed(message: String) -> Refusal {
    Refusal {
        reason: RejectReason::Malformed,
        code: Code::InvalidArgument,
        message,
    }
}

impl From<Refusal> for Status {
    fn from(refusal: Refusal) -> Self {
        refusal_status(refusal.reason, refusal.code, refusal.message)
    }
}

/// What a failed receive on an ingest stream was. tonic's decoder reports undecodable bytes as
/// `INTERNAL` and a message above the limit as `OUT_OF_RANGE` (or `RESOURCE_EXHAUSTED` when it
/// only shows after decompression), always without a source error; a failure of the connection
/// underneath carries the hyper or h2 error as its source. The latter is the actor going away,
/// not a refusal.
fn receive_failure(status: &Status) -> Option<Refusal> {
    if status.source().is_some() {
        return None;
    }
    match status.code() {
        Code::OutOfRange | Code::ResourceExhausted => Some(Refusal {
            reason: RejectReason::Oversized,
            code: Code::ResourceExhausted,
            message: status.message().to_string(),
        }),
        Code::Internal => Some(malformed(status.message().to_string())),
        _ => None,
    }
}

/// How the server ends an ingest stream when it shuts down: `finished` once the run is over, else
/// `UNAVAILABLE` without a reason (the actor tries again, maybe with a restarted learner).
fn shutting_down(learner: &Learner) -> Status {
    if learner.is_finished() {
        Refusal::from(IngestError::Finished).into()
    } else {
        Status::unavailable("the learner is shutting down")
    }
}

type AckSender = mpsc::Sender<Result<pb::IngestAck, Status>>;

impl LearnerGrpc {
    /// One ingest stream, until the actor hangs up, a message is refused or the server closes.
    async fn run_ingest(self, mut requests: Streaming<pb::IngestRequest>, acks: AckSender) {
        let mut closing = self.closing.subscribe();
        let mut pending: Option<pb::IngestAck> = None;
        // The highest ack of the stream: acks never go back, even for a resend of a message
        // stored long ago, which the learner acknowledges with its own sequence.
        let mut acked_through = 0;
        // The actor of the stream's first message (one copy per stream), to name in the
        // refusal of bytes that do not decode later on.
        let mut stream_actor: Option<String> = None;
        // The incarnation of the stream's latest message, and the durable watermark sent.
        let mut incarnation = 0;
        let mut durable_through = 0;
        // Commits of the learner's write-ahead log: durability advances without new messages.
        let mut commits = self.learner.durable_commits().map(Published::subscribe);
        let end = loop {
            tokio::select! {
                biased;
                () = until_set(&mut closing) => break Some(shutting_down(&self.learner)),
                changed = async { commits.as_mut().expect("only with a log").changed().await },
                    if commits.is_some() && acked_through > durable_through =>
                {
                    if changed.is_err() {
                        commits = None;
                        continue;
                    }
                    let actor = stream_actor.as_deref().unwrap_or_default();
                    let durable = self
                        .learner
                        .durable_through(actor, incarnation)
                        .min(acked_through);
                    if durable > durable_through {
                        durable_through = durable;
                        let ack = pending.get_or_insert_with(|| pb::IngestAck {
                            acked_through,
                            weights_version: self.learner.weights().latest().map_or(0, |w| w.version),
                            durable_through,
                        });
                        ack.durable_through = durable_through;
                    }
                }
                permit = acks.reserve(), if pending.is_some() => {
                    // An error: the actor hung up.
                    let Ok(permit) = permit else { return };
                    if let Some(ack) = pending.take() {
                        permit.send(Ok(ack));
                    }
                }
                next = requests.message() => match next {
                    Ok(Some(msg)) => {
                    if stream_actor.is_none() {
                        self.learner.set_actor_transport(&msg.actor_id, TRANSPORT);
                        // A longer id is refused with this very message, ending the stream.
                        let id = &msg.actor_id;
                        stream_actor = Some(if id.len() <= MAX_ACTOR_ID_BYTES { id.clone() } else { String::new() });
                    }
                    incarnation = msg.incarnation;
                    match self.accept(msg).await {
                        Ok(ack) => {
                            // Cumulative: a later ack covers the queued one.
                            acked_through = acked_through.max(ack.acked_through);
                            durable_through = durable_through.max(ack.durable_through.min(acked_through));
                            pending = Some(pb::IngestAck {
                                acked_through,
                                durable_through,
                                ..ack
                            });
                        }
                        Err(status) => break Some(status),
                    }
                    }
                    Ok(None) => break None,
                    Err(status) => match receive_failure(&status) {
                        Some(refusal) => {
                            let actor = stream_actor.as_deref().unwrap_or_default();
                            break Some(self.refuse("ingest stream", actor, refusal));
                        }
                        None => {
                            tracing::debug!(error = %status, "ingest stream ended by the actor");
                            return;
                        }
                    },
                },
            }
        };
        // What was stored is acknowledged before the stream ends, so the actor does not resend
        // it (resends are harmless, but not free).
        if let Some(ack) = pending
            && acks.send(Ok(ack)).await.is_err()
        {
            return;
        }
        if let Some(status) = end {
            let _ = acks.send(Err(status)).await;
        }
    }

    /// Validates, waits for room and stores one message; the ack for it.
    async fn accept(&self, mut msg: pb::IngestRequest) -> Result<pb::IngestAck, Status> {
        let learner = &self.learner;
        let options = learner.options();
        let msg = decode_ingest(&mut msg, learner.dims(), options.max_batch_transitions)
            .map_err(|e| self.refuse("ingest message", &msg.actor_id, e.into()))?;
        let throttled = learner.throttle(&msg.actor_id);
        if !throttled.is_zero() {
            let mut closing = self.closing.subscribe();
            tokio::select! {
                () = tokio::time::sleep(throttled) => {}
                () = until_set(&mut closing) => return Err(shutting_down(learner)),
            }
        }
        if !learner.has_room() {
            self.wait_for_room().await?;
        }
        match learner.ingest(&msg) {
            Ok(_) => Ok(pb::IngestAck {
                acked_through: msg.sequence,
                weights_version: learner.weights().latest().map_or(0, |w| w.version),
                // With a log, durability is read when it commits (and here, for a resend of
                // what a resumed learner recovered); without one, stored is durable.
                durable_through: match learner.durable_commits() {
                    Some(_) => learner.durable_through(&msg.actor_id, msg.incarnation),
                    None => msg.sequence,
                },
            }),
            // The learner counted it.
            Err(e) => Err(self.refused("ingest message", &msg.actor_id, e)),
        }
    }

    /// Waits, on the blocking pool, until the learner has room or the run is over (then the
    /// message is handed to ingest, which refuses it or acknowledges a resend).
    async fn wait_for_room(&self) -> Result<(), Status> {
        let mut closing = self.closing.subscribe();
        loop {
            let learner = self.learner.clone();
            let wait = tokio::task::spawn_blocking(move || learner.wait_for_room(ROOM_WAIT));
            let result = tokio::select! {
                result = wait => result,
                () = until_set(&mut closing) => return Err(shutting_down(&self.learner)),
            };
            match result {
                Ok(Ok(())) | Ok(Err(RoomError::Finished)) => return Ok(()),
                Ok(Err(RoomError::TimedOut)) => {}
                Err(e) => return Err(Status::internal(format!("waiting for room: {e}"))),
            }
        }
    }

    /// One weights stream: the first snapshot at or above `min_version`, then every newer one,
    /// until a final snapshot is sent, the watcher hangs up or the server closes.
    async fn run_watch(self, min_version: u64, out: mpsc::Sender<Result<pb::Weights, Status>>) {
        let mut published = self.learner.weights().subscribe();
        let mut closing = self.closing.subscribe();
        let mut sent = min_version.checked_sub(1);
        loop {
            let latest = published.borrow_and_update().clone();
            if let Some(snapshot) = latest.filter(|s| sent.is_none_or(|v| s.version > v)) {
                sent = Some(snapshot.version);
                let last = snapshot.run_finished;
                if out
                    .send(Ok(pb::Weights::from(snapshot.as_ref().clone())))
                    .await
                    .is_err()
                    || last
                {
                    return;
                }
            }
            tokio::select! {
                // A snapshot published before the server closed (the final one) is still sent.
                biased;
                changed = published.changed() => if changed.is_err() { return },
                () = until_set(&mut closing) => return,
                () = out.closed() => return,
            }
        }
    }
}

#[tonic::async_trait]
impl pb::learner_server::Learner for LearnerGrpc {
    async fn register(
        &self,
        request: Request<pb::RegisterRequest>,
    ) -> Result<Response<pb::RegisterResponse>, Status> {
        let request = request.into_inner();
        let actor = self.checked_id(
            "registration",
            "register_request.actor_id",
            &request.actor_id,
        )?;
        let previous = PreviousIncarnation::of_request(&request);
        let registration = Registration::try_from(request)
            .map_err(|e| self.refuse("registration", &actor, e.into()))?;
        let wants_shm = registration
            .transports
            .iter()
            .any(|t| t == hac_transport::shm::TRANSPORT);
        let mut admission = self
            .learner
            .register_again(registration, previous)
            .map_err(|e| self.refuse("registration", &actor, e.into()))?;
        if wants_shm {
            admission.shm = self.shm_offer.as_deref().cloned();
        }
        Ok(Response::new(admission.into()))
    }

    type IngestStream = ReceiverStream<Result<pb::IngestAck, Status>>;

    async fn ingest(
        &self,
        request: Request<Streaming<pb::IngestRequest>>,
    ) -> Result<Response<Self::IngestStream>, Status> {
        let (tx, rx) = mpsc::channel(ACK_QUEUE);
        tokio::spawn(self.clone().run_ingest(request.into_inner(), tx));
        Ok(Response::new(ReceiverStream::new(rx)))
    }

    type WatchWeightsStream = ReceiverStream<Result<pb::Weights, Status>>;

    async fn watch_weights(
        &self,
        request: Request<pb::WatchWeightsRequest>,
    ) -> Result<Response<Self::WatchWeightsStream>, Status> {
        let request = request.into_inner();
        let actor = self.checked_id(
            "weights watch",
            "watch_weights_request.actor_id",
            &request.actor_id,
        )?;
        let watch = WeightsWatch::try_from(request)
            .map_err(|e| self.refuse("weights watch", &actor, e.into()))?;
        // Weights go to registered actors only (the learner counts the refusal): an unknown or
        // superseded incarnation registers (again) first.
        self.learner
            .check_incarnation(&watch.actor_id, watch.incarnation)
            .map_err(|e| self.refused("weights watch", &watch.actor_id, e))?;
        let (tx, rx) = mpsc::channel(WEIGHTS_QUEUE);
        tokio::spawn(self.clone().run_watch(watch.min_version, tx));
        Ok(Response::new(ReceiverStream::new(rx)))
    }

    async fn report_evaluation(
        &self,
        request: Request<pb::EvaluationReport>,
    ) -> Result<Response<pb::EvaluationAck>, Status> {
        let request = request.into_inner();
        let actor = self.checked_id(
            "evaluation report",
            "evaluation_report.actor_id",
            &request.actor_id,
        )?;
        let evaluation = Evaluation::try_from(request)
            .map_err(|e| self.refuse("evaluation report", &actor, e.into()))?;
        // The learner counts its own refusals.
        self.learner
            .report_evaluation(&evaluation)
            .map_err(|e| self.refused("evaluation report", &evaluation.actor_id, e))?;
        self.learner
            .set_actor_transport(&evaluation.actor_id, TRANSPORT);
        Ok(Response::new(pb::EvaluationAck {}))
    }

    async fn await_turn(
        &self,
        request: Request<pb::TurnRequest>,
    ) -> Result<Response<pb::TurnReply>, Status> {
        let pb::TurnRequest {
            actor_id,
            incarnation,
            wait_ms,
        } = request.into_inner();
        if let Err(e) = check_actor_id("turn_request.actor_id", &actor_id) {
            return Err(self.refuse("turn request", &actor_id, e.into()));
        }
        if incarnation == 0 {
            let e = WireError::missing("turn_request.incarnation");
            return Err(self.refuse("turn request", &actor_id, e.into()));
        }
        let learner = self.learner.clone();
        let wait = Duration::from_millis(u64::from(wait_ms));
        // The learner waits on a condition variable; a blocking thread per waiting actor, for
        // at most the learner's cap on one wait. The id comes back for the refusal.
        let (actor_id, turn) = tokio::task::spawn_blocking(move || {
            let turn = learner.await_turn(&actor_id, incarnation, wait);
            (actor_id, turn)
        })
        .await
        // Not INTERNAL: that code is tonic's for a request that does not decode (see
        // `RefuseUndecodable`).
        .map_err(|e| Status::unknown(format!("turn wait failed: {e}")))?;
        // The learner counts its own refusals.
        let turn = turn.map_err(|e| self.refused("turn request", &actor_id, e))?;
        Ok(Response::new(pb::TurnReply {
            granted: turn.granted,
            episodes: turn.episodes,
            episode: turn.episode,
        }))
    }
}
