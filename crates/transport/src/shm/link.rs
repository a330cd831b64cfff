//! [`ShmLink`]: an actor's link to a learner on its host, over shared memory.
//!
//! Messages are packed straight into memory loaned from the actor's `ingest` publisher and stay
//! held (the gRPC link's [`Held`]) until an ack says they are durable, not just stored; at most
//! a window of them is unacknowledged, which the learner's subscriber buffer always holds, and at
//! most `max_held` are held. Waiting (a full window, a flush) sleeps on the actor's ack event; a
//! wait without any ack for [`STALL_CHECK`] looks at the learner: if its subscriber is not the
//! one the messages went to (a restarted learner), everything not durable is sent again from the
//! oldest on, a window at a time. A learner resumed from its write-ahead log knows the
//! incarnation and acknowledges what it has as duplicates; one that does not (`unknown_actor`),
//! or lacks a message (`sequence_gap`), makes the link register again naming its incarnation and
//! the oldest message held, as the gRPC link does: kept, the link resends under the same
//! numbering; not kept, it renumbers what it holds from 1 under the new incarnation.

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use hac_proto::{
    Admission, IngestItem, IngestRef, PACKED_ALIGNMENT, PreviousIncarnation, Published,
    Registration, RejectReason, WeightsSnapshot, max_packed_ingest_len, pack_ingest,
    packed_ingest_len,
};
use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::{
    Alignment, AllocationStrategy, BackpressureStrategy, CallbackProgression, PortFactory as _,
};
use iceoryx2::service::port_factory::{event, publish_subscribe};

use super::{
    Ack, AckWire, Ipc, Namespace, Node, ShmError, WeightsReceiver, check_free_space,
    cleanup_dead_nodes, host_identity, open_ack_events, open_acks, segment_bytes,
};
use crate::grpc::{ConnectError, GrpcLink, GrpcLinkOptions};
use crate::held::Held;
use crate::{
    ActorLink, EvaluationOf, GrantedTurn, IngestSink, LinkError, LinkStats, WeightsSource,
};

/// Whether shared memory is required or only preferred.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ShmMode {
    /// `--transport shm`: fail unless the learner serves shared memory to this host.
    Require,
    /// `--transport auto`: shared memory if the learner offers it to this host and it works,
    /// gRPC otherwise.
    Prefer,
}

/// What `send` does when the window of unacknowledged messages is full.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Overflow {
    /// Wait for acks: the learner's backpressure reaches the actor.
    Block,
    /// Drop the new transition batch and count it ([`ShmLink::dropped`]). Episode summaries
    /// always wait: the learner's schedule counts them.
    Drop,
}

/// How a [`ShmLink`] uses shared memory.
#[derive(Debug, Clone, PartialEq)]
pub struct ShmLinkOptions {
    pub mode: ShmMode,
    /// Most messages unacknowledged (also capped by the learner's window).
    pub window: usize,
    /// The largest batch the actor sends, in transitions (capped by the learner's limit): sizes
    /// the actor's shared-memory slots.
    pub max_batch_transitions: usize,
    pub overflow: Overflow,
    /// The shared-memory file system, checked for room.
    pub shm_dir: PathBuf,
    /// Give up once no learner has listened for this long.
    pub give_up_after: Duration,
}

impl Default for ShmLinkOptions {
    fn default() -> Self {
        Self {
            mode: ShmMode::Prefer,
            window: 256,
            max_batch_transitions: 1024,
            overflow: Overflow::Block,
            shm_dir: PathBuf::from(super::SHM_DIR),
            give_up_after: Duration::from_secs(300),
        }
    }
}

/// A wait without any ack for this long looks at the learner.
pub const STALL_CHECK: Duration = Duration::from_secs(1);
/// The longest single sleep on the ack event (then the link checks its clocks again).
const WAIT_SLICE: Duration = Duration::from_millis(100);
/// Re-registrations in a row without an ack before the link gives up (as the gRPC link).
const MAX_REREGISTRATIONS: u32 = 5;
/// Drop warnings at most this often.
const WARN_EVERY: Duration = Duration::from_secs(5);

