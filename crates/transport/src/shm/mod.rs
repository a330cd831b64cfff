//! Shared memory between the learner and actors on its host, with iceoryx2 (publish-subscribe
//! and events over `/dev/shm`): transition batches go to the learner without serialisation or a
//! system call per batch, and every weights version reaches the actors once, whoever joins late.
//!
//! - The learner's side, `hac_serve::shm::ShmServer`, runs beside the gRPC server, on threads
//!   of its own: one takes ingest messages in place and acknowledges them, one publishes
//!   weights. It is built from what this module shares with the actor's side: the service names
//!   of a [`Namespace`], the [`Ack`] and its wire form, the ack services ([`open_acks`],
//!   [`open_ack_events`]), iceoryx2 nodes ([`node`], [`cleanup_dead_nodes`]) and the free-space
//!   check.
//! - [`ShmLink`] (actor side) is an [`ActorLink`](crate::ActorLink): batches and episode
//!   summaries over shared memory, the control plane (registration, evaluation reports) over a
//!   [`GrpcLink`](crate::grpc::GrpcLink). With [`ShmMode::Prefer`] it falls back to gRPC for
//!   everything when shared memory is not offered to its host or cannot be used.
//! - `weights`: [`WeightsReceiver`], an actor's subscription to the weights, on a thread.
//! - `space`: the free-space check of `/dev/shm` before anything is mapped.
//!
//! # Services of one run
//! Every name starts with `hac/<namespace>/`; the [`Namespace`] is made of the run's config
//! digest and the learner's gRPC address, so two learners on one host never share a service
//! (they cannot listen on one address), while a learner restarted on its address with the same
//! run finds its actors where it left them.
//!
//! | service | pattern | from -> to | payload |
//! |---|---|---|---|
//! | `ingest` | publish-subscribe | each actor -> learner | a packed ingest message |
//! | `ingest` | event | each actor -> learner | "a message is waiting" |
//! | `acks/<actor>-<incarnation>` | publish-subscribe | learner -> that actor | [`Ack`] |
//! | `acks/<actor>-<incarnation>` | event | learner -> that actor | "an ack is waiting" |
//! | `weights` | publish-subscribe, history 1 | learner -> actors | a packed snapshot |
//! | `weights` | event | learner -> actors | "a snapshot is waiting" |
//!
//! # Delivery, exactly once and backpressure
//! The same rules as gRPC. An actor keeps every message until a cumulative ack says it is
//! durable ([`Ack::durable_through`]: in the learner's write-ahead log), and never has more
//! unacknowledged messages than the learner's subscriber buffer holds (the window), so nothing
//! is ever dropped in shared memory. The learner reads a message only while
//! it has room (its rate limiter), stores it through the learner's `ingest_ref`
//! (the same checks, counts and dedup by actor, incarnation and sequence as gRPC), and acks it;
//! when training falls behind it reads nothing, acks stop, and actors block in `send` (or, if
//! asked, drop new batches and count them: [`Overflow::Drop`]). A refusal travels in the ack
//! ([`Ack::refusal`]); after one, the learner ignores the rest of that incarnation, as gRPC ends
//! the stream, until the actor starts over below the refused message. When the learner's
//! subscriber changes (a restarted learner), the actor resends everything not durable from the
//! oldest on; `unknown_actor`, `stale_incarnation` and `sequence_gap` make it register again
//! naming its incarnation and the oldest message it holds, as the gRPC link does, and resend
//! under the incarnation the learner answers with (the same one if the learner has everything
//! before that message: a learner resumed from its write-ahead log).
//!
//! # Hygiene
//! Both sides remove the resources of dead iceoryx2 nodes (killed processes) at start, and the
//! learner again every few seconds, so a killed actor's slot is free for its restart. Both check
//! that `/dev/shm` has room for what they map (a tmpfs maps lazily: without the check, a full
//! one kills the process with SIGBUS on first write). iceoryx2 keeps its bookkeeping under
//! `/tmp/iceoryx2`; containers that share memory must share that directory and `/dev/shm`.

mod link;
mod space;
mod weights;

use std::fmt;
use std::net::SocketAddr;
use std::sync::Once;

use hac_proto::RejectReason;
use iceoryx2::prelude::{
    LogLevel, NodeBuilder, NodeName, ServiceName, SignalHandlingMode, set_log_level_from_env_or,
};
use iceoryx2::service::port_factory::{event, publish_subscribe};

