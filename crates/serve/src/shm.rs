//! [`ShmServer`]: the learner's side of shared memory (see [`hac_transport::shm`] for the
//! services, the delivery rules and the actor's side), beside [`grpc::serve`](crate::grpc::serve).
//!
//! Two threads. *Ingest* waits for room in the learner (backpressure: nothing is read meanwhile,
//! so actors' windows fill and they block), takes the next packed message from the `ingest`
//! subscriber, ingests it in place through [`Learner::ingest_ref`] and acknowledges cumulatively
//! per actor incarnation (acks are published once per round of messages, not per message), with
//! the durable watermark read from the learner as the gRPC server does. When nothing waits it
//! sleeps on the `ingest` event, and every few seconds it removes dead nodes and the ack services
//! nobody listens to any more, and logs the summary of refusals not logged one by one (a
//! `RefusalLog`). *Weights* waits for each new snapshot in the learner's
//! [`Published`] cell and publishes it packed, with history 1. With a
//! write-ahead log, a third thread, *commits*, signals the `ingest` event after each commit of
//! the log, so that durability advancing reaches the actors at once, without new messages.

use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use hac_learner::{IngestError, Learner, RoomError};
use hac_proto::{
    Clipped, PACKED_ALIGNMENT, Published, ShmOffer, WeightsSnapshot, pack_weights,
    packed_weights_len, unpack_ingest,
};
use hac_transport::refusal_log::{RefusalLog, SUMMARY_INTERVAL};
use hac_transport::shm::{
    Ack, AckService, AckWire, Ipc, Namespace, Node, SHM_DIR, ShmError, TRANSPORT, check_free_space,
    cleanup_dead_nodes, host_identity, node, open_ack_events, open_acks, segment_bytes,
};
use iceoryx2::port::ReceiveError;
use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::port::update_connections::UpdateConnections as _;
use iceoryx2::prelude::{Alignment, AllocationStrategy, PortFactory as _};
use iceoryx2::service::port_factory::{event, publish_subscribe};

/// How the learner serves shared memory.
#[derive(Debug, Clone, PartialEq)]
pub struct ShmServerOptions {
    /// Most actors attached at once (more are refused a port and fall back to gRPC).
    pub max_actors: usize,
    /// Messages each actor may have unacknowledged: the learner's receive buffer per actor.
    pub window: usize,
    /// The shared-memory file system, checked for room.
    pub shm_dir: PathBuf,
}

impl Default for ShmServerOptions {
    fn default() -> Self {
        Self {
            max_actors: 32,
            window: 32,
            shm_dir: PathBuf::from(SHM_DIR),
        }
    }
}

/// Longest sleep of the ingest thread when nothing arrives (it wakes at once on an actor's
/// event); also how soon it notices a shutdown.
const IDLE_WAIT: Duration = Duration::from_millis(50);
/// One blocking wait for room in the learner.
const ROOM_WAIT: Duration = Duration::from_millis(100);
/// Messages taken in a row before the acks due are published.
const ACK_EVERY: usize = 32;
/// How often dead nodes and unused ack services are cleaned up.
const HOUSEKEEPING: Duration = Duration::from_secs(2);
/// The weights thread's wait for a new version, between deliveries of history to late joiners.
const WEIGHTS_WAIT: Duration = Duration::from_millis(50);
/// The commits thread's wait for a commit, between looks at the stop flag.
const COMMIT_WAIT: Duration = Duration::from_millis(100);

type IngestService = publish_subscribe::PortFactory<Ipc, [u8], ()>;

/// The learner's shared-memory server: serves `hac/<namespace>/...` until stopped or dropped.
#[derive(Debug)]
pub struct ShmServer {
    offer: ShmOffer,
    stop: Arc<AtomicBool>,
    threads: Vec<JoinHandle<()>>,
}