/// The actor's ports in one namespace.
struct Attached {
    namespace: Namespace,
    node: Node,
    ingest: publish_subscribe::PortFactory<Ipc, [u8], ()>,
    publisher: Publisher<Ipc, [u8], ()>,
    /// The largest packed message, in bytes.
    slot: usize,
    _ingest_events: event::PortFactory<Ipc>,
    ingest_notifier: Notifier<Ipc>,
    acks: AckPorts,
    /// min(the link's window, the learner's buffer).
    window: usize,
    /// The learner's subscriber the messages went to, as last seen.
    learner: Vec<u128>,
    _weights: WeightsReceiver,
}

/// One incarnation's ack subscription.
struct AckPorts {
    incarnation: u64,
    _service: publish_subscribe::PortFactory<Ipc, AckWire, ()>,
    subscriber: Subscriber<Ipc, AckWire, ()>,
    _events: event::PortFactory<Ipc>,
    listener: Listener<Ipc>,
}

impl AckPorts {
    fn open(
        node: &Node,
        namespace: &Namespace,
        actor_id: &str,
        incarnation: u64,
    ) -> Result<Self, ShmError> {
        let name = namespace.acks(actor_id, incarnation)?;
        let service = open_acks(node, &name)?;
        let subscriber = service
            .subscriber_builder()
            .create()
            .map_err(|e| ShmError::iceoryx(format!("subscribing to {name}"), e))?;
        let events = open_ack_events(node, &name)?;
        let listener = events
            .listener_builder()
            .create()
            .map_err(|e| ShmError::iceoryx(format!("listening to {name}"), e))?;
        Ok(Self {
            incarnation,
            _service: service,
            subscriber,
            _events: events,
            listener,
        })
    }
}

impl Attached {
    /// Opens the learner's services in `namespace` for `actor_id`'s `incarnation`, after checking
    /// that `/dev/shm` has room for the actor's slots.
    fn open(
        namespace: Namespace,
        admission: &Admission,
        options: &ShmLinkOptions,
        actor_id: &str,
        weights: (Arc<Published<WeightsSnapshot>>, Arc<AtomicU64>),
    ) -> Result<Self, ShmError> {
        let node = super::node(&format!("hac-actor-{actor_id}"))?;
        cleanup_dead_nodes(&node);
        let name = namespace.ingest()?;
        let ingest = node
            .service_builder(&name)
            .publish_subscribe::<[u8]>()
            .payload_alignment(Alignment::new(PACKED_ALIGNMENT).expect("a power of two"))
            .open()
            .map_err(|e| ShmError::iceoryx(format!("opening {name}"), e))?;
        let config = ingest.static_config();
        let window = options
            .window
            .min(config.subscriber_max_buffer_size())
            .max(1);
        let floats = admission
            .levels
            .iter()
            .enumerate()
            .map(|(level, d)| 2 * d.state + d.action + d.goal + 2 + admission.extra_width(level))
            .max()
            .unwrap_or(0);
        let max_count = options
            .max_batch_transitions
            .min(admission.max_batch_transitions)
            .max(1);
        let slot = max_packed_ingest_len(actor_id.len(), max_count, floats);
        // The learner's buffer and borrowed samples, and one loan.
        let chunks = config.max_subscribers()
            * (config.subscriber_max_buffer_size() + config.subscriber_max_borrowed_samples())
            + 1;
        check_free_space(
            &options.shm_dir,
            segment_bytes(chunks, slot),
            "this actor's shared memory",
            "lower --batch-transitions, or use --transport grpc",
        )?;
        let publisher = ingest_publisher(&ingest, slot)?;
        let ingest_events = node
            .service_builder(&name)
            .event()
            .open()
            .map_err(|e| ShmError::iceoryx(format!("opening the event {name}"), e))?;
        let ingest_notifier = ingest_events
            .notifier_builder()
            .create()
            .map_err(|e| ShmError::iceoryx(format!("notifying {name}"), e))?;
        let acks = AckPorts::open(&node, &namespace, actor_id, admission.incarnation)?;
        let (cell, version) = weights;
        let weights = WeightsReceiver::start(&namespace, cell, version)?;
        let learner = subscriber_ids(&ingest);
        Ok(Self {
            namespace,
            node,
            ingest,
            publisher,
            slot,
            _ingest_events: ingest_events,
            ingest_notifier,
            acks,
            window,
            learner,
            _weights: weights,
        })
    }
}