pub use link::{Overflow, ShmLink, ShmLinkOptions, ShmMode};
pub use space::{SHM_DIR, check_free_space, segment_bytes};
pub use weights::WeightsReceiver;

/// The transport name actors list at registration to be offered shared memory.
pub const TRANSPORT: &str = "shm";

/// iceoryx2's inter-process service with thread-safe ports (links must be `Send`), on both
/// sides.
pub type Ipc = iceoryx2::prelude::ipc_threadsafe::Service;
/// An iceoryx2 node of this process (see [`node`]).
pub type Node = iceoryx2::node::Node<Ipc>;
/// The ack service of one actor incarnation (see [`open_acks`]).
pub type AckService = publish_subscribe::PortFactory<Ipc, AckWire, ()>;

/// Why shared memory could not be set up or used.
#[derive(Debug, Clone, thiserror::Error)]
pub enum ShmError {
    /// An iceoryx2 call failed; `what` says which step.
    #[error("{what}: {message}")]
    Iceoryx { what: String, message: String },
    /// Not enough room in the shared-memory file system.
    #[error(
        "{what} needs about {needed_mib} MiB of shared memory, but {dir} has {free_mib} MiB free \
         (of {total_mib} MiB). Give it more (docker run --shm-size=1g, compose `shm_size: 1g`, \
         Kubernetes: an emptyDir with `medium: Memory` and a `sizeLimit` mounted at /dev/shm) or \
         {lower}"
    )]
    NoSpace {
        what: &'static str,
        dir: String,
        needed_mib: u64,
        free_mib: u64,
        total_mib: u64,
        /// What to lower instead.
        lower: &'static str,
    },
    /// A namespace announced by the learner that cannot name services.
    #[error("invalid shared-memory namespace `{0}`")]
    BadNamespace(String),
}

impl ShmError {
    /// An [`Iceoryx`](Self::Iceoryx) error: `what` step failed with `error`.
    pub fn iceoryx(what: impl Into<String>, error: impl fmt::Display) -> Self {
        Self::Iceoryx {
            what: what.into(),
            message: error.to_string(),
        }
    }
}

/// The prefix of a run's service names, `hac/<namespace>/`. Made of characters any iceoryx2
/// service name takes, at most [`Namespace::MAX_LEN`] long.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub struct Namespace(String);

impl Namespace {
    /// The longest namespace.
    pub const MAX_LEN: usize = 96;

    /// The namespace of the run with config digest `digest` served at `addr`: unique among the
    /// learners alive on a host (no two listen on one address), the same for a learner restarted
    /// on its address with the same config.
    pub fn for_run(digest: &str, addr: SocketAddr) -> Self {
        let digest: String = digest
            .chars()
            .filter(char::is_ascii_hexdigit)
            .take(16)
            .collect();
        let addr: String = addr
            .to_string()
            .chars()
            .map(|c| if c.is_ascii_alphanumeric() { c } else { '-' })
            .collect();
        Self(format!("{digest}-{}", addr.trim_matches('-')))
    }

    /// A namespace as announced at registration, checked.
    pub fn parse(text: &str) -> Result<Self, ShmError> {
        let ok = !text.is_empty()
            && text.len() <= Self::MAX_LEN
            && text
                .bytes()
                .all(|b| b.is_ascii_alphanumeric() || b == b'-' || b == b'_' || b == b'.');
        if ok {
            Ok(Self(text.to_string()))
        } else {
            Err(ShmError::BadNamespace(text.to_string()))
        }
    }

    /// The namespace without the `hac/` prefix.
    pub fn as_str(&self) -> &str {
        &self.0
    }

    fn service(&self, rest: &str) -> Result<ServiceName, ShmError> {
        let name = format!("hac/{}/{rest}", self.0);
        ServiceName::new(&name).map_err(|e| ShmError::iceoryx(format!("service name `{name}`"), e))
    }

    /// The `ingest` service (messages and their event), actors -> learner.
    pub fn ingest(&self) -> Result<ServiceName, ShmError> {
        self.service("ingest")
    }

    /// The `weights` service (snapshots and their event), learner -> actors.
    pub fn weights(&self) -> Result<ServiceName, ShmError> {
        self.service("weights")
    }

    /// One actor incarnation's acks. Actor ids are free text: a hash stands in for them (the
    /// ack itself carries the incarnation, which the actor checks).
    pub fn acks(&self, actor_id: &str, incarnation: u64) -> Result<ServiceName, ShmError> {
        self.service(&format!("acks/{:016x}-{incarnation}", fnv1a(actor_id)))
    }
}

