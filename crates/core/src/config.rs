//! The agent's hyperparameters: one serde struct, with defaults supplied per environment.

use serde::{Deserialize, Serialize};

use crate::Bounds;

/// Exploration noise: a fraction of each dimension's half range (the paper's convention), or an
/// absolute standard deviation per dimension (the PyTorch port's convention).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum Noise {
    Relative(f32),
    Absolute(Vec<f32>),
}

impl Noise {
    /// The absolute standard deviation per dimension for outputs bounded by `bounds`.
    pub fn std(&self, bounds: &Bounds) -> Vec<f32> {
        match self {
            Noise::Relative(f) => (0..bounds.dim())
                .map(|d| f * bounds.half_range(d))
                .collect(),
            Noise::Absolute(v) => v.clone(),
        }
    }

    fn check(&self, what: &str, dim: usize) -> Result<(), ConfigError> {
        match self {
            Noise::Relative(f) if !(f.is_finite() && *f >= 0.0) => Err(ConfigError::invalid(
                what,
                format!("must be a finite fraction >= 0, got {f}"),
            )),
            Noise::Absolute(v) if v.len() != dim => Err(ConfigError::invalid(
                what,
                format!("needs {dim} values (one per dimension), got {}", v.len()),
            )),
            Noise::Absolute(v) if v.iter().any(|x| !(x.is_finite() && *x >= 0.0)) => Err(
                ConfigError::invalid(what, "values must be finite and >= 0".into()),
            ),
            _ => Ok(()),
        }
    }
}

/// HAC hyperparameters. Every field has a meaning in docs/ALGORITHM.md; the defaults for a
/// given environment and level count come from `Env::default_config`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AgentConfig {
    /// Number of levels k (1 = flat DDPG + HER).
    pub levels: usize,
    /// H: attempts per level before it returns control (also the critic's bound and the penalty).
    pub horizon: usize,
    /// lambda: probability that a level above 0 tests its subgoal.
    pub subgoal_test_prob: f32,
    /// Probability of a uniform random action in a training episode.
    pub random_action_prob: f32,
    /// Gaussian noise on level 0's primitive actions.
    pub action_noise: Noise,
    /// Gaussian noise on the subgoals of levels above 0.
    pub subgoal_noise: Noise,
    /// Hindsight goals per HER pass (2 random + the last one when 3).
    pub num_replay_goals: usize,
    /// Discount factor.
    pub gamma: f32,
    /// Hidden layer widths of actor and critic.
    pub hidden_layers: Vec<usize>,
    pub actor_lr: f32,
    pub critic_lr: f32,
    /// Minibatch size per update.
    pub batch_size: usize,
    /// Updates per level after each training episode (once the buffer holds one batch).
    pub updates_per_episode: usize,
    /// Polyak rate of target networks; absent = no target networks (the reference's setting).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub target_tau: Option<f32>,
    /// Weight of an L2 penalty on the actor's pre-`tanh` outputs (mean square), added to its
    /// loss `-Q`; 0 = the paper's actor loss. A safeguard against an actor stuck at a corner of
    /// its bounds where a saturated critic gives no gradient.
    #[serde(default)]
    pub actor_preactivation_l2: f32,
    /// Compute the critic's slope `-H s (1 - s)` from its pre-sigmoid output instead of from
    /// `Q` as the reference does (`false`), where it rounds to exactly 0 once `Q` reads `-H`.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub exact_critic_slope: bool,
    /// The actor's `tanh` reads exactly `+-1` from `|x| >= 7.9074` on, as TensorFlow's float
    /// `tanh` (the reference code's arithmetic) does: the default. `false`: libm's, which rounds
    /// to `+-1` only from `|x|` of about 9.01, so an output at its bound keeps a gradient of
    /// about `5e-7`: the default before docs/RESULTS.md's measurements changed it. Always
    /// written to a run's `config.toml`; a file from before has no such key and reads `false`,
    /// as that run was trained.
    #[serde(default)]
    pub saturating_tanh: bool,
    /// Clip each hindsight action of the levels above 0 (the subgoal a level below actually
    /// achieved, when it missed the proposed one) into the subgoal bounds on every dimension that
    /// is not an angle, so the stored action is one the actor can propose. `false` (the paper's):
    /// the achieved subgoal as projected, which lies outside the bounds when the state does (a
    /// cartpole's cart past +-2.5 m).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub clip_hindsight_actions: bool,
    /// Episodes' worth of transitions each level's replay keeps (sizes the buffers).
    pub episodes_to_store: usize,
    /// Upper bound on any level's replay capacity.
    pub replay_capacity_max: usize,
    /// Training episodes between test rounds.
    pub exploration_episodes: usize,
    /// Greedy test episodes per test round.
    pub test_episodes: usize,
}