/// A publisher of packed messages of up to `slot` bytes to `ingest`.
fn ingest_publisher(
    ingest: &publish_subscribe::PortFactory<Ipc, [u8], ()>,
    slot: usize,
) -> Result<Publisher<Ipc, [u8], ()>, ShmError> {
    ingest
        .publisher_builder()
        .initial_max_slice_len(slot)
        .allocation_strategy(AllocationStrategy::PowerOfTwo)
        .max_loaned_samples(1)
        // Never block on a full buffer: only a dead learner's buffer can fill (the window fits
        // the live one), and what it holds is resent anyway.
        .backpressure_strategy(BackpressureStrategy::DiscardData)
        .create()
        .map_err(|e| ShmError::iceoryx(format!("publishing to {}", ingest.name()), e))
}

impl Attached {
    /// New ports for a new learner: the ingest publisher and the ack subscription are made
    /// again, so that nothing of the connections to the learner before carries over (a killed
    /// learner's ports may be being removed by another process at that very moment, and a
    /// connection to them left half made would never deliver). Keeps the old ones if new ones
    /// cannot be had.
    fn renew(&mut self, actor_id: &str) {
        match ingest_publisher(&self.ingest, self.slot) {
            Ok(publisher) => self.publisher = publisher,
            Err(e) => tracing::warn!(error = %e, "renewing the ingest publisher"),
        }
        match AckPorts::open(&self.node, &self.namespace, actor_id, self.acks.incarnation) {
            Ok(acks) => self.acks = acks,
            Err(e) => tracing::warn!(error = %e, "renewing the ack subscription"),
        }
    }
}

/// The ids of the subscribers (the learner) of an ingest service.
fn subscriber_ids(service: &publish_subscribe::PortFactory<Ipc, [u8], ()>) -> Vec<u128> {
    let mut ids = Vec::new();
    service.dynamic_config().list_subscribers(|details| {
        ids.push(details.subscriber_id.value());
        CallbackProgression::Continue
    });
    ids.sort_unstable();
    ids
}

/// An [`ActorLink`] to a learner on this host: ingest and weights over shared memory,
/// registration and evaluation reports over gRPC; see the module docs. Falls back to gRPC for
/// everything ([`ShmMode::Prefer`]) when shared memory is not to be had.
pub struct ShmLink {
    grpc: GrpcLink,
    options: ShmLinkOptions,
    /// Most messages held until durable (the gRPC link's `max_held`).
    max_held: usize,
    /// `None`: everything goes over `grpc`.
    attached: Option<Attached>,
    registration: Option<Registration>,
    digest: String,
    incarnation: u64,
    /// Every message the learner has not said is durable, numbered under `incarnation`.
    held: Held<IngestItem>,
    /// The newest message published to the learner listening now: those after it wait for room
    /// in the window (after a rewind, they are sent again).
    sent_through: u64,
    /// The gRPC link's counters, which this link keeps while it sends over shared memory.
    stats: Arc<LinkStats>,
    weights: Arc<Published<WeightsSnapshot>>,
    learner_version: Arc<AtomicU64>,
    /// Since the last ack, or the last look at the learner.
    quiet_since: Instant,
    /// Since no learner has listened, if none does.
    alone_since: Option<Instant>,
    reregistrations: u32,
    dropped_batches: u64,
    dropped_transitions: u64,
    last_drop_warning: Option<Instant>,
}

