//! [`RefusalLog`]: warnings about refused input, rate limited, shared by the learner's gRPC and
//! shared-memory servers (in `hac-serve`) and the token check of every server. A broken or hostile client can be refused thousands of times a second,
//! and a line per refusal would drown the log and cost more than the refusal itself. So the first
//! refusal of each (reason, actor) pair in an interval is logged in full, later ones are only
//! counted, and when an interval in which some were not logged ends, one summary line gives its
//! counts by reason and actor. Every line names the actor, cut by [`Clipped`].

use std::fmt::{self, Write as _};
use std::time::{Duration, Instant};

use hac_proto::Clipped;
use hac_proto::RejectReason;
use parking_lot::Mutex;

/// How often the counts of refusals not logged are summarized.
pub const SUMMARY_INTERVAL: Duration = Duration::from_secs(10);
/// Distinct (reason, actor) pairs tracked per interval; refusals of further pairs are logged
/// only in the summary, by reason (a client inventing ids must not grow this without bound).
const MAX_PAIRS: usize = 32;
/// How an input with no readable actor id (bytes that do not decode) is named.
const NO_ACTOR: &str = "(unknown)";

/// Rate-limited refusal warnings; see the module docs.
#[derive(Debug)]
pub struct RefusalLog {
    interval: Duration,
    state: Mutex<Interval>,
}

#[derive(Debug)]
struct Interval {
    started: Instant,
    pairs: Vec<Pair>,
    /// Refusals of pairs beyond [`MAX_PAIRS`], by reason.
    others: Vec<(RejectReason, u64)>,
    /// Refusals counted but not logged in full.
    suppressed: u64,
}

/// Refusals of one reason and actor in the interval. The actor is kept as its clipped head and
/// its length: what is shown, without copying an id of any length.
#[derive(Debug)]
struct Pair {
    reason: RejectReason,
    head: String,
    len: usize,
    count: u64,
}

/// The counts of an interval in which some refusals were not logged.
#[derive(Debug, PartialEq)]
pub(crate) struct Summary {
    pub seconds: u64,
    pub refusals: u64,
    pub suppressed: u64,
    /// `reason actor: count` pairs, then `reason (other actors): count`, comma-separated.
    pub counts: String,
}

impl RefusalLog {
    /// A log that summarizes every `interval` (servers use [`SUMMARY_INTERVAL`]).
    pub fn new(interval: Duration) -> Self {
        Self {
            interval,
            state: Mutex::new(Interval::new(Instant::now())),
        }
    }

    /// Reports a refusal of `actor`'s input ("" when there is no readable id) under `reason`:
    /// a warning if it is the first of its pair in this interval, else only counted. `what`
    /// names the input (`ingest message`, `registration`, ...). `finished` is the normal end
    /// of a run, not a warning.
    pub fn refused(
        &self,
        what: &'static str,
        reason: RejectReason,
        actor: &str,
        error: &dyn fmt::Display,
    ) {
        let actor = if actor.is_empty() { NO_ACTOR } else { actor };
        let reason_name = reason.name();
        if reason == RejectReason::Finished {
            tracing::debug!(what, actor = %Clipped(actor), reason = reason_name, %error, "input refused");
            return;
        }
        let (first, summary) = self.note(Instant::now(), reason, actor);
        if let Some(summary) = summary {
            summary.log();
        }
        if first {
            tracing::warn!(what, actor = %Clipped(actor), reason = reason_name, %error, "input refused");
        }
    }

    /// Logs the summary of the interval if it has ended: servers call this now and then, so
    /// that the end of a burst is reported without waiting for the next refusal.
    pub fn flush(&self) {
        if let Some(summary) = self.take_summary(Instant::now()) {
            summary.log();
        }
    }

    /// Counts a refusal at `now`: whether to log it in full, and the summary of the interval
    /// that ended before it, if that one has something to report.
    fn note(&self, now: Instant, reason: RejectReason, actor: &str) -> (bool, Option<Summary>) {
        let mut state = self.state.lock();
        let summary = state.roll(now, self.interval);
        let clipped = Clipped(actor);
        let head = clipped.head();
        let known = state
            .pairs
            .iter()
            .position(|p| p.reason == reason && p.len == actor.len() && p.head == head);
        let first = match known {
            Some(index) => {
                state.pairs[index].count += 1;
                false
            }
            None if state.pairs.len() < MAX_PAIRS => {
                state.pairs.push(Pair {
                    reason,
                    head: head.to_string(),
                    len: actor.len(),
                    count: 1,
                });
                true
            }
            None => {
                match state.others.iter_mut().find(|(r, _)| *r == reason) {
                    Some((_, count)) => *count += 1,
                    None => state.others.push((reason, 1)),
                }
                false
            }
        };
        if !first {
            state.suppressed += 1;
        }
        (first, summary)
    }

