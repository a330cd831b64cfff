//! [`Episodes`]: the episode runner of a run's algorithm, HAC's hierarchy or HIRO's two levels,
//! behind one call.

use crate::hiro::{HiroConfig, HiroRollout};
use crate::rollout::{EpisodeOutcome, Exploration, Hierarchy, LevelCounts, Policy};
use crate::{AgentConfig, Env, EnvSpec, Mode, Rng, TransitionSink, within_goal};

/// Runs episodes of the run's algorithm; owns every buffer an episode needs.
// One per actor, made once and never moved while it runs: the variants' sizes do not matter.
#[allow(clippy::large_enum_variant)]
#[derive(Debug)]
pub enum Episodes {
    /// HAC (Levy et al., 2019): Algorithm 1 through every level.
    Hac(Hierarchy),
    /// HIRO (Nachum et al., 2018): its two levels, the high level's steps packed into its
    /// transitions' [`crate::Transition::extra`].
    Hiro(HiroRollout),
}

impl Episodes {
    /// HIRO's rollout when `hiro` is given, else HAC's hierarchy for `config`.
    pub fn new(spec: &EnvSpec, config: &AgentConfig, hiro: Option<&HiroConfig>) -> Self {
        match hiro {
            None => Self::Hac(Hierarchy::new(spec, config)),
            Some(h) => Self::Hiro(HiroRollout::new(spec, h.c).with_task_reward(h.task_reward)),
        }
    }

    /// Resets `env`, draws an end goal for `mode` and plays one episode; in `Mode::Train`
    /// every transition goes to `sink`, tagged with its level.
    pub fn run_episode(
        &mut self,
        env: &mut dyn Env,
        policy: &mut dyn Policy,
        exploration: &mut dyn Exploration,
        mode: Mode,
        rng: &mut Rng,
        sink: &mut dyn TransitionSink,
    ) -> EpisodeOutcome {
        match self {
            Self::Hac(h) => h.run_episode(env, policy, exploration, mode, rng, sink),
            Self::Hiro(h) => h.run_episode_packed(env, policy, exploration, mode, rng, sink),
        }
    }

    /// The end goal of the current (or last) episode.
    pub fn end_goal(&self) -> &[f32] {
        match self {
            Self::Hac(h) => h.end_goal(),
            Self::Hiro(h) => h.end_goal(),
        }
    }

    /// The end-goal projection of the current (or last) episode's first state.
    pub fn start_achieved(&self) -> &[f32] {
        match self {
            Self::Hac(h) => h.start_achieved(),
            Self::Hiro(h) => h.start_achieved(),
        }
    }

    /// The end-goal projection of the current (or last) episode's last state.
    pub fn final_achieved(&self) -> &[f32] {
        match self {
            Self::Hac(h) => h.final_achieved(),
            Self::Hiro(h) => h.final_achieved(),
        }
    }

    /// Whether the current (or last) episode moved what the end goal measures by more than the
    /// end goal's thresholds (on some dimension, angles along the circle where the environment
    /// says so): for pick-and-place, whether the block ended more than 3 cm from where it
    /// started. Hindsight end goals differ from the start only in such episodes.
    pub fn moved_end_goal(&self) -> bool {
        let spec = match self {
            Self::Hac(h) => h.spec(),
            Self::Hiro(h) => h.spec(),
        };
        let (threshold, angles) = spec.goal_test(true);
        !within_goal(
            self.final_achieved(),
            self.start_achieved(),
            threshold,
            angles,
        )
    }

    /// Adds what each level did in the current (or last) episode to `totals` (one entry per
    /// level). HAC only: HIRO's levels are not given goals to reach in HAC's sense, so its
    /// episodes add nothing.
    pub fn add_level_counts(&self, totals: &mut [LevelCounts]) {
        if let Self::Hac(h) = self {
            for (level, total) in totals.iter_mut().enumerate().take(h.num_levels()) {
                total.add(h.level_counts(level));
            }
        }
    }
}