impl std::fmt::Debug for ShmLink {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ShmLink")
            .field(
                "namespace",
                &self.attached.as_ref().map(|a| a.namespace.as_str()),
            )
            .field("incarnation", &self.incarnation)
            .field("held", &self.held.len())
            .field("unacked", &self.held.unacked())
            .field("acked_through", &self.held.acked_through())
            .field("durable_through", &self.held.durable_through())
            .finish_non_exhaustive()
    }
}

impl ShmLink {
    /// A link to the learner whose gRPC service is at `url` (the control plane, and everything
    /// when shared memory is not used). Connects lazily, like [`GrpcLink::connect`]. Holds at
    /// most `grpc.max_held` messages until durable, as the gRPC link does.
    pub fn connect(
        url: &str,
        grpc: GrpcLinkOptions,
        options: ShmLinkOptions,
    ) -> Result<Self, ConnectError> {
        if options.window == 0 {
            return Err(ConnectError::ZeroWindow);
        }
        if grpc.max_held < options.window {
            return Err(ConnectError::HeldBelowWindow);
        }
        let grpc = GrpcLink::connect(
            url,
            GrpcLinkOptions {
                watch_weights: false,
                ..grpc
            },
        )?;
        let stats = grpc.stats().unwrap_or_default();
        Ok(Self {
            max_held: grpc.max_held(),
            grpc,
            options,
            attached: None,
            registration: None,
            digest: String::new(),
            incarnation: 0,
            held: Held::default(),
            sent_through: 0,
            stats,
            weights: Arc::default(),
            learner_version: Arc::default(),
            quiet_since: Instant::now(),
            alone_since: None,
            reregistrations: 0,
            dropped_batches: 0,
            dropped_transitions: 0,
            last_drop_warning: None,
        })
    }

    /// Whether messages go over shared memory now (else over gRPC).
    pub fn uses_shm(&self) -> bool {
        self.attached.is_some()
    }

    /// The namespace in use, if attached.
    pub fn namespace(&self) -> Option<&Namespace> {
        self.attached.as_ref().map(|a| &a.namespace)
    }

    /// Messages sent over shared memory and not yet acknowledged.
    pub fn unacked(&self) -> usize {
        self.held.unacked()
    }

    /// Messages kept until the learner says they are durable (acknowledged ones included).
    pub fn held(&self) -> usize {
        self.held.len()
    }

    /// Every message up to this sequence is acknowledged (in the current incarnation).
    pub fn acked_through(&self) -> u64 {
        self.held.acked_through()
    }

    /// Every message up to this sequence is durable (in the current incarnation).
    pub fn durable_through(&self) -> u64 {
        self.held.durable_through()
    }

    /// The incarnation messages are numbered under now (0 before registration).
    pub fn incarnation(&self) -> u64 {
        self.incarnation
    }

    /// Transition batches and their transitions dropped by [`Overflow::Drop`].
    pub fn dropped(&self) -> (u64, u64) {
        (self.dropped_batches, self.dropped_transitions)
    }

    fn actor_id(&self) -> &str {
        self.registration
            .as_ref()
            .map_or("", |r| r.actor_id.as_str())
    }

    /// Puts the held counts into the link's stats (while attached: the gRPC link reports its
    /// own otherwise).
    fn report(&self) {
        if self.attached.is_some() {
            self.stats.set_unacked(self.held.unacked());
            self.stats.set_undurable(self.held.undurable());
        }
    }

