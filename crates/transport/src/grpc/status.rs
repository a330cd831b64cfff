//! The `hac.v1.Status` service: [`StatusGrpc`] serves whatever a [`StatusSource`] says (the
//! learner, through `hac-serve`, or an actor daemon's [`ActorNodeStatus`]), once or as a stream.
//!
//! A request costs one snapshot: the learner's takes its locks one at a time, briefly, and none
//! is held across an await. Watch streams send a snapshot at once and then every interval the
//! client asked for (bounded below, so a careless client cannot make the server spin), until
//! the client hangs up or the server closes.

use std::fmt;
use std::sync::Arc;
use std::time::Duration;

use hac_proto::{ActorRole, pb};
use tokio::sync::{mpsc, watch};
use tokio_stream::wrappers::ReceiverStream;
use tonic::{Request, Response, Status};

use super::until_set;

/// Shortest interval between the snapshots of a status watch.
pub const MIN_WATCH_INTERVAL: Duration = Duration::from_millis(100);
/// Longest interval between the snapshots of a status watch.
pub const MAX_WATCH_INTERVAL: Duration = Duration::from_secs(3600);
/// The interval of a watch that asks for 0.
pub const DEFAULT_WATCH_INTERVAL: Duration = Duration::from_secs(1);

/// Something that can say how it is doing: the learner, an actor daemon.
pub trait StatusSource: Send + Sync + 'static {
    /// A snapshot now. `max_evaluations`: the learner's most recent evaluations to include
    /// (0: all of them).
    fn node_status(&self, max_evaluations: usize) -> pb::NodeStatus;
}

/// "trainer" or "evaluator".
pub fn role_name(role: ActorRole) -> &'static str {
    match role {
        ActorRole::Trainer => "trainer",
        ActorRole::Evaluator => "evaluator",
    }
}

/// An actor daemon's view of itself (`hac.v1.ActorStatus`; the fields are documented there).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ActorNodeStatus {
    pub actor_id: String,
    pub role: &'static str,
    pub hostname: String,
    /// "connecting", "running" or "stopping".
    pub state: &'static str,
    pub learner: String,
    pub transport: &'static str,
    pub incarnation: u64,
    pub uptime: Duration,
    pub episodes: u64,
    pub successes: u64,
    pub env_steps: u64,
    pub env_steps_per_s: f64,
    pub rates_window: Duration,
    pub evaluations: u64,
    pub weights_version: u64,
    pub learner_weights_version: u64,
    pub unacked: u64,
    pub reconnects: u64,
    pub undurable: u64,
    pub sent_transitions: u64,
    pub durable_transitions: u64,
}

impl From<&ActorNodeStatus> for pb::ActorStatus {
    fn from(s: &ActorNodeStatus) -> Self {
        Self {
            actor_id: s.actor_id.clone(),
            role: s.role.into(),
            hostname: s.hostname.clone(),
            state: s.state.into(),
            learner: s.learner.clone(),
            transport: s.transport.into(),
            incarnation: s.incarnation,
            uptime_seconds: s.uptime.as_secs_f64(),
            episodes: s.episodes,
            successes: s.successes,
            env_steps: s.env_steps,
            env_steps_per_second: s.env_steps_per_s,
            rates_window_seconds: s.rates_window.as_secs_f64(),
            evaluations: s.evaluations,
            weights_version: s.weights_version,
            learner_weights_version: s.learner_weights_version,
            weights_lag: s.learner_weights_version.saturating_sub(s.weights_version),
            unacked: s.unacked,
            reconnects: s.reconnects,
            undurable: s.undurable,
            sent_transitions: s.sent_transitions,
            durable_transitions: s.durable_transitions,
        }
    }
}

impl From<&ActorNodeStatus> for pb::NodeStatus {
    fn from(s: &ActorNodeStatus) -> Self {
        Self {
            node: Some(pb::node_status::Node::Actor(s.into())),
        }
    }
}

/// The `hac.v1.Status` service over a [`StatusSource`]. Cheap to clone.
#[derive(Clone)]
pub struct StatusGrpc {
    source: Arc<dyn StatusSource>,
    /// Set when the server shuts down: watch streams end.
    closing: watch::Receiver<bool>,
}

impl fmt::Debug for StatusGrpc {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("StatusGrpc").finish_non_exhaustive()
    }
}

impl StatusGrpc {
    /// Serves `source`; watch streams end once `closing` is set.
    pub fn new(source: Arc<dyn StatusSource>, closing: watch::Receiver<bool>) -> Self {
        Self { source, closing }
    }

    pub fn into_service(self) -> pb::status_server::StatusServer<Self> {
        pb::status_server::StatusServer::new(self)
    }
}

/// The interval a watch asks for, bounded to `MIN_WATCH_INTERVAL..=MAX_WATCH_INTERVAL`.
fn watch_interval(interval_ms: u32) -> Duration {
    if interval_ms == 0 {
        return DEFAULT_WATCH_INTERVAL;
    }
    Duration::from_millis(u64::from(interval_ms)).clamp(MIN_WATCH_INTERVAL, MAX_WATCH_INTERVAL)
}

/// Snapshots queued per status watcher before the server waits for the client to read.
const WATCH_QUEUE: usize = 2;

#[tonic::async_trait]
impl pb::status_server::Status for StatusGrpc {
    async fn get_status(
        &self,
        request: Request<pb::GetStatusRequest>,
    ) -> Result<Response<pb::NodeStatus>, Status> {
        let max = request.into_inner().max_evaluations as usize;
        Ok(Response::new(self.source.node_status(max)))
    }

    type WatchStatusStream = ReceiverStream<Result<pb::NodeStatus, Status>>;

    async fn watch_status(
        &self,
        request: Request<pb::WatchStatusRequest>,
    ) -> Result<Response<Self::WatchStatusStream>, Status> {
        let request = request.into_inner();
        let interval = watch_interval(request.interval_ms);
        let max = request.max_evaluations as usize;
        let (tx, rx) = mpsc::channel(WATCH_QUEUE);
        let source = self.source.clone();
        let mut closing = self.closing.clone();
        tokio::spawn(async move {
            let mut tick = tokio::time::interval(interval);
            tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
            loop {
                tokio::select! {
                    biased;
                    () = until_set(&mut closing) => return,
                    () = tx.closed() => return,
                    _ = tick.tick() => {}
                }
                let snapshot = source.node_status(max);
                tokio::select! {
                    biased;
                    () = until_set(&mut closing) => return,
                    sent = tx.send(Ok(snapshot)) => if sent.is_err() { return },
                }
            }
        });
        Ok(Response::new(ReceiverStream::new(rx)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn watch_intervals_are_bounded() {
        assert_eq!(watch_interval(0), DEFAULT_WATCH_INTERVAL);
        assert_eq!(watch_interval(1), MIN_WATCH_INTERVAL);
        assert_eq!(watch_interval(250), Duration::from_millis(250));
        assert_eq!(watch_interval(u32::MAX), MAX_WATCH_INTERVAL);
    }

    #[test]
    fn an_actor_status_reports_its_weights_lag() {
        let status = ActorNodeStatus {
            actor_id: "a".into(),
            role: "trainer",
            weights_version: 7,
            learner_weights_version: 10,
            ..ActorNodeStatus::default()
        };
        let pb::NodeStatus {
            node: Some(pb::node_status::Node::Actor(actor)),
        } = pb::NodeStatus::from(&status)
        else {
            panic!("an actor status")
        };
        assert_eq!(actor.weights_lag, 3);
        assert_eq!(actor.role, "trainer");
    }
}