impl fmt::Display for Namespace {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "hac/{}", self.0)
    }
}

/// 64-bit FNV-1a: stable across builds and processes, unlike std's hasher.
fn fnv1a(text: &str) -> u64 {
    text.bytes().fold(0xcbf2_9ce4_8422_2325, |h, b| {
        (h ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3)
    })
}

/// This host as seen from shared memory: the kernel's boot id and the host name (containers in
/// one pod share both; separate pods and hosts differ). Empty if the boot id is unreadable.
pub fn host_identity() -> String {
    let read = |path: &str| {
        std::fs::read_to_string(path)
            .map(|s| s.trim().to_string())
            .unwrap_or_default()
    };
    let boot = read("/proc/sys/kernel/random/boot_id");
    if boot.is_empty() {
        return String::new();
    }
    format!("{boot}/{}", read("/proc/sys/kernel/hostname"))
}

/// A cumulative acknowledgement from the learner to one actor incarnation.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Ack {
    /// Every message up to this sequence is stored (or was a duplicate of a stored one).
    pub acked_through: u64,
    /// ... and up to this one durable (at most `acked_through`): in the learner's write-ahead
    /// log, so that a learner killed and resumed still has it (without a log, stored). The
    /// actor keeps every message until this covers it.
    pub durable_through: u64,
    /// The newest weights version the learner has published.
    pub weights_version: u64,
    /// Set on a refusal: the message after `acked_through` was refused for this reason, and
    /// nothing more of this incarnation will be read.
    pub refusal: Option<RejectReason>,
    pub incarnation: u64,
}

/// An [`Ack`] in shared memory: `acked_through`, `weights_version`, the refusal's code (0: none,
/// else 1 + its index in [`RejectReason::ALL`]), `incarnation`, `durable_through`.
pub type AckWire = [u64; 5];

impl Ack {
    /// The ack as published to the actor.
    pub fn to_wire(self) -> AckWire {
        let refusal = self.refusal.map_or(0, |r| {
            1 + RejectReason::ALL.iter().position(|&x| x == r).unwrap_or(0) as u64
        });
        [
            self.acked_through,
            self.weights_version,
            refusal,
            self.incarnation,
            self.durable_through,
        ]
    }

    /// An ack as received; `None` for a refusal code this build does not know.
    pub fn from_wire(wire: &AckWire) -> Option<Self> {
        let refusal = match wire[2] {
            0 => None,
            code => Some(*RejectReason::ALL.get(usize::try_from(code - 1).ok()?)?),
        };
        Some(Self {
            acked_through: wire[0],
            weights_version: wire[1],
            refusal,
            incarnation: wire[3],
            durable_through: wire[4],
        })
    }
}

/// A node of this process named `name`: no signal handlers of its own (the daemons handle
/// SIGINT and SIGTERM), iceoryx2's log at warnings and up unless `IOX2_LOG_LEVEL` says otherwise.
pub fn node(name: &str) -> Result<Node, ShmError> {
    static LOG_LEVEL: Once = Once::new();
    LOG_LEVEL.call_once(|| set_log_level_from_env_or(LogLevel::Error));
    let mut builder = NodeBuilder::new().signal_handling_mode(SignalHandlingMode::Disabled);
    let name: String = name.chars().take(100).collect();
    if let Ok(name) = NodeName::new(&name) {
        builder = builder.name(&name);
    }
    builder
        .create::<Ipc>()
        .map_err(|e| ShmError::iceoryx("creating an iceoryx2 node", e))
}

/// Removes what dead nodes (killed processes) left behind; logs what it did.
pub fn cleanup_dead_nodes(node: &Node) {
    let state = node.try_cleanup_dead_nodes();
    if state.cleanups > 0 || state.failed_cleanups > 0 {
        tracing::info!(
            cleaned = state.cleanups,
            failed = state.failed_cleanups,
            "removed the shared memory of dead processes"
        );
    }
}

/// The ack service of one actor incarnation, named by [`Namespace::acks`]; the learner and the
/// actor both open or create it, whichever comes first, with these settings.
pub fn open_acks(node: &Node, name: &ServiceName) -> Result<AckService, ShmError> {
    node.service_builder(name)
        .publish_subscribe::<AckWire>()
        .enable_safe_overflow(true)
        .history_size(1)
        .subscriber_max_buffer_size(4)
        .subscriber_max_borrowed_samples(1)
        .max_publishers(2)
        .max_subscribers(2)
        .max_nodes(4)
        .open_or_create()
        .map_err(|e| ShmError::iceoryx(format!("opening {name}"), e))
}