    /// Attaches to the namespace `admission` offers, or falls back to gRPC (`Prefer`), or fails
    /// (`Require`). What is held goes wherever the link ends up: over gRPC, numbered on from
    /// the durable watermark under the same incarnation.
    fn attach(&mut self, admission: &Admission) -> Result<(), LinkError> {
        let previous = self.attached.take();
        let offered = admission.shm.as_ref().filter(|offer| {
            let me = host_identity();
            !me.is_empty() && offer.host == me
        });
        let attempt = match offered {
            None => Err(format!(
                "the learner serves no shared memory to this host ({}; start it with --shm on \
                 this host)",
                if admission.shm.is_some() {
                    "it runs on another host"
                } else {
                    "none offered"
                }
            )),
            Some(offer) => Namespace::parse(&offer.namespace)
                .and_then(|namespace| {
                    // The same namespace: reuse the ports; a new incarnation gets its acks.
                    match previous {
                        Some(mut attached) if attached.namespace == namespace => {
                            if attached.acks.incarnation != admission.incarnation {
                                attached.acks = AckPorts::open(
                                    &attached.node,
                                    &namespace,
                                    self.actor_id(),
                                    admission.incarnation,
                                )?;
                            }
                            Ok(attached)
                        }
                        _ => Attached::open(
                            namespace,
                            admission,
                            &self.options,
                            self.actor_id(),
                            (self.weights.clone(), self.learner_version.clone()),
                        ),
                    }
                })
                .map_err(|e| format!("shared memory: {e}")),
        };
        match attempt {
            Ok(attached) => {
                if self.attached.is_none() {
                    tracing::info!(
                        namespace = %attached.namespace,
                        window = attached.window,
                        "sending over shared memory"
                    );
                }
                self.attached = Some(attached);
                self.stats
                    .incarnation
                    .store(admission.incarnation, Ordering::Relaxed);
                self.report();
                Ok(())
            }
            Err(why) if self.options.mode == ShmMode::Require => Err(LinkError::Refused(why)),
            Err(why) => {
                tracing::info!(reason = %why, "using gRPC");
                self.grpc.watch_weights();
                // What shared memory did not make durable goes over gRPC, in order, numbered on
                // from there (a learner that kept the incarnation has everything before it).
                self.grpc.continue_after(self.held.durable_through());
                for item in self.held.take_all() {
                    // The gRPC link counts it as sent again.
                    self.stats
                        .sent_transitions
                        .fetch_sub(transitions_of(&item), Ordering::Relaxed);
                    self.grpc.send(item)?;
                }
                self.sent_through = self.held.durable_through();
                Ok(())
            }
        }
    }

    /// Packs `item` as sequence `sequence` into a loaned sample and sends it.
    fn publish(&self, item: &IngestItem, sequence: u64) -> Result<(), LinkError> {
        let attached = self.attached.as_ref().expect("publish only while attached");
        let msg = IngestRef {
            actor_id: self.registration.as_ref().map_or("", |r| &r.actor_id),
            incarnation: self.incarnation,
            sequence,
            item: item.view(),
        };
        let len = packed_ingest_len(&msg);
        let mut sample = attached
            .publisher
            .loan_slice(len)
            .map_err(|e| LinkError::Unavailable(format!("loaning shared memory: {e}")))?;
        pack_ingest(&msg, sample.payload_mut());
        sample
            .send()
            .map_err(|e| LinkError::Unavailable(format!("sending over shared memory: {e}")))?;
        // Cheap: an event already pending is not signalled again.
        if let Err(e) = attached.ingest_notifier.notify() {
            tracing::debug!(error = %e, "notifying the learner");
        }
        Ok(())
    }

    /// Publishes the held messages after `sent_through` while fewer than a window of them are
    /// unacknowledged: a new message at once, the rest of a resend as acks make room (the
    /// learner's buffer never holds more than a window).
    fn pump(&mut self) -> Result<(), LinkError> {
        let Some(attached) = &self.attached else {
            return Ok(());
        };
        let window = attached.window as u64;
        self.sent_through = self.sent_through.max(self.held.acked_through());
        while self.sent_through < self.held.last()
            && self.sent_through - self.held.acked_through() < window
        {
            let sequence = self.sent_through + 1;
            let item = self
                .held
                .get(sequence)
                .expect("held after the durable watermark");
            self.publish(item, sequence)?;
            self.sent_through = sequence;
        }
        Ok(())
    }