impl ShmServer {
    /// Cleans up dead nodes, checks `/dev/shm` for room, creates (or, after a restart whose
    /// actors still hold them, opens) the run's services and starts both threads.
    pub fn start(
        learner: Arc<Learner>,
        namespace: Namespace,
        options: ShmServerOptions,
    ) -> Result<Self, ShmError> {
        if options.max_actors == 0 || options.window == 0 {
            return Err(ShmError::iceoryx(
                "configuring shared memory",
                "--shm-max-actors and --shm-window must be at least 1",
            ));
        }
        let host = host_identity();
        if host.is_empty() {
            return Err(ShmError::iceoryx(
                "identifying this host",
                "/proc/sys/kernel/random/boot_id is unreadable",
            ));
        }
        let node = node(&format!("hac-learner-{}", namespace.as_str()))?;
        cleanup_dead_nodes(&node);

        let snapshot = learner
            .weights()
            .latest()
            .ok_or_else(|| ShmError::iceoryx("starting", "the learner has published nothing"))?;
        let snapshot_len = packed_weights_len(&snapshot);
        // Per watcher: its buffer (2) and a borrowed sample; plus history and a loan.
        let weights_chunks = options.max_actors * 3 + 2;
        check_free_space(
            &options.shm_dir,
            segment_bytes(weights_chunks, snapshot_len) + options.max_actors as u64 * (1 << 16),
            "the learner's shared memory (weights for --shm-max-actors actors)",
            "lower --shm-max-actors",
        )?;

        let ingest_name = namespace.ingest()?;
        let ingest = node
            .service_builder(&ingest_name)
            .publish_subscribe::<[u8]>()
            .payload_alignment(Alignment::new(PACKED_ALIGNMENT).expect("a power of two"))
            .enable_safe_overflow(false)
            .history_size(0)
            .subscriber_max_buffer_size(options.window)
            .subscriber_max_borrowed_samples(1)
            .max_publishers(options.max_actors)
            .max_subscribers(1)
            .max_nodes(options.max_actors + 4)
            .open_or_create()
            .map_err(|e| ShmError::iceoryx(format!("creating {ingest_name}"), e))?;
        let subscriber = ingest
            .subscriber_builder()
            .create()
            .map_err(|e| ShmError::iceoryx(format!("subscribing to {ingest_name}"), e))?;
        let ingest_events = node
            .service_builder(&ingest_name)
            .event()
            // The actors, and the commits thread.
            .max_notifiers(options.max_actors + 1)
            .max_listeners(2)
            .max_nodes(options.max_actors + 4)
            .open_or_create()
            .map_err(|e| ShmError::iceoryx(format!("creating the event {ingest_name}"), e))?;
        let listener = ingest_events
            .listener_builder()
            .create()
            .map_err(|e| ShmError::iceoryx(format!("listening to {ingest_name}"), e))?;

        let weights_name = namespace.weights()?;
        let weights = node
            .service_builder(&weights_name)
            .publish_subscribe::<[u8]>()
            .enable_safe_overflow(true)
            .history_size(1)
            .subscriber_max_buffer_size(2)
            .subscriber_max_borrowed_samples(1)
            .max_publishers(2)
            .max_subscribers(options.max_actors)
            .max_nodes(options.max_actors + 4)
            .open_or_create()
            .map_err(|e| ShmError::iceoryx(format!("creating {weights_name}"), e))?;
        let publisher = weights
            .publisher_builder()
            .initial_max_slice_len(snapshot_len)
            .allocation_strategy(AllocationStrategy::PowerOfTwo)
            .max_loaned_samples(1)
            .create()
            .map_err(|e| ShmError::iceoryx(format!("publishing to {weights_name}"), e))?;
        let weights_events = node
            .service_builder(&weights_name)
            .event()
            .max_notifiers(2)
            .max_listeners(options.max_actors)
            .max_nodes(options.max_actors + 4)
            .open_or_create()
            .map_err(|e| ShmError::iceoryx(format!("creating the event {weights_name}"), e))?;
        let notifier = weights_events
            .notifier_builder()
            .create()
            .map_err(|e| ShmError::iceoryx(format!("notifying {weights_name}"), e))?;

        // Only with a write-ahead log: without one, what is stored is durable at once.
        let commit_notifier = match learner.durable_commits() {
            Some(_) => Some(
                ingest_events
                    .notifier_builder()
                    .create()
                    .map_err(|e| ShmError::iceoryx(format!("notifying {ingest_name}"), e))?,
            ),
            None => None,
        };

        let node = Arc::new(node);
        let stop = Arc::new(AtomicBool::new(false));
        let ingest_thread = Ingest {
            learner: learner.clone(),
            namespace: namespace.clone(),
            node: node.clone(),
            _service: ingest,
            subscriber,
            _events: ingest_events,
            listener,
            acks: HashMap::new(),
            refusals: RefusalLog::new(SUMMARY_INTERVAL),
            commits_seen: None,
            stop: stop.clone(),
        };
        let commits_thread = commit_notifier.map(|notifier| Commits {
            learner: learner.clone(),
            notifier,
            stop: stop.clone(),
        });
        let weights_thread = Weights {
            learner,
            _node: node,
            _service: weights,
            publisher,
            _events: weights_events,
            notifier,
            stop: stop.clone(),
        };
        let spawn = |name: &str, f: Box<dyn FnOnce() + Send>| {
            std::thread::Builder::new()
                .name(name.into())
                .spawn(f)
                .map_err(|e| ShmError::iceoryx("starting a thread", e))
        };
        let mut threads = vec![
            spawn("hac-shm-ingest", Box::new(move || ingest_thread.run()))?,
            spawn("hac-shm-weights", Box::new(move || weights_thread.run()))?,
        ];
        if let Some(commits) = commits_thread {
            threads.push(spawn("hac-shm-commits", Box::new(move || commits.run()))?);
        }
        tracing::info!(
            namespace = %namespace,
            max_actors = options.max_actors,
            window = options.window,
            "serving shared memory"
        );
        Ok(Self {
            offer: ShmOffer {
                namespace: namespace.as_str().to_string(),
                host,
            },
            stop,
            threads,
        })
    }