    /// The summary of the interval if it ended by `now` (and starts the next one).
    fn take_summary(&self, now: Instant) -> Option<Summary> {
        self.state.lock().roll(now, self.interval)
    }
}

impl Interval {
    fn new(started: Instant) -> Self {
        Self {
            started,
            pairs: Vec::new(),
            others: Vec::new(),
            suppressed: 0,
        }
    }

    /// Starts a new interval if this one ended by `now`; the ended one's summary if some of its
    /// refusals were not logged (otherwise every one already was).
    fn roll(&mut self, now: Instant, interval: Duration) -> Option<Summary> {
        let elapsed = now.saturating_duration_since(self.started);
        if elapsed < interval {
            return None;
        }
        let ended = std::mem::replace(self, Self::new(now));
        (ended.suppressed > 0).then(|| ended.summary(elapsed))
    }

    fn summary(&self, elapsed: Duration) -> Summary {
        let mut counts = String::new();
        let mut refusals = 0;
        for pair in &self.pairs {
            let sep = if counts.is_empty() { "" } else { ", " };
            let _ = write!(counts, "{sep}{} {}", pair.reason.name(), pair.head);
            if pair.len > pair.head.len() {
                let _ = write!(counts, "... ({} bytes)", pair.len);
            }
            let _ = write!(counts, ": {}", pair.count);
            refusals += pair.count;
        }
        for (reason, count) in &self.others {
            let sep = if counts.is_empty() { "" } else { ", " };
            let _ = write!(counts, "{sep}{} (other actors): {count}", reason.name());
            refusals += count;
        }
        Summary {
            seconds: elapsed.as_secs(),
            refusals,
            suppressed: self.suppressed,
            counts,
        }
    }
}

impl Summary {
    fn log(&self) {
        tracing::warn!(
            seconds = self.seconds,
            refusals = self.refusals,
            not_logged = self.suppressed,
            counts = %self.counts,
            "refusals in the last interval"
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_first_refusal_per_reason_and_actor_is_logged_then_one_summary_per_interval() {
        let log = RefusalLog::new(Duration::from_secs(10));
        let t0 = log.state.lock().started;
        let at = |secs: u64| t0 + Duration::from_secs(secs);
        let long = "x".repeat(1 << 20);

        assert_eq!(log.note(at(1), RejectReason::NotFinite, "a"), (true, None));
        for _ in 0..99 {
            assert_eq!(log.note(at(2), RejectReason::NotFinite, "a"), (false, None));
        }
        // Another actor, another reason: each pair's first is logged.
        assert_eq!(log.note(at(3), RejectReason::NotFinite, "b"), (true, None));
        assert_eq!(
            log.note(at(3), RejectReason::InvalidBatch, "a"),
            (true, None)
        );
        assert_eq!(
            log.note(at(4), RejectReason::InvalidBatch, &long),
            (true, None)
        );
        assert_eq!(
            log.note(at(4), RejectReason::InvalidBatch, &long),
            (false, None)
        );
        // Nothing to summarize before the interval ends.
        assert_eq!(log.take_summary(at(9)), None);

        // The first refusal after the interval is logged, and brings the summary.
        let (first, summary) = log.note(at(11), RejectReason::NotFinite, "a");
        assert!(first);
        assert_eq!(
            summary,
            Some(Summary {
                seconds: 11,
                refusals: 104,
                suppressed: 100,
                counts: format!(
                    "not_finite a: 100, not_finite b: 1, invalid_batch a: 1, invalid_batch {}... \
                     (1048576 bytes): 2",
                    "x".repeat(64)
                ),
            })
        );
        // An interval whose every refusal was logged needs no summary.
        assert_eq!(log.take_summary(at(30)), None);
    }

    #[test]
    fn pairs_beyond_the_limit_are_counted_by_reason() {
        let log = RefusalLog::new(Duration::from_secs(10));
        let t0 = log.state.lock().started;
        for i in 0..MAX_PAIRS + 5 {
            let (first, _) = log.note(t0, RejectReason::UnknownActor, &format!("ghost-{i}"));
            assert_eq!(first, i < MAX_PAIRS, "{i}");
        }
        let summary = log
            .take_summary(t0 + Duration::from_secs(10))
            .expect("refusals were not logged");
        assert_eq!((summary.refusals, summary.suppressed), (37, 5));
        assert!(
            summary.counts.ends_with("unknown_actor (other actors): 5"),
            "{}",
            summary.counts
        );
        assert_eq!(
            log.state.lock().pairs.len(),
            0,
            "a new interval starts empty"
        );
    }
}