    /// Applies every ack waiting, handles a refusal, then publishes what the acks made room for.
    fn poll(&mut self) -> Result<(), LinkError> {
        self.receive_acks()?;
        self.pump()?;
        self.report();
        Ok(())
    }

    /// Applies every ack waiting; handles a refusal.
    fn receive_acks(&mut self) -> Result<(), LinkError> {
        loop {
            let Some(attached) = &self.attached else {
                return Ok(());
            };
            let wire = match attached.acks.subscriber.receive() {
                Ok(Some(sample)) => *sample.payload(),
                Ok(None) => return Ok(()),
                Err(e) => return Err(LinkError::Unavailable(format!("receiving acks: {e}"))),
            };
            let Some(ack) = Ack::from_wire(&wire) else {
                tracing::warn!(?wire, "an ack this build does not understand");
                continue;
            };
            if ack.incarnation != self.incarnation {
                continue;
            }
            self.quiet_since = Instant::now();
            self.alone_since = None;
            self.learner_version
                .store(ack.weights_version, Ordering::Relaxed);
            self.stats
                .learner_version
                .store(ack.weights_version, Ordering::Relaxed);
            let mut durable = 0;
            self.held
                .acknowledge(ack.acked_through, ack.durable_through, |item| {
                    durable += transitions_of(&item);
                });
            self.stats
                .durable_transitions
                .fetch_add(durable, Ordering::Relaxed);
            match ack.refusal {
                None => self.reregistrations = 0,
                // A gap: a resumed learner lacks messages sent to the learner before it (this
                // link sent on before it noticed the restart); registering again naming the
                // incarnation keeps it, and what is not durable is resent.
                Some(
                    RejectReason::UnknownActor
                    | RejectReason::StaleIncarnation
                    | RejectReason::SequenceGap,
                ) => self.reregister()?,
                Some(RejectReason::Finished) => return Err(LinkError::Finished),
                Some(reason) => {
                    return Err(LinkError::Refused(format!(
                        "the learner refused message {} as `{}` (its log says why)",
                        self.held.acked_through() + 1,
                        reason.name()
                    )));
                }
            }
        }
    }

    /// Registers again (the learner does not know this incarnation, or lacks messages of it),
    /// naming the incarnation and the oldest message held, checks the run is the same, and
    /// resends what is held from the oldest on: under the same numbering if the learner kept
    /// the incarnation (it has everything durable), else renumbered from 1 under the new one.
    fn reregister(&mut self) -> Result<(), LinkError> {
        self.reregistrations += 1;
        if self.reregistrations > MAX_REREGISTRATIONS {
            return Err(LinkError::Refused(format!(
                "registered {MAX_REREGISTRATIONS} times in a row without getting anything \
                 through: is another actor using the id `{}`?",
                self.actor_id()
            )));
        }
        let registration = self
            .registration
            .clone()
            .ok_or_else(|| LinkError::Refused("send before register".into()))?;
        let previous = PreviousIncarnation {
            incarnation: self.incarnation,
            resend_from: self.held.durable_through() + 1,
        };
        let admission = self.grpc.register_naming(&registration, Some(previous))?;
        if admission.run_config_digest != self.digest {
            return Err(LinkError::Refused(format!(
                "the learner runs a different config now (digest {}, registered under {}): \
                 restart the actor",
                admission.run_config_digest, self.digest
            )));
        }
        let kept = admission.incarnation == self.incarnation;
        if kept {
            self.held.rewind();
        } else {
            self.incarnation = admission.incarnation;
            self.held.renumber();
        }
        self.sent_through = self.held.durable_through();
        self.learner_version.store(0, Ordering::Relaxed);
        self.attach(&admission)?;
        tracing::info!(
            actor = %registration.actor_id,
            incarnation = admission.incarnation,
            kept,
            resent = self.held.len(),
            "registered again with the learner"
        );
        self.pump()
    }