impl AgentConfig {
    /// The paper's reference hyperparameters for `levels` levels with horizon `horizon`: lambda
    /// 0.3, 20% random actions, noise 0.1 of the half range, 3 replay goals, gamma 0.98, 3 hidden
    /// layers of 64, Adam at 1e-3, batches of 1024, 40 updates per episode, no target networks,
    /// 200 episodes stored, 50 training episodes then 100 test episodes per round, and the
    /// reference code's float `tanh` (`saturating_tanh`). Environments
    /// start here and override what the task sets differently (docs/ENVIRONMENTS.md).
    pub fn reference(levels: usize, horizon: usize) -> Self {
        Self {
            levels,
            horizon,
            subgoal_test_prob: 0.3,
            random_action_prob: 0.2,
            action_noise: Noise::Relative(0.1),
            subgoal_noise: Noise::Relative(0.1),
            num_replay_goals: 3,
            gamma: 0.98,
            hidden_layers: vec![64, 64, 64],
            actor_lr: 1e-3,
            critic_lr: 1e-3,
            batch_size: 1024,
            updates_per_episode: 40,
            target_tau: None,
            actor_preactivation_l2: 0.0,
            exact_critic_slope: false,
            saturating_tanh: true,
            clip_hindsight_actions: false,
            episodes_to_store: 200,
            replay_capacity_max: 10_000_000,
            exploration_episodes: 50,
            test_episodes: 100,
        }
    }

    /// Replay capacity of `level`, as in the reference: `(1 + replay goals) * H` transitions per
    /// attempt (plus `H / 3` penalties above level 0), `H^(k-1-level)` attempts per episode.
    pub fn replay_capacity(&self, level: usize) -> usize {
        let h = self.horizon;
        let mut per_attempt = (1 + self.num_replay_goals) * h;
        if level > 0 {
            per_attempt += h / 3;
        }
        let attempts = h.saturating_pow((self.levels - 1 - level) as u32);
        per_attempt
            .saturating_mul(attempts)
            .saturating_mul(self.episodes_to_store)
            .clamp(self.batch_size, self.replay_capacity_max)
    }

    /// Rejects values that make no sense, naming the key.
    pub fn validate(&self, action_dim: usize, subgoal_dim: usize) -> Result<(), ConfigError> {
        let positive = |key: &str, v: usize| {
            if v == 0 {
                Err(ConfigError::invalid(key, "must be at least 1".into()))
            } else {
                Ok(())
            }
        };
        positive("levels", self.levels)?;
        positive("horizon", self.horizon)?;
        positive("batch_size", self.batch_size)?;
        positive("episodes_to_store", self.episodes_to_store)?;
        positive("replay_capacity_max", self.replay_capacity_max)?;
        positive("test_episodes", self.test_episodes)?;
        positive("exploration_episodes", self.exploration_episodes)?;
        if self.levels > 8 {
            return Err(ConfigError::invalid(
                "levels",
                "at most 8 levels are supported".into(),
            ));
        }
        for (key, p) in [
            ("subgoal_test_prob", self.subgoal_test_prob),
            ("random_action_prob", self.random_action_prob),
        ] {
            if !(0.0..=1.0).contains(&p) {
                return Err(ConfigError::invalid(
                    key,
                    format!("must be in [0, 1], got {p}"),
                ));
            }
        }
        if self.num_replay_goals > crate::rollout::MAX_REPLAY_GOALS {
            return Err(ConfigError::invalid(
                "num_replay_goals",
                format!("at most {} are supported", crate::rollout::MAX_REPLAY_GOALS),
            ));
        }
        if !(self.gamma > 0.0 && self.gamma <= 1.0) {
            return Err(ConfigError::invalid(
                "gamma",
                format!("must be in (0, 1], got {}", self.gamma),
            ));
        }
        for (key, lr) in [("actor_lr", self.actor_lr), ("critic_lr", self.critic_lr)] {
            if !(lr.is_finite() && lr > 0.0) {
                return Err(ConfigError::invalid(
                    key,
                    format!("must be a positive number, got {lr}"),
                ));
            }
        }
        if self.hidden_layers.is_empty() || self.hidden_layers.contains(&0) {
            return Err(ConfigError::invalid(
                "hidden_layers",
                "needs at least one layer, each at least 1 wide".into(),
            ));
        }
        if let Some(tau) = self.target_tau
            && !(tau > 0.0 && tau <= 1.0)
        {
            return Err(ConfigError::invalid(
                "target_tau",
                format!("must be in (0, 1], got {tau}"),
            ));
        }
        let l2 = self.actor_preactivation_l2;
        if !(l2.is_finite() && l2 >= 0.0) {
            return Err(ConfigError::invalid(
                "actor_preactivation_l2",
                format!("must be a finite number >= 0, got {l2}"),
            ));
        }
        self.action_noise.check("action_noise", action_dim)?;
        self.subgoal_noise.check("subgoal_noise", subgoal_dim)?;
        Ok(())
    }
}

/// A configuration value that cannot be used.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("invalid config value for `{key}`: {reason}")]
pub struct ConfigError {
    pub key: String,
    pub reason: String,
}

impl ConfigError {
    pub fn invalid(key: &str, reason: String) -> Self {
        Self {
            key: key.to_string(),
            reason,
        }
    }
}
