//! [`LevelModel`]: one level's networks and the way they learn, HAC's or HIRO's.

use hac_core::hiro::{HiroConfig, goal_radius};
use hac_core::{AgentConfig, Bounds, EnvSpec, Rng};

use crate::{ActorNet, LearnerConfig, LevelLearner, NnError, Td3Config, Td3Learner};

impl Td3Config {
    /// HIRO's level `level` (0: primitive actions, 1: relative goals in `[-r, r]`, `r` the
    /// subgoal bounds' half ranges) on `spec`: the shared settings from `agent` (hidden
    /// layers, gamma, learning rates, target rate), the TD3 ones from `hiro`.
    ///
    /// Panics if `agent.target_tau` is unset (a validated HIRO run has it).
    pub fn for_hiro_level(
        agent: &AgentConfig,
        hiro: &HiroConfig,
        spec: &EnvSpec,
        level: usize,
    ) -> Self {
        let action_bounds = if level == 0 {
            spec.action_bounds.clone()
        } else {
            Bounds::symmetric(&goal_radius(spec))
        };
        Self {
            dims: spec.level_dims(level, 2),
            action_bounds,
            gamma: agent.gamma,
            hidden: agent.hidden_layers.clone(),
            actor_lr: agent.actor_lr,
            critic_lr: agent.critic_lr,
            tau: agent
                .target_tau
                .expect("HIRO runs are validated to have target networks"),
            policy_noise: hiro.policy_noise,
            noise_clip: hiro.noise_clip,
            policy_delay: hiro.policy_delay,
            critic_loss: hiro.critic_loss,
        }
    }
}

/// One level's learner: HAC's bounded DDPG learner or, in a HIRO run, a TD3 learner.
#[derive(Debug, Clone)]
pub enum LevelModel {
    /// HAC's level learner.
    Hac(Box<LevelLearner>),
    /// One of HIRO's two levels.
    Td3(Box<Td3Learner>),
}

impl LevelModel {
    /// Level `level` of a freshly initialised agent: HIRO's when `hiro` is given, else HAC's.
    pub fn new(
        agent: &AgentConfig,
        hiro: Option<&HiroConfig>,
        spec: &EnvSpec,
        level: usize,
        rng: &mut Rng,
    ) -> Self {
        match hiro {
            None => Self::Hac(Box::new(LevelLearner::new(
                LearnerConfig::for_level(agent, spec, level),
                rng,
            ))),
            Some(hiro) => Self::Td3(Box::new(Td3Learner::new(
                Td3Config::for_hiro_level(agent, hiro, spec, level),
                rng,
            ))),
        }
    }

    /// Reads what [`to_safetensors`](Self::to_safetensors) wrote, for the level [`new`](Self::new)
    /// would build from the same arguments.
    pub fn from_safetensors(
        agent: &AgentConfig,
        hiro: Option<&HiroConfig>,
        spec: &EnvSpec,
        level: usize,
        bytes: &[u8],
    ) -> Result<Self, NnError> {
        Ok(match hiro {
            None => Self::Hac(Box::new(LevelLearner::from_safetensors(
                LearnerConfig::for_level(agent, spec, level),
                bytes,
            )?)),
            Some(hiro) => Self::Td3(Box::new(Td3Learner::from_safetensors(
                Td3Config::for_hiro_level(agent, hiro, spec, level),
                bytes,
            )?)),
        })
    }

    /// The learner's whole state (networks, optimisers, targets) as a safetensors file.
    pub fn to_safetensors(&self) -> Vec<u8> {
        match self {
            Self::Hac(l) => l.to_safetensors(),
            Self::Td3(l) => l.to_safetensors(),
        }
    }

    /// The current actor.
    pub fn actor(&self) -> &ActorNet {
        match self {
            Self::Hac(l) => l.actor(),
            Self::Td3(l) => l.actor(),
        }
    }

    /// Updates done so far (TD3: critic updates).
    pub fn updates(&self) -> u64 {
        match self {
            Self::Hac(l) => l.updates(),
            Self::Td3(l) => l.updates(),
        }
    }

    /// The greedy action `pi(state, goal)`, written into `out`.
    pub fn act(&mut self, state: &[f32], goal: &[f32], out: &mut [f32]) {
        match self {
            Self::Hac(l) => l.act(state, goal, out),
            Self::Td3(l) => l.act(state, goal, out),
        }
    }

    /// Shares HAC's updates among `threads` threads ([`LevelLearner::set_threads`]); a TD3
    /// level updates on its trainer's thread alone (its batches are 10 times smaller).
    pub fn set_threads(&mut self, threads: usize) {
        if let Self::Hac(l) = self {
            l.set_threads(threads);
        }
    }

    /// HAC's learner, if this is one.
    pub fn as_hac(&self) -> Option<&LevelLearner> {
        match self {
            Self::Hac(l) => Some(l),
            Self::Td3(_) => None,
        }
    }
}
