//! HAC core: everything about Hierarchical Actor-Critic that involves no IO and no learning.
//!
//! - [`hiro`]: HIRO's goal arithmetic (the paper's baseline): the goal transition, the
//!   intrinsic reward and the off-policy correction of high-level transitions.
//! - [`rates`]: [`RateWindow`](rates::RateWindow), per-second rates of counters over a sliding
//!   window, and [`TokenBucket`](rates::TokenBucket), a message rate limit (status and admission
//!   of the processes; clocks are passed in).
//! - [`rng`]: the seeded, portable random generator all components draw from.
//! - [`bounds`]: boxes (action and subgoal bounds) and the per-dimension goal test.
//! - [`env`]: the [`Env`] trait and the static [`EnvSpec`] every environment describes.
//! - [`limits`]: [`TransitionLimits`], what a level's transitions can hold (admission of
//!   transitions from outside the process).
//! - [`config`]: [`AgentConfig`], the hyperparameters, validated with errors that name the key.
//! - [`transition`]: transitions as produced, the [`TransitionSink`] they go to, and [`Batch`].
//! - [`rollout`]: the hierarchy rollout: one episode through k levels with the behaviour policy,
//!   subgoal testing, and all three transition kinds (hindsight action, HER, subgoal penalty).

pub mod bounds;
pub mod config;
pub mod env;
pub mod episodes;
pub mod hiro;
pub mod limits;
pub mod rates;
pub mod rng;
pub mod rollout;
pub mod transition;

pub use bounds::{Bounds, within, within_goal};
pub use config::{AgentConfig, ConfigError, Noise};
pub use env::{Env, EnvSpec, LevelDims, Mode, StateError, horizon_covering};
pub use episodes::Episodes;
pub use limits::{LimitError, TransitionLimits};
pub use rng::Rng;
pub use rollout::{
    EpisodeOutcome, Exploration, GaussianExploration, Hierarchy, LevelCounts, Policy,
};
pub use transition::{
    Batch, BatchRef, NullSink, OwnedTransition, Transition, TransitionKind, TransitionSink,
};