    /// What registration announces to actors that can use shared memory.
    pub fn offer(&self) -> ShmOffer {
        self.offer.clone()
    }

    /// Stops both threads and releases the services (also on drop).
    pub fn stop(mut self) {
        self.shut_down();
    }

    fn shut_down(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        for thread in self.threads.drain(..) {
            let _ = thread.join();
        }
    }
}

impl Drop for ShmServer {
    fn drop(&mut self) {
        self.shut_down();
    }
}

/// What the learner knows of one actor incarnation.
struct AckPort {
    incarnation: u64,
    acked_through: u64,
    /// The durable watermark sent (at most `acked_through`).
    durable_through: u64,
    /// An ack is due.
    dirty: bool,
    /// The sequence of a message refused: the rest of this incarnation is not read (as gRPC ends
    /// the stream), until the actor starts over below it (it registered again and the learner
    /// kept its incarnation: it resends from its oldest message not durable).
    refused_at: Option<u64>,
    /// The learner's status knows this actor streams over shared memory.
    transport_noted: bool,
    last_message: Instant,
    service: AckService,
    publisher: Publisher<Ipc, AckWire, ()>,
    _events: event::PortFactory<Ipc>,
    notifier: Notifier<Ipc>,
}

impl AckPort {
    fn open(
        node: &Node,
        namespace: &Namespace,
        actor_id: &str,
        incarnation: u64,
    ) -> Result<Self, ShmError> {
        let name = namespace.acks(actor_id, incarnation)?;
        let service = open_acks(node, &name)?;
        let publisher = service
            .publisher_builder()
            .max_loaned_samples(1)
            .create()
            .map_err(|e| ShmError::iceoryx(format!("publishing to {name}"), e))?;
        let events = open_ack_events(node, &name)?;
        let notifier = events
            .notifier_builder()
            .create()
            .map_err(|e| ShmError::iceoryx(format!("notifying {name}"), e))?;
        Ok(Self {
            incarnation,
            acked_through: 0,
            durable_through: 0,
            dirty: false,
            refused_at: None,
            transport_noted: false,
            last_message: Instant::now(),
            service,
            publisher,
            _events: events,
            notifier,
        })
    }

    fn send(&mut self, ack: Ack) {
        self.dirty = false;
        if let Err(e) = self.publisher.send_copy(ack.to_wire()) {
            tracing::warn!(error = %e, incarnation = self.incarnation, "publishing an ack");
        }
        if let Err(e) = self.notifier.notify() {
            tracing::debug!(error = %e, "notifying an actor");
        }
    }
}

struct Ingest {
    learner: Arc<Learner>,
    namespace: Namespace,
    node: Arc<Node>,
    _service: IngestService,
    subscriber: Subscriber<Ipc, [u8], ()>,
    _events: event::PortFactory<Ipc>,
    listener: Listener<Ipc>,
    /// By actor id, one entry per incarnation seen recently.
    acks: HashMap<String, Vec<AckPort>>,
    refusals: RefusalLog,
    /// The write-ahead log's commit count at the last look (`None`: no look yet, or no log).
    commits_seen: Option<u64>,
    stop: Arc<AtomicBool>,
}

