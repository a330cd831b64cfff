//! [`Published`]: the latest value of something that changes (the weights), readable without
//! waiting, awaitable from threads (condition variable) and from async tasks (a `watch` channel).

use std::sync::Arc;
use std::time::Duration;

use parking_lot::{Condvar, Mutex};
use tokio::sync::watch;

/// A cell holding the latest published `T` (shared as `Arc<T>`). Publishing replaces the value
/// and wakes every waiter; readers never block publishers for longer than an `Arc` clone.
#[derive(Debug)]
pub struct Published<T> {
    latest: Mutex<Option<Arc<T>>>,
    changed: Condvar,
    watch: watch::Sender<Option<Arc<T>>>,
}

impl<T> Default for Published<T> {
    fn default() -> Self {
        Self {
            latest: Mutex::new(None),
            changed: Condvar::new(),
            watch: watch::Sender::new(None),
        }
    }
}

impl<T> Published<T> {
    /// Replaces the value and wakes every waiter.
    pub fn publish(&self, value: Arc<T>) {
        *self.latest.lock() = Some(value.clone());
        self.changed.notify_all();
        self.watch.send_replace(Some(value));
    }

    /// The latest value, if anything was published yet.
    pub fn latest(&self) -> Option<Arc<T>> {
        self.latest.lock().clone()
    }

    /// Blocks until the latest value satisfies `ready` (checked at once, then after every
    /// publication) or `timeout` passes; returns the value that satisfied it.
    pub fn wait_for(&self, timeout: Duration, mut ready: impl FnMut(&T) -> bool) -> Option<Arc<T>> {
        let mut latest = self.latest.lock();
        let satisfied = |v: &Option<Arc<T>>, ready: &mut dyn FnMut(&T) -> bool| {
            v.as_deref().is_some_and(&mut *ready)
        };
        if !satisfied(&latest, &mut ready) {
            self.changed
                .wait_while_for(&mut latest, |v| !satisfied(v, &mut ready), timeout);
        }
        latest.clone().filter(|v| ready(v))
    }

    /// An async receiver of every publication (it sees the latest value at once, then each new
    /// one; values published faster than it reads are skipped, never queued).
    pub fn subscribe(&self) -> watch::Receiver<Option<Arc<T>>> {
        self.watch.subscribe()
    }
}

#[cfg(test)]
mod tests {
    use std::time::Instant;

    use super::*;

    #[test]
    fn waiters_wake_on_the_publication_that_satisfies_them() {
        let cell = Arc::new(Published::<u64>::default());
        assert!(cell.latest().is_none());
        let publisher = {
            let cell = cell.clone();
            std::thread::spawn(move || {
                for v in 1..=5 {
                    std::thread::sleep(Duration::from_millis(2));
                    cell.publish(Arc::new(v));
                }
            })
        };
        let got = cell.wait_for(Duration::from_secs(10), |&v| v >= 3);
        assert!(got.is_some_and(|v| *v >= 3));
        publisher.join().expect("publisher");
        assert_eq!(cell.latest().as_deref(), Some(&5));
    }

    #[test]
    fn wait_times_out_with_none() {
        let cell = Published::<u64>::default();
        cell.publish(Arc::new(1));
        let t0 = Instant::now();
        assert!(
            cell.wait_for(Duration::from_millis(20), |&v| v > 1)
                .is_none()
        );
        assert!(t0.elapsed() >= Duration::from_millis(20));
    }
}
