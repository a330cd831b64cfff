//! [`WeightsReceiver`]: an actor's subscription to the learner's weights over shared memory.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::thread::JoinHandle;
use std::time::Duration;

use hac_proto::Published;
use hac_proto::{WeightsSnapshot, unpack_weights};

use super::{Namespace, ShmError, node};

/// How long the thread sleeps between looks when no event wakes it: the bound on noticing a
/// snapshot delivered without an event (the history a late joiner gets), and on stopping.
const POLL: Duration = Duration::from_millis(50);

/// A thread that subscribes to `hac/<namespace>/weights` and publishes every snapshot it receives
/// into a [`Published`] cell (the newest only, when several wait). Late joiners get the latest
/// snapshot from the service's history. Stops when dropped.
#[derive(Debug)]
pub struct WeightsReceiver {
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<()>>,
}

impl WeightsReceiver {
    /// Subscribes (the learner must serve `namespace`) and starts the thread. `learner_version`
    /// is lowered when versions start again (a restarted learner), as the gRPC link does.
    pub fn start(
        namespace: &Namespace,
        into: Arc<Published<WeightsSnapshot>>,
        learner_version: Arc<AtomicU64>,
    ) -> Result<Self, ShmError> {
        let node = node("hac-weights")?;
        let name = namespace.weights()?;
        let service = node
            .service_builder(&name)
            .publish_subscribe::<[u8]>()
            .open()
            .map_err(|e| ShmError::iceoryx(format!("opening {name}"), e))?;
        let subscriber = service
            .subscriber_builder()
            .create()
            .map_err(|e| ShmError::iceoryx(format!("subscribing to {name}"), e))?;
        let events = node
            .service_builder(&name)
            .event()
            .open()
            .map_err(|e| ShmError::iceoryx(format!("opening the event {name}"), e))?;
        let listener = events
            .listener_builder()
            .create()
            .map_err(|e| ShmError::iceoryx(format!("listening to {name}"), e))?;
        let stop = Arc::new(AtomicBool::new(false));
        let thread = {
            let stop = stop.clone();
            std::thread::Builder::new()
                .name("hac-shm-weights".into())
                .spawn(move || {
                    // The node and service live as long as their ports.
                    let _keep = (node, service, events);
                    while !stop.load(Ordering::Relaxed) {
                        // Each sample is unpacked and released before the next is received:
                        // the service lets a subscriber borrow one sample at a time, and
                        // holding the newest while receiving the one after it failed with
                        // ExceedsMaxBorrows whenever two snapshots were waiting.
                        let mut newest = None;
                        loop {
                            match subscriber.receive() {
                                Ok(Some(sample)) => match unpack_weights(sample.payload()) {
                                    Ok(snapshot) => newest = Some(snapshot),
                                    Err(e) => tracing::warn!(
                                        error = %e,
                                        "invalid weights from the learner"
                                    ),
                                },
                                Ok(None) => break,
                                Err(e) => {
                                    tracing::warn!(error = %e, "receiving weights");
                                    break;
                                }
                            }
                        }
                        if let Some(snapshot) = newest {
                            deliver(snapshot, &into, &learner_version);
                        }
                        if let Err(e) = listener.timed_wait(|_| {}, POLL) {
                            tracing::warn!(error = %e, "waiting for weights");
                            std::thread::sleep(POLL);
                        }
                    }
                })
                .map_err(|e| ShmError::iceoryx("starting the weights thread", e))?
        };
        Ok(Self {
            stop,
            thread: Some(thread),
        })
    }
}

fn deliver(snapshot: WeightsSnapshot, into: &Published<WeightsSnapshot>, version: &AtomicU64) {
    let previous = into.latest().map_or(0, |w| w.version);
    if snapshot.version < previous {
        tracing::info!(
            version = snapshot.version,
            previous,
            "weights versions start again: the learner restarted"
        );
        version.store(snapshot.version, Ordering::Relaxed);
    } else {
        version.fetch_max(snapshot.version, Ordering::Relaxed);
    }
    into.publish(Arc::new(snapshot));
}

impl Drop for WeightsReceiver {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}