impl Ingest {
    /// Reads in rounds of at most one message per actor. The subscriber's `receive` looks at
    /// its publishers in a fixed order and returns the first one's message, so a loop that
    /// took one message at a time served the first actor whenever it had one waiting (a fast
    /// actor refills its window as soon as it is acknowledged) and starved the others: with two
    /// shared-memory trainers, one often stored nothing. A subscriber borrows at most one
    /// message per publisher and `receive` skips the publishers at that limit, so holding the
    /// round's messages until the round is taken moves it on to the next actor each time.
    fn run(mut self) {
        let mut last_housekeeping = Instant::now();
        let mut taken = 0usize;
        let mut round = Vec::new();
        while !self.stop.load(Ordering::Relaxed) {
            loop {
                match self.subscriber.receive() {
                    Ok(Some(sample)) => round.push(sample),
                    Ok(None) => break,
                    // Every publisher with a message waiting has one in this round.
                    Err(ReceiveError::ExceedsMaxBorrows) => break,
                    Err(e) => {
                        tracing::warn!(error = %e, "receiving an ingest message");
                        std::thread::sleep(IDLE_WAIT);
                        break;
                    }
                }
            }
            if round.is_empty() {
                self.flush_acks();
                if last_housekeeping.elapsed() >= HOUSEKEEPING {
                    self.housekeeping();
                    last_housekeeping = Instant::now();
                }
                if let Err(e) = self.listener.timed_wait(|_| {}, IDLE_WAIT) {
                    tracing::warn!(error = %e, "waiting for ingest messages");
                    std::thread::sleep(IDLE_WAIT);
                }
                continue;
            }
            for sample in round.drain(..) {
                if !self.wait_for_room() {
                    // Stopping: the rest of the round is not acknowledged, so it is not lost.
                    break;
                }
                self.take(sample.payload());
                drop(sample);
                taken += 1;
                if taken.is_multiple_of(ACK_EVERY) {
                    self.flush_acks();
                    if last_housekeeping.elapsed() >= HOUSEKEEPING {
                        self.housekeeping();
                        last_housekeeping = Instant::now();
                    }
                }
            }
        }
        self.flush_acks();
    }

    /// Backpressure: waits until the learner has room for a message (acknowledging what was
    /// stored meanwhile). Once the run is over messages are read and refused as `finished`.
    /// False when the server stops first.
    fn wait_for_room(&mut self) -> bool {
        while !self.learner.has_room() {
            self.flush_acks();
            match self.learner.wait_for_room(ROOM_WAIT) {
                Ok(()) | Err(RoomError::Finished) => return true,
                Err(RoomError::TimedOut) if self.stop.load(Ordering::Relaxed) => return false,
                Err(RoomError::TimedOut) => {}
            }
        }
        true
    }

    /// Ingests one packed message and notes the ack it earns (or sends the refusal at once).
    fn take(&mut self, bytes: &[u8]) {
        let msg = match unpack_ingest(bytes) {
            Ok(msg) => msg,
            Err(e) => {
                // Without a readable identity there is nobody to answer.
                let e = IngestError::from(e);
                self.learner.count_rejection(e.reason());
                self.refusals
                    .refused("shared-memory message", e.reason(), "", &e);
                return;
            }
        };
        let Some(port) = port(
            &mut self.acks,
            &self.node,
            &self.namespace,
            msg.actor_id,
            msg.incarnation,
        ) else {
            return;
        };
        port.last_message = Instant::now();
        if let Some(refused) = port.refused_at {
            if msg.sequence >= refused {
                return;
            }
            port.refused_at = None;
        }
        match self.learner.ingest_ref(&msg) {
            Ok(_) => {
                if !port.transport_noted {
                    self.learner.set_actor_transport(msg.actor_id, TRANSPORT);
                    port.transport_noted = true;
                }
                port.acked_through = port.acked_through.max(msg.sequence);
                port.dirty = true;
            }
            Err(e) => {
                // The learner counted it.
                self.refusals
                    .refused("ingest message", e.reason(), msg.actor_id, &e);
                port.refused_at = Some(msg.sequence);
                let ack = Ack {
                    acked_through: port.acked_through,
                    durable_through: port.durable_through,
                    weights_version: weights_version(&self.learner),
                    refusal: Some(e.reason()),
                    incarnation: port.incarnation,
                };
                port.send(ack);
            }
        }
    }

    /// Publishes the acks due: every port that stored something since its last ack, or whose
    /// durable watermark advanced (read from the learner when something was stored, or the log
    /// committed since the last look; without a log, stored is durable).
    fn flush_acks(&mut self) {
        let logged = self.learner.durable_commits();
        // Read before the watermarks: a commit after this is seen at the next look.
        let commits = logged.and_then(Published::latest).map(|n| *n);
        let committed = commits != self.commits_seen;
        self.commits_seen = commits;
        let mut version = None;
        for (actor_id, ports) in &mut self.acks {
            for port in ports.iter_mut() {
                if port.durable_through < port.acked_through && (port.dirty || committed) {
                    let durable = match logged {
                        Some(_) => self
                            .learner
                            .durable_through(actor_id, port.incarnation)
                            .min(port.acked_through),
                        None => port.acked_through,
                    };
                    if durable > port.durable_through {
                        port.durable_through = durable;
                        port.dirty = true;
                    }
                }
                if !port.dirty {
                    continue;
                }
                let weights_version =
                    *version.get_or_insert_with(|| weights_version(&self.learner));
                let ack = Ack {
                    acked_through: port.acked_through,
                    durable_through: port.durable_through,
                    weights_version,
                    refusal: None,
                    incarnation: port.incarnation,
                };
                port.send(ack);
            }
        }
    }