/// The event beside [`open_acks`]' service ("an ack is waiting"), opened or created the same way.
pub fn open_ack_events(
    node: &Node,
    name: &ServiceName,
) -> Result<event::PortFactory<Ipc>, ShmError> {
    node.service_builder(name)
        .event()
        .max_notifiers(2)
        .max_listeners(2)
        .max_nodes(4)
        .open_or_create()
        .map_err(|e| ShmError::iceoryx(format!("opening the event {name}"), e))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn namespaces_differ_by_run_and_by_address_and_name_valid_services() {
        let digest = "3fa9c1d2e4b5a6f70123456789abcdef";
        let a = Namespace::for_run(digest, "127.0.0.1:50051".parse().unwrap());
        assert_eq!(a.as_str(), "3fa9c1d2e4b5a6f7-127-0-0-1-50051");
        assert_eq!(a.to_string(), "hac/3fa9c1d2e4b5a6f7-127-0-0-1-50051");
        let b = Namespace::for_run(digest, "127.0.0.1:50052".parse().unwrap());
        let c = Namespace::for_run("ffff", "127.0.0.1:50051".parse().unwrap());
        let v6 = Namespace::for_run(digest, "[::1]:7".parse().unwrap());
        assert!(a != b && a != c && b != c);
        for ns in [&a, &b, &c, &v6] {
            assert_eq!(Namespace::parse(ns.as_str()).unwrap(), *ns);
            assert!(ns.ingest().is_ok() && ns.weights().is_ok());
        }
        assert_eq!(
            a.ingest().unwrap().as_str(),
            "hac/3fa9c1d2e4b5a6f7-127-0-0-1-50051/ingest"
        );
        assert_ne!(a.ingest().unwrap(), b.ingest().unwrap());
    }

    #[test]
    fn ack_services_are_per_actor_and_incarnation_whatever_the_id() {
        let ns = Namespace::parse("abc-1").unwrap();
        let names: Vec<String> = [("trainer-0", 1), ("trainer-0", 2), ("trainer-1", 1)]
            .iter()
            .chain(&[("pod/ä ö ü", 1), ("", 1)])
            .map(|&(id, inc)| ns.acks(id, inc).unwrap().as_str().to_string())
            .collect();
        let distinct: std::collections::HashSet<_> = names.iter().collect();
        assert_eq!(distinct.len(), names.len(), "{names:?}");
        assert!(names.iter().all(|n| n.starts_with("hac/abc-1/acks/")));
        assert_eq!(fnv1a(""), 0xcbf2_9ce4_8422_2325);
        assert_eq!(fnv1a("a"), 0xaf63_dc4c_8601_ec8c);
    }

    #[test]
    fn bad_namespaces_are_refused() {
        for bad in ["", "a/b", "a b", "ü", &"x".repeat(Namespace::MAX_LEN + 1)] {
            assert!(Namespace::parse(bad).is_err(), "{bad:?}");
        }
    }

    #[test]
    fn acks_round_trip_with_every_refusal() {
        let plain = Ack {
            acked_through: 17,
            durable_through: 11,
            weights_version: 4,
            refusal: None,
            incarnation: 2,
        };
        assert_eq!(plain.to_wire(), [17, 4, 0, 2, 11]);
        assert_eq!(Ack::from_wire(&plain.to_wire()), Some(plain));
        // Every field has a place of its own: none is lost or swapped on the way.
        let wide = Ack {
            acked_through: u64::MAX - 1,
            durable_through: u64::MAX - 2,
            weights_version: u64::MAX - 3,
            refusal: Some(RejectReason::SequenceGap),
            incarnation: u64::MAX,
        };
        assert_eq!(Ack::from_wire(&wide.to_wire()), Some(wide));
        for reason in RejectReason::ALL {
            let ack = Ack {
                refusal: Some(reason),
                ..plain
            };
            assert_eq!(Ack::from_wire(&ack.to_wire()), Some(ack));
        }
        assert_eq!(Ack::from_wire(&[1, 1, 999, 1, 1]), None);
    }

    #[test]
    fn the_host_identity_has_a_boot_id_and_a_host_name() {
        let id = host_identity();
        // Linux always has a boot id; the identity is stable within a boot.
        let (boot, _host) = id.split_once('/').expect("boot id / host name");
        assert_eq!(boot.len(), 36, "{id}");
        assert_eq!(id, host_identity());
    }
}
