//! The reference schedule (docs/ALGORITHM.md, "The schedule"), written once for any learner:
//! blocks of `exploration_episodes` training episodes, each followed by a round of `test_episodes`
//! greedy test episodes whose success rate is one point of the learning curve.

use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use hac_agent::{LevelReport, RoundReport};

/// What the schedule needs from a learner. Training is split in two so that rollout speed and
/// update speed are reported separately, as the embedded neural trainer does.
pub trait Learner {
    /// Runs one training episode (behaviour policy, transitions kept); returns the primitive
    /// actions it took.
    fn rollout(&mut self) -> usize;
    /// Learns from the episode [`Learner::rollout`] just ran.
    fn learn(&mut self);
    /// Runs `episodes` greedy test episodes (learning nothing); returns the success rate.
    fn test(&mut self, episodes: usize) -> f32;
    /// Each level's statistics so far.
    fn level_reports(&self) -> Vec<LevelReport>;
}

/// How long to train and how often to test.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Schedule {
    /// Training episodes in total.
    pub episodes: u64,
    /// Training episodes between test rounds.
    pub exploration_episodes: usize,
    /// Greedy episodes per test round.
    pub test_episodes: usize,
    /// Stop after the first test round at or above this success rate.
    pub stop_at: Option<f32>,
}

/// The result of [`run`].
#[derive(Debug, Clone, PartialEq)]
pub struct Trained {
    /// One report per test round.
    pub curve: Vec<RoundReport>,
    /// Training episodes run (more than the last round's count after an interrupt).
    pub episodes: u64,
}

/// Runs `schedule`, calling `on_round` after every test round. Setting `interrupt` ends the run
/// before the next training episode, without a final test round; the learner keeps what it
/// learned.
pub fn run(
    learner: &mut impl Learner,
    schedule: &Schedule,
    interrupt: &AtomicBool,
    mut on_round: impl FnMut(&RoundReport),
) -> Trained {
    let started = Instant::now();
    let (mut episodes, mut env_steps) = (0u64, 0u64);
    let (mut rollout_time, mut update_time) = (Duration::ZERO, Duration::ZERO);
    let (mut last_steps, mut last_updates) = (0u64, 0u64);
    let (mut last_rollout, mut last_update) = (Duration::ZERO, Duration::ZERO);
    let mut curve = Vec::new();
    let block_len = schedule.exploration_episodes.max(1) as u64;
    while episodes < schedule.episodes {
        for _ in 0..block_len.min(schedule.episodes - episodes) {
            if interrupt.load(Ordering::Relaxed) {
                return Trained { curve, episodes };
            }
            let t0 = Instant::now();
            env_steps += learner.rollout() as u64;
            let t1 = Instant::now();
            learner.learn();
            rollout_time += t1 - t0;
            update_time += t1.elapsed();
            episodes += 1;
        }
        let success_rate = learner.test(schedule.test_episodes);
        let levels = learner.level_reports();
        let updates: u64 = levels.iter().map(|l| l.updates).sum();
        let report = RoundReport {
            round: curve.len() + 1,
            episodes,
            env_steps,
            success_rate,
            elapsed_s: started.elapsed().as_secs_f64(),
            env_steps_per_s: per_second(env_steps - last_steps, rollout_time - last_rollout),
            updates_per_s: per_second(updates - last_updates, update_time - last_update),
            levels,
        };
        (last_steps, last_updates) = (env_steps, updates);
        (last_rollout, last_update) = (rollout_time, update_time);
        on_round(&report);
        let done = schedule
            .stop_at
            .is_some_and(|target| report.success_rate >= target);
        curve.push(report);
        if done {
            break;
        }
    }
    Trained { curve, episodes }
}

fn per_second(n: u64, time: Duration) -> f64 {
    let s = time.as_secs_f64();
    if s > 0.0 { n as f64 / s } else { 0.0 }
}

/// The progress line `hac train` prints per test round.
pub fn progress_line(report: &RoundReport) -> String {
    format!(
        "round {:>3} | episodes {:>5} | success {:>5.1}% | env steps/s {:>9.0} | updates/s {:>7.0} | elapsed {:>7.1}s",
        report.round,
        report.episodes,
        100.0 * report.success_rate,
        report.env_steps_per_s,
        report.updates_per_s,
        report.elapsed_s
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Succeeds in test rounds with a scripted rate; counts what the schedule asks of it.
    #[derive(Default)]
    struct Scripted {
        rates: Vec<f32>,
        rollouts: u64,
        learns: u64,
        tests: Vec<usize>,
        interrupt_after: Option<(u64, &'static AtomicBool)>,
    }

    impl Learner for Scripted {
        fn rollout(&mut self) -> usize {
            self.rollouts += 1;
            if let Some((n, flag)) = self.interrupt_after
                && self.rollouts == n
            {
                flag.store(true, Ordering::Relaxed);
            }
            7
        }
        fn learn(&mut self) {
            self.learns += 1;
        }
        fn test(&mut self, episodes: usize) -> f32 {
            self.tests.push(episodes);
            self.rates.get(self.tests.len() - 1).copied().unwrap_or(0.0)
        }
        fn level_reports(&self) -> Vec<LevelReport> {
            vec![LevelReport {
                updates: self.learns * 3,
                ..LevelReport::default()
            }]
        }
    }

    fn schedule(episodes: u64, stop_at: Option<f32>) -> Schedule {
        Schedule {
            episodes,
            exploration_episodes: 4,
            test_episodes: 9,
            stop_at,
        }
    }

    #[test]
    fn blocks_of_training_then_a_test_round_with_a_short_last_block() {
        let mut l = Scripted::default();
        let t = run(&mut l, &schedule(10, None), &AtomicBool::new(false), |_| {});
        assert_eq!((l.rollouts, l.learns, t.episodes), (10, 10, 10));
        assert_eq!(l.tests, [9, 9, 9]);
        let points: Vec<(usize, u64, u64)> = t
            .curve
            .iter()
            .map(|r| (r.round, r.episodes, r.env_steps))
            .collect();
        assert_eq!(points, [(1, 4, 28), (2, 8, 56), (3, 10, 70)]);
        assert_eq!(t.curve[2].levels[0].updates, 30);
    }

    #[test]
    fn stops_at_the_first_round_reaching_the_target() {
        let mut l = Scripted {
            rates: vec![0.2, 0.95, 1.0],
            ..Scripted::default()
        };
        let mut seen = 0;
        let t = run(
            &mut l,
            &schedule(100, Some(0.9)),
            &AtomicBool::new(false),
            |_| seen += 1,
        );
        assert_eq!((t.curve.len(), seen, t.episodes), (2, 2, 8));
    }

    #[test]
    fn an_interrupt_ends_between_episodes_without_a_test_round() {
        static FLAG: AtomicBool = AtomicBool::new(false);
        let mut l = Scripted {
            interrupt_after: Some((6, &FLAG)),
            ..Scripted::default()
        };
        let t = run(&mut l, &schedule(100, None), &FLAG, |_| {});
        assert_eq!((t.episodes, l.learns, t.curve.len()), (6, 6, 1));
    }
}