    /// Sleeps until an ack may have come (at most until `deadline`), then looks at the learner
    /// if nothing came for a while.
    fn wait(&mut self, deadline: Option<Instant>) -> Result<(), LinkError> {
        let Some(attached) = &self.attached else {
            return Ok(());
        };
        let slice = deadline.map_or(WAIT_SLICE, |d| {
            d.saturating_duration_since(Instant::now()).min(WAIT_SLICE)
        });
        if let Err(e) = attached.acks.listener.timed_wait(|_| {}, slice) {
            tracing::debug!(error = %e, "waiting for acks");
            std::thread::sleep(slice);
        }
        if self.quiet_since.elapsed() >= STALL_CHECK {
            self.quiet_since = Instant::now();
            self.check_learner()?;
        }
        Ok(())
    }

    /// After a long silence: a learner that is no longer the one the messages went to gets
    /// everything not durable again, from the oldest on (what the one before acknowledged after
    /// its log's last commit may be lost with it); no learner at all for `give_up_after` fails
    /// the link.
    fn check_learner(&mut self) -> Result<(), LinkError> {
        let Some(attached) = &mut self.attached else {
            return Ok(());
        };
        cleanup_dead_nodes(&attached.node);
        let now = subscriber_ids(&attached.ingest);
        if now.is_empty() {
            let since = *self.alone_since.get_or_insert_with(Instant::now);
            if since.elapsed() >= self.options.give_up_after {
                return Err(LinkError::Unavailable(format!(
                    "no learner has listened on {} for {:?}",
                    attached.namespace, self.options.give_up_after
                )));
            }
            tracing::debug!("no learner listening; waiting");
        }
        if now == attached.learner {
            return Ok(());
        }
        let listening = !now.is_empty();
        attached.learner = now;
        if listening {
            self.alone_since = None;
            // The acks the learner before sent are in: what they said durable stays so.
            self.receive_acks()?;
            let actor_id = self
                .registration
                .as_ref()
                .map_or("", |r| r.actor_id.as_str());
            let Some(attached) = &mut self.attached else {
                return Ok(());
            };
            attached.renew(actor_id);
            self.held.rewind();
            self.sent_through = self.held.durable_through();
            tracing::info!(
                resent = self.held.len(),
                from = self.held.durable_through() + 1,
                "a new learner listens: resending what is not durable"
            );
            self.pump()?;
            self.report();
        }
        Ok(())
    }

    fn window(&self) -> usize {
        self.attached.as_ref().map_or(usize::MAX, |a| a.window)
    }

    fn count_drop(&mut self, item: &IngestItem) {
        let IngestItem::Batch(batch) = item else {
            return;
        };
        self.dropped_batches += 1;
        self.dropped_transitions += batch.batch.len as u64;
        if self
            .last_drop_warning
            .is_none_or(|at| at.elapsed() >= WARN_EVERY)
        {
            self.last_drop_warning = Some(Instant::now());
            tracing::warn!(
                dropped_batches = self.dropped_batches,
                dropped_transitions = self.dropped_transitions,
                "the learner is behind: dropping transition batches (--shm-overflow drop)"
            );
        }
    }
}

/// The transitions an ingest item carries (0 for an episode summary).
fn transitions_of(item: &IngestItem) -> u64 {
    match item {
        IngestItem::Batch(batch) => batch.batch.len as u64,
        IngestItem::Episode { .. } => 0,
    }
}

