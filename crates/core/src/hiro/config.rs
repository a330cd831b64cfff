//! HIRO's settings, and which of the run's shared settings it reads.

use std::fmt;
use std::str::FromStr;

use serde::{Deserialize, Serialize};

use crate::{AgentConfig, ConfigError, Noise};

/// The algorithm a run trains: HAC (the default) or HIRO, the HAC paper's baseline.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Algo {
    /// Hierarchical Actor-Critic (Levy et al., 2019): any number of levels.
    #[default]
    Hac,
    /// HIRO (Nachum et al., 2018): exactly 2 levels, TD3 at both.
    Hiro,
}

impl Algo {
    /// Every algorithm, as named on the command line.
    pub const ALL: [Algo; 2] = [Algo::Hac, Algo::Hiro];

    pub fn name(self) -> &'static str {
        match self {
            Algo::Hac => "hac",
            Algo::Hiro => "hiro",
        }
    }

    pub fn is_hac(&self) -> bool {
        *self == Algo::Hac
    }
}

impl fmt::Display for Algo {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for Algo {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        Self::ALL
            .into_iter()
            .find(|a| a.name() == s)
            .ok_or_else(|| format!("unknown algorithm `{s}` (known: hac, hiro)"))
    }
}

/// HIRO's own settings (`[hiro]` in a run config). What it shares with HAC comes from
/// `[agent]`: the hidden layers, gamma, learning rates, batch size, the target networks' rate
/// (`target_tau`), the exploration noise of each level (`action_noise`, `subgoal_noise`), the
/// replay capacity and the test schedule. [`HiroConfig::agent_defaults`] sets those to HIRO's
/// reference values; HAC's own keys (horizon, subgoal testing, hindsight goals, random
/// actions) and `updates_per_episode` (HIRO's is [`HiroConfig::updates_per_step`]) are not read.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HiroConfig {
    /// c: primitive steps between the high level's decisions.
    pub c: usize,
    /// Gaussian candidates the off-policy correction draws beside the stored goal and the
    /// achieved displacement (HIRO: 8, so 10 in all); 0 turns the correction off (the stored
    /// goal or the displacement only).
    pub candidates: usize,
    /// TD3's target smoothing noise, a fraction of each output's half range.
    pub policy_noise: f32,
    /// The smoothing noise is clipped to this fraction of the half range.
    pub noise_clip: f32,
    /// The actor and the targets move once per this many critic updates.
    pub policy_delay: u64,
    /// Updates per primitive step: HIRO trains its low level once per step and its high level
    /// once per `c` steps (1.0). The learner grants them per episode, as for HAC: level 0
    /// `updates_per_step x max_actions` updates per training episode, level 1 that over `c`.
    pub updates_per_step: f32,
    /// The task reward the high level sums over its steps: the sparse one of the HAC paper's
    /// comparison (the default), or minus the distance to the end goal, the dense reward the
    /// HIRO paper's own tasks used (a diagnostic: it changes what the high level learns from,
    /// not the task's success test).
    #[serde(default)]
    pub task_reward: TaskReward,
    /// What each critic minimises against its TD target: the mean squared error of the TD3
    /// paper (the default), or the Huber loss (delta 1) that the HIRO paper's reference code
    /// and the public PyTorch port of it use. Left out of a run's `config.toml` when it is the
    /// default, so runs from before the key keep their configuration digest.
    #[serde(default, skip_serializing_if = "CriticLoss::is_mse")]
    pub critic_loss: CriticLoss,
}

/// What a TD3 critic minimises against its target ([`HiroConfig::critic_loss`]).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum CriticLoss {
    /// The mean of `(Q - y)^2`: the TD3 paper's.
    #[default]
    Mse,
    /// The mean of the Huber loss with delta 1: `(Q - y)^2 / 2` within 1 of the target,
    /// `|Q - y| - 1/2` beyond, so that no sample's gradient exceeds 1 (the HIRO paper's
    /// reference code, and the PyTorch port's `smooth_l1_loss`).
    Huber,
}

impl CriticLoss {
    /// The loss of one sample whose prediction is `err` off its target, and the loss's
    /// derivative in the prediction.
    pub fn value_and_slope(self, err: f32) -> (f32, f32) {
        match self {
            CriticLoss::Mse => (err * err, 2.0 * err),
            CriticLoss::Huber if err.abs() <= 1.0 => (0.5 * err * err, err),
            CriticLoss::Huber => (err.abs() - 0.5, err.signum()),
        }
    }

    fn is_mse(&self) -> bool {
        *self == CriticLoss::Mse
    }
}