    /// Removes dead nodes' resources (a killed actor's publisher slot), then the ack ports of
    /// incarnations nobody listens to any more.
    fn housekeeping(&mut self) {
        self.refusals.flush();
        cleanup_dead_nodes(&self.node);
        for ports in self.acks.values_mut() {
            ports.retain(|p| {
                p.dirty
                    || p.last_message.elapsed() < HOUSEKEEPING
                    || p.service.dynamic_config().number_of_subscribers() > 0
            });
        }
        self.acks.retain(|_, ports| !ports.is_empty());
    }
}

/// The ack port of `actor_id`'s `incarnation`, opened on first use (allocates only then).
fn port<'a>(
    acks: &'a mut HashMap<String, Vec<AckPort>>,
    node: &Node,
    namespace: &Namespace,
    actor_id: &str,
    incarnation: u64,
) -> Option<&'a mut AckPort> {
    if !acks.contains_key(actor_id) {
        acks.insert(actor_id.to_string(), Vec::new());
    }
    let ports = acks.get_mut(actor_id)?;
    let index = match ports.iter().position(|p| p.incarnation == incarnation) {
        Some(index) => index,
        None => match AckPort::open(node, namespace, actor_id, incarnation) {
            Ok(port) => {
                ports.push(port);
                ports.len() - 1
            }
            Err(e) => {
                let actor = Clipped(actor_id);
                tracing::warn!(%actor, incarnation, error = %e, "cannot answer an actor");
                return None;
            }
        },
    };
    ports.get_mut(index)
}

/// Signals the `ingest` event after each commit of the learner's write-ahead log: the ingest
/// thread wakes and sends the acks whose durable watermark advanced.
struct Commits {
    learner: Arc<Learner>,
    notifier: Notifier<Ipc>,
    stop: Arc<AtomicBool>,
}

impl Commits {
    fn run(self) {
        let Some(commits) = self.learner.durable_commits() else {
            return;
        };
        let mut seen = commits.latest().map(|n| *n);
        while !self.stop.load(Ordering::Relaxed) {
            if let Some(n) = commits.wait_for(COMMIT_WAIT, |&n| Some(n) != seen) {
                seen = Some(*n);
                if let Err(e) = self.notifier.notify() {
                    tracing::debug!(error = %e, "notifying the ingest thread of a commit");
                }
            }
        }
    }
}

fn weights_version(learner: &Learner) -> u64 {
    learner.weights().latest().map_or(0, |w| w.version)
}

struct Weights {
    learner: Arc<Learner>,
    _node: Arc<Node>,
    _service: publish_subscribe::PortFactory<Ipc, [u8], ()>,
    publisher: Publisher<Ipc, [u8], ()>,
    _events: event::PortFactory<Ipc>,
    notifier: Notifier<Ipc>,
    stop: Arc<AtomicBool>,
}

impl Weights {
    fn run(self) {
        let mut sent = None;
        while !self.stop.load(Ordering::Relaxed) {
            let next = self
                .learner
                .weights()
                .wait_for(WEIGHTS_WAIT, |w| sent != Some(w.version));
            match next {
                Some(snapshot) => {
                    sent = Some(snapshot.version);
                    if let Err(e) = self.publish(&snapshot) {
                        let version = snapshot.version;
                        tracing::warn!(version, error = %e, "publishing weights");
                    }
                }
                // Hands the history (the latest snapshot) to subscribers that joined since.
                None => {
                    if let Err(e) = self.publisher.update_connections() {
                        tracing::debug!(error = %e, "updating weights connections");
                    }
                }
            }
        }
    }

    fn publish(&self, snapshot: &WeightsSnapshot) -> Result<(), ShmError> {
        let len = packed_weights_len(snapshot);
        let mut sample = self
            .publisher
            .loan_slice(len)
            .map_err(|e| ShmError::iceoryx("loaning a weights sample", e))?;
        pack_weights(snapshot, sample.payload_mut());
        sample
            .send()
            .map_err(|e| ShmError::iceoryx("sending weights", e))?;
        self.notifier
            .notify()
            .map_err(|e| ShmError::iceoryx("notifying weights", e))?;
        Ok(())
    }
}