impl IngestSink for ShmLink {
    /// Blocks while a window of messages is unacknowledged or `max_held` are not durable (or,
    /// with [`Overflow::Drop`], drops a transition batch then), as the gRPC link does.
    fn send(&mut self, item: IngestItem) -> Result<(), LinkError> {
        if self.incarnation == 0 {
            return Err(LinkError::Refused("send before register".into()));
        }
        loop {
            if self.attached.is_none() {
                return self.grpc.send(item);
            }
            self.poll()?;
            if self.attached.is_none() {
                continue;
            }
            if self.held.has_room(self.window(), self.max_held) {
                break;
            }
            if self.options.overflow == Overflow::Drop && matches!(item, IngestItem::Batch(_)) {
                self.count_drop(&item);
                return Ok(());
            }
            self.wait(None)?;
        }
        if self.held.unacked() == 0 {
            self.quiet_since = Instant::now();
        }
        self.stats
            .sent_transitions
            .fetch_add(transitions_of(&item), Ordering::Relaxed);
        self.held.push(item);
        self.pump()?;
        self.report();
        Ok(())
    }

    fn flush(&mut self, timeout: Duration) -> Result<(), LinkError> {
        let deadline = Instant::now() + timeout;
        loop {
            if self.attached.is_none() {
                return self
                    .grpc
                    .flush(deadline.saturating_duration_since(Instant::now()));
            }
            self.poll()?;
            if self.attached.is_some() && self.held.unacked() == 0 {
                return Ok(());
            }
            if Instant::now() >= deadline {
                return Err(LinkError::TimedOut(self.held.unacked()));
            }
            self.wait(Some(deadline))?;
        }
    }

    /// Until the learner says everything is durable (the shm server reports it like the gRPC
    /// server); over the gRPC fallback, the gRPC link's.
    fn flush_durable(&mut self, timeout: Duration) -> Result<(), LinkError> {
        let deadline = Instant::now() + timeout;
        loop {
            if self.attached.is_none() {
                return self
                    .grpc
                    .flush_durable(deadline.saturating_duration_since(Instant::now()));
            }
            self.poll()?;
            if self.attached.is_some() && self.held.is_empty() {
                return Ok(());
            }
            if Instant::now() >= deadline {
                return Err(LinkError::TimedOut(self.held.len()));
            }
            self.wait(Some(deadline))?;
        }
    }
}

impl WeightsSource for ShmLink {
    fn weights(&self) -> &Published<WeightsSnapshot> {
        if self.attached.is_some() {
            &self.weights
        } else {
            self.grpc.weights()
        }
    }

    fn learner_version(&self) -> u64 {
        if self.attached.is_some() {
            self.learner_version.load(Ordering::Relaxed)
        } else {
            self.grpc.learner_version()
        }
    }
}

impl ActorLink for ShmLink {
    fn register(&mut self, registration: &Registration) -> Result<Admission, LinkError> {
        let mut registration = registration.clone();
        if !registration
            .transports
            .iter()
            .any(|t| t == super::TRANSPORT)
        {
            registration.transports.push(super::TRANSPORT.into());
        }
        let admission = self.grpc.register(&registration)?;
        self.registration = Some(registration);
        self.digest = admission.run_config_digest.clone();
        self.incarnation = admission.incarnation;
        self.held.renumber();
        self.sent_through = 0;
        self.attach(&admission)?;
        self.pump()?;
        Ok(admission)
    }

    /// Over the gRPC control link, like registration.
    fn await_turn(&mut self, wait: Duration) -> Result<Option<GrantedTurn>, LinkError> {
        self.grpc.await_turn(wait)
    }

    fn report_evaluation(&mut self, report: &EvaluationOf) -> Result<bool, LinkError> {
        self.grpc.report_evaluation(report)
    }

    /// The link's counters: over shared memory this link's (incarnation, unacknowledged and
    /// undurable messages, transitions sent and durable, the learner's version), with the gRPC
    /// control link's reconnects; over the gRPC fallback, the gRPC link's.
    fn stats(&self) -> Option<Arc<LinkStats>> {
        Some(self.stats.clone())
    }

    fn transport(&self) -> &'static str {
        if self.attached.is_some() {
            super::TRANSPORT
        } else {
            self.grpc.transport()
        }
    }
}