/// What HIRO's high level is rewarded with at each primitive step ([`HiroConfig::task_reward`]).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum TaskReward {
    /// -1 per step, 0 at the step that reaches the end goal (which ends the episode): the task's
    /// own sparse reward, as the HAC paper's comparison gives both algorithms.
    #[default]
    Sparse,
    /// `-||G - p_end(s')||`, the distance from the step's end-goal projection to the end goal
    /// (angles along the circle where the goal test takes them so): the dense reward of the
    /// HIRO paper's tasks. The episode still ends, and succeeds, only within the thresholds.
    Distance,
}

impl Default for HiroConfig {
    /// The HIRO paper's values: c = 10, 8 random candidates, smoothing 0.2 clipped to 0.5,
    /// the actor every 2nd update.
    fn default() -> Self {
        Self {
            c: 10,
            candidates: 8,
            policy_noise: 0.2,
            noise_clip: 0.5,
            policy_delay: 2,
            updates_per_step: 1.0,
            task_reward: TaskReward::Sparse,
            critic_loss: CriticLoss::Mse,
        }
    }
}

impl HiroConfig {
    /// HIRO's reference values for the settings it shares with HAC: gamma 0.99, actor lr
    /// 1e-4, critic lr 1e-3, batch 100, target networks at rate 0.005, Gaussian noise of 0.1
    /// of the half range at both levels, no random actions. Hidden layers, updates per
    /// episode and replay capacity stay as they are (the same networks and schedule as HAC,
    /// so that a comparison measures the algorithms).
    pub fn agent_defaults(agent: &mut AgentConfig) {
        agent.gamma = 0.99;
        agent.actor_lr = 1e-4;
        agent.critic_lr = 1e-3;
        agent.batch_size = 100;
        agent.target_tau = Some(0.005);
        agent.action_noise = Noise::Relative(0.1);
        agent.subgoal_noise = Noise::Relative(0.1);
        agent.random_action_prob = 0.0;
    }

    /// Updates per training episode of `level` in episodes of at most `max_actions` primitive
    /// actions ([`updates_per_step`](Self::updates_per_step)).
    pub fn updates_per_episode(&self, level: usize, max_actions: usize) -> f64 {
        let steps = if level == 0 {
            max_actions as f64
        } else {
            max_actions as f64 / self.c as f64
        };
        f64::from(self.updates_per_step) * steps
    }

    /// Checks every field and the run's level count (HIRO has exactly two levels), naming the
    /// first invalid one.
    pub fn validate(&self, levels: usize, agent: &AgentConfig) -> Result<(), ConfigError> {
        if levels != 2 {
            return Err(ConfigError::invalid(
                "levels",
                format!("{levels}: HIRO has exactly 2 levels (`--algo hiro` needs `--levels 2`)"),
            ));
        }
        if agent.target_tau.is_none() {
            return Err(ConfigError::invalid(
                "agent.target_tau",
                "HIRO's TD3 needs target networks: set a rate in (0, 1]".into(),
            ));
        }
        if self.c == 0 || self.c > 1000 {
            return Err(ConfigError::invalid(
                "hiro.c",
                format!("{} (must be 1 to 1000)", self.c),
            ));
        }
        if self.candidates > 1000 {
            return Err(ConfigError::invalid(
                "hiro.candidates",
                format!("{} (at most 1000)", self.candidates),
            ));
        }
        for (key, v) in [
            ("hiro.policy_noise", self.policy_noise),
            ("hiro.noise_clip", self.noise_clip),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(ConfigError::invalid(
                    key,
                    format!("{v} (must be a finite fraction >= 0)"),
                ));
            }
        }
        if !(self.updates_per_step.is_finite() && self.updates_per_step > 0.0) {
            return Err(ConfigError::invalid(
                "hiro.updates_per_step",
                format!(
                    "{} (must be a finite number above 0)",
                    self.updates_per_step
                ),
            ));
        }
        if self.policy_delay == 0 {
            return Err(ConfigError::invalid(
                "hiro.policy_delay",
                "must be at least 1".into(),
            ));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::CriticLoss;

    #[test]
    fn critic_losses_and_their_slopes() {
        assert_eq!(CriticLoss::Mse.value_and_slope(3.0), (9.0, 6.0));
        assert_eq!(CriticLoss::Mse.value_and_slope(-0.5), (0.25, -1.0));
        // Huber, delta 1: quadratic within 1, linear beyond, continuous at the seam.
        assert_eq!(CriticLoss::Huber.value_and_slope(0.5), (0.125, 0.5));
        assert_eq!(CriticLoss::Huber.value_and_slope(-1.0), (0.5, -1.0));
        assert_eq!(CriticLoss::Huber.value_and_slope(3.0), (2.5, 1.0));
        assert_eq!(CriticLoss::Huber.value_and_slope(-300.0), (299.5, -1.0));
        let (inside, _) = CriticLoss::Huber.value_and_slope(1.0);
        let (outside, _) = CriticLoss::Huber.value_and_slope(1.0 + 1e-6);
        assert!((outside - inside).abs() < 1e-5);
    }
}
