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

use std::error::Error as _;
use std::future::Future;
use std::sync::Arc;
use std::time::Duration;

use hac_learner::{IngestError, Learner, RegisterError, RejectReason, RoomError};
use hac_proto::{Evaluation, Registration, ShmOffer, WeightsWatch, WireError, decode_ingest, pb};
use tokio::net::TcpListener;
use tokio::sync::{mpsc, watch};
use tokio_stream::wrappers::ReceiverStream;
use tonic::metadata::MetadataValue;
use tonic::{Code, Request, Response, Status, Streaming};

use super::ops::{Health, LEARNER_SERVICE, STATUS_SERVICE, ServerSecurity, router, serve_router};
use super::status::StatusGrpc;
use super::{REJECT_REASON_KEY, until_set};

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
}

impl LearnerGrpc {
    pub fn new(learner: Arc<Learner>) -> Self {
        Self {
            learner,
            closing: Arc::new(watch::Sender::new(false)),
            shm_offer: None,
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

    /// The tonic service with the message size limits of `options`.
    pub fn into_service(self, options: &ServerOptions) -> pb::learner_server::LearnerServer<Self> {
        pb::learner_server::LearnerServer::new(self)
            .max_decoding_message_size(options.max_message_bytes)
            .max_encoding_message_size(options.max_message_bytes)
    }

    /// A status for a refusal, counted under its reason.
    fn refuse(&self, refusal: Refusal) -> Status {
        self.learner.count_rejection(refusal.reason);
        refusal.into()
    }
}

/// Serves `learner` on `listener` until `shutdown` completes: `hac.v1.Learner`, `hac.v1.Status`,
/// health and reflection, behind `options.security`. Health is `SERVING` from the start (and
/// `NOT_SERVING` while [`Learner::trouble`] says why) until the run is finished (the learner then serves only its final weights) or `shutdown`
/// completes. Then ends every open stream, stops accepting connections and waits up to
/// `options.drain_timeout` for the open ones to close.
pub async fn serve(
    learner: Arc<Learner>,
    listener: TcpListener,
    options: ServerOptions,
    shutdown: impl Future<Output = ()>,
) -> Result<(), tonic::transport::Error> {
    let service = LearnerGrpc::new(learner.clone()).with_shm_offer(options.shm_offer.clone());
    let health = Health::new(LEARNER_SERVICE).await;
    let status = StatusGrpc::new(learner.clone(), service.closing.subscribe());
    let counter = learner.clone();
    let on_refused: Arc<dyn Fn() + Send + Sync> =
        Arc::new(move || counter.count_rejection(RejectReason::Unauthenticated));
    let router = router(
        &options.security,
        Some(on_refused),
        &health,
        &[LEARNER_SERVICE, STATUS_SERVICE],
    )?
    .add_service(status.into_service())
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
    let signal = async move {
        shutdown.await;
        stopping_tx.send_replace(true);
        health.set_serving(false).await;
        service.close();
    };
    let served = serve_router(router, listener, options.drain_timeout, signal).await;
    reporter.abort();
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
        let code = match &e {
            IngestError::Invalid(_)
            | IngestError::UnknownWeightsVersion(_)
            | IngestError::OutOfRange { .. }
            | IngestError::EpisodeTooLong { .. } => Code::InvalidArgument,
            IngestError::UnknownActor(_) => Code::NotFound,
            IngestError::StaleIncarnation { .. }
            | IngestError::StaleWeights { .. }
            | IngestError::Finished => Code::FailedPrecondition,
            IngestError::SequenceGap { .. } => Code::OutOfRange,
            IngestError::WrongRole(_) | IngestError::TrainerEvaluation(_) => Code::PermissionDenied,
        };
        Self {
            reason: e.reason(),
            code,
            message: e.to_string(),
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

impl From<Refusal> for Status {
    fn from(refusal: Refusal) -> Self {
        let mut status = Status::new(refusal.code, refusal.message);
        status.metadata_mut().insert(
            REJECT_REASON_KEY,
            MetadataValue::from_static(refusal.reason.name()),
        );
        status
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
    let (reason, code) = match status.code() {
        Code::OutOfRange | Code::ResourceExhausted => {
            (RejectReason::Oversized, Code::ResourceExhausted)
        }
        Code::Internal => (RejectReason::Malformed, Code::InvalidArgument),
        _ => return None,
    };
    Some(Refusal {
        reason,
        code,
        message: status.message().to_string(),
    })
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
        let mut transport_noted = false;
        let end = loop {
            tokio::select! {
                biased;
                () = until_set(&mut closing) => break Some(shutting_down(&self.learner)),
                permit = acks.reserve(), if pending.is_some() => {
                    // An error: the actor hung up.
                    let Ok(permit) = permit else { return };
                    if let Some(ack) = pending.take() {
                        permit.send(Ok(ack));
                    }
                }
                next = requests.message() => match next {
                    Ok(Some(msg)) => {
                    if !transport_noted {
                        self.learner.set_actor_transport(&msg.actor_id, TRANSPORT);
                        transport_noted = true;
                    }
                    match self.accept(msg).await {
                        Ok(ack) => {
                            // Cumulative: a later ack covers the queued one.
                            let through = pending.map_or(0, |p| p.acked_through);
                            pending = Some(pb::IngestAck {
                                acked_through: ack.acked_through.max(through),
                                ..ack
                            });
                        }
                        Err(status) => break Some(status),
                    }
                    }
                    Ok(None) => break None,
                    Err(status) => match receive_failure(&status) {
                        Some(refusal) => {
                            tracing::warn!(reason = refusal.reason.name(), error = %refusal.message, "ingest stream refused");
                            break Some(self.refuse(refusal));
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
        if let Some(ack) = pending {
            if acks.send(Ok(ack)).await.is_err() {
                return;
            }
        }
        if let Some(status) = end {
            let _ = acks.send(Err(status)).await;
        }
    }

    /// Validates, waits for room and stores one message; the ack for it.
    async fn accept(&self, msg: pb::IngestRequest) -> Result<pb::IngestAck, Status> {
        let learner = &self.learner;
        let options = learner.options();
        let msg = decode_ingest(msg, learner.dims(), options.max_batch_transitions).map_err(|e| {
            let refusal = Refusal::from(e);
            tracing::warn!(reason = refusal.reason.name(), error = %refusal.message, "ingest message refused");
            self.refuse(refusal)
        })?;
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
            }),
            Err(e) => {
                if !matches!(e, IngestError::Finished) {
                    tracing::warn!(actor = %msg.actor_id, reason = e.reason().name(), error = %e, "ingest message refused");
                }
                // The learner counted it.
                Err(Refusal::from(e).into())
            }
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
        let registration =
            Registration::try_from(request.into_inner()).map_err(|e| self.refuse(e.into()))?;
        let wants_shm = registration
            .transports
            .iter()
            .any(|t| t == crate::shm::TRANSPORT);
        let mut admission = self
            .learner
            .register(registration)
            .map_err(|e| self.refuse(e.into()))?;
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
        let watch =
            WeightsWatch::try_from(request.into_inner()).map_err(|e| self.refuse(e.into()))?;
        let (tx, rx) = mpsc::channel(WEIGHTS_QUEUE);
        tokio::spawn(self.clone().run_watch(watch.min_version, tx));
        Ok(Response::new(ReceiverStream::new(rx)))
    }

    async fn report_evaluation(
        &self,
        request: Request<pb::EvaluationReport>,
    ) -> Result<Response<pb::EvaluationAck>, Status> {
        let evaluation =
            Evaluation::try_from(request.into_inner()).map_err(|e| self.refuse(e.into()))?;
        // The learner counts its own refusals.
        self.learner
            .report_evaluation(&evaluation)
            .map_err(|e| Status::from(Refusal::from(e)))?;
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
        if actor_id.is_empty() {
            return Err(self.refuse(WireError::missing("turn_request.actor_id").into()));
        }
        if incarnation == 0 {
            return Err(self.refuse(WireError::missing("turn_request.incarnation").into()));
        }
        let learner = self.learner.clone();
        let wait = Duration::from_millis(u64::from(wait_ms));
        // The learner waits on a condition variable; a blocking thread per waiting actor, for
        // at most the learner's cap on one wait.
        let turn =
            tokio::task::spawn_blocking(move || learner.await_turn(&actor_id, incarnation, wait))
                .await
                .map_err(|e| Status::internal(format!("turn wait failed: {e}")))?
                // The learner counts its own refusals.
                .map_err(|e| Status::from(Refusal::from(e)))?;
        Ok(Response::new(pb::TurnReply {
            granted: turn.granted,
            episodes: turn.episodes,
        }))
    }
}
