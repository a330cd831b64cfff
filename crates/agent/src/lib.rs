//! The HAC agent and the embedded training schedule.
//!
//! - [`Agent`]: one [`LevelLearner`] per level; it is the rollout's [`Policy`] (greedy outputs)
//!   and saves/loads its weights as one safetensors file per level.
//! - [`Trainer`]: the reference schedule in one process: training episodes through the
//!   hierarchy rollout into per-level replay, `updates_per_episode` updates per level after each
//!   episode (levels update in parallel, each from its own RNG stream, so results do not depend on
//!   the thread count), and greedy test rounds whose success rate is the learning curve.

mod run_config;

use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use hac_core::{
    AgentConfig, Batch, ConfigError, Env, EnvSpec, EpisodeOutcome, GaussianExploration, Hierarchy,
    Mode, NullSink, Policy, Rng,
};
use hac_nn::{LearnerConfig, LevelLearner, NnError, UpdateStats};
use hac_replay::{Replay, ReplayTable};
use serde::{Deserialize, Serialize};

pub use run_config::{RunConfig, RunConfigError};

/// Why an agent could not be built, saved or loaded.
#[derive(Debug, thiserror::Error)]
pub enum AgentError {
    #[error(transparent)]
    Config(#[from] ConfigError),
    #[error("{path}: {source}")]
    Io {
        path: String,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: {source}")]
    Weights {
        path: String,
        #[source]
        source: NnError,
    },
}

/// k level learners; level 0 acts in the environment, level `i > 0` proposes subgoals.
#[derive(Debug)]
pub struct Agent {
    levels: Vec<LevelLearner>,
}

impl Agent {
    /// Freshly initialised networks for every level; `config` must have been validated.
    pub fn new(spec: &EnvSpec, config: &AgentConfig, rng: &mut Rng) -> Self {
        let levels = (0..config.levels)
            .map(|level| {
                LevelLearner::new(
                    LearnerConfig::for_level(config, spec, level),
                    &mut rng.fork(),
                )
            })
            .collect();
        Self { levels }
    }

    /// An agent made of trained level learners, level 0 first.
    pub fn from_levels(levels: Vec<LevelLearner>) -> Self {
        Self { levels }
    }

    /// The level learners, level 0 first.
    pub fn into_levels(self) -> Vec<LevelLearner> {
        self.levels
    }

    pub fn levels(&self) -> &[LevelLearner] {
        &self.levels
    }

    /// Writes `level<i>.safetensors` (actor, critic) for every level into `dir`.
    pub fn save(&self, dir: &Path) -> Result<(), AgentError> {
        std::fs::create_dir_all(dir).map_err(|source| AgentError::Io {
            path: dir.display().to_string(),
            source,
        })?;
        for (i, level) in self.levels.iter().enumerate() {
            let path = dir.join(format!("level{i}.safetensors"));
            let tmp = path.with_extension("safetensors.tmp");
            let io = |source| AgentError::Io {
                path: path.display().to_string(),
                source,
            };
            std::fs::write(&tmp, level.to_safetensors()).map_err(io)?;
            std::fs::rename(&tmp, &path).map_err(io)?;
        }
        Ok(())
    }

    /// Reads the weights `save` wrote, checking them against the run's config.
    pub fn load(dir: &Path, spec: &EnvSpec, config: &AgentConfig) -> Result<Self, AgentError> {
        let mut levels = Vec::with_capacity(config.levels);
        for level in 0..config.levels {
            let path = dir.join(format!("level{level}.safetensors"));
            let shown = path.display().to_string();
            let bytes = std::fs::read(&path).map_err(|source| AgentError::Io {
                path: shown.clone(),
                source,
            })?;
            let expected = LearnerConfig::for_level(config, spec, level);
            let learner = LevelLearner::from_safetensors(expected, &bytes).map_err(|source| {
                AgentError::Weights {
                    path: shown.clone(),
                    source,
                }
            })?;
            levels.push(learner);
        }
        Ok(Self { levels })
    }
}

impl Policy for Agent {
    fn act(&mut self, level: usize, state: &[f32], goal: &[f32], action: &mut [f32]) {
        self.levels[level].act(state, goal, action);
    }
}

/// How the trainer runs (not part of the algorithm's hyperparameters).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct TrainerOptions {
    /// Seed of every random stream of the run.
    pub seed: u64,
    /// Threads for per-level updates; 1 = everything on the calling thread.
    pub threads: usize,
    /// Replay shards per level.
    pub replay_shards: usize,
}

impl Default for TrainerOptions {
    fn default() -> Self {
        Self {
            seed: 0,
            threads: 2,
            replay_shards: 1,
        }
    }
}

/// One level's training statistics at a test round.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct LevelReport {
    /// Updates done so far.
    pub updates: u64,
    /// Transitions in replay.
    pub replay_len: usize,
    /// Statistics of the last update (zero before the first).
    pub critic_loss: f32,
    pub actor_loss: f32,
    pub mean_q: f32,
}

/// One point of the learning curve.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RoundReport {
    /// 1-based test round.
    pub round: usize,
    /// Training episodes so far.
    pub episodes: u64,
    /// Primitive actions in training episodes so far.
    pub env_steps: u64,
    /// Greedy test success rate of this round.
    pub success_rate: f32,
    /// Seconds since training started.
    pub elapsed_s: f64,
    /// Training rollout speed since the last round (primitive actions per second).
    pub env_steps_per_s: f64,
    /// Update speed since the last round (updates per second, all levels).
    pub updates_per_s: f64,
    pub levels: Vec<LevelReport>,
}

impl RoundReport {
    /// Header of the learning-curve CSV for `levels` levels.
    pub fn csv_header(levels: usize) -> String {
        let mut h = String::from(
            "round,episodes,env_steps,success_rate,elapsed_s,env_steps_per_s,updates_per_s",
        );
        for l in 0..levels {
            for f in [
                "updates",
                "replay_len",
                "critic_loss",
                "actor_loss",
                "mean_q",
            ] {
                h.push_str(&format!(",level{l}_{f}"));
            }
        }
        h
    }

    pub fn csv_row(&self) -> String {
        let mut r = format!(
            "{},{},{},{:.4},{:.3},{:.1},{:.1}",
            self.round,
            self.episodes,
            self.env_steps,
            self.success_rate,
            self.elapsed_s,
            self.env_steps_per_s,
            self.updates_per_s
        );
        for l in &self.levels {
            r.push_str(&format!(
                ",{},{},{},{},{}",
                l.updates, l.replay_len, l.critic_loss, l.actor_loss, l.mean_q
            ));
        }
        r
    }
}

/// Per-level training state beside the learner: its sampler stream and batch buffer.
#[derive(Debug)]
struct LevelTraining {
    rng: Rng,
    batch: Batch,
    updates: u64,
    last: Option<UpdateStats>,
}

impl LevelTraining {
    fn update(&mut self, learner: &mut LevelLearner, table: &ReplayTable, updates: usize) {
        // The paper's rule: a level learns only once its buffer holds a whole batch.
        if table.len() < self.batch.len {
            return;
        }
        for _ in 0..updates {
            table
                .sample(&mut self.rng, &mut self.batch)
                .expect("a table holding a batch can be sampled");
            self.last = Some(learner.update(&self.batch));
            self.updates += 1;
        }
    }
}

/// The embedded training loop: rollouts, replay, updates and test rounds in one process.
#[derive(Debug)]
pub struct Trainer {
    env: Box<dyn Env>,
    config: AgentConfig,
    options: TrainerOptions,
    agent: Agent,
    training: Vec<LevelTraining>,
    replay: Replay,
    hierarchy: Hierarchy,
    exploration: GaussianExploration,
    train_rng: Rng,
    test_rng: Rng,
    episodes: u64,
    env_steps: u64,
    rounds: usize,
    started: Instant,
    rollout_time: Duration,
    update_time: Duration,
}

impl Trainer {
    /// A trainer with fresh networks and empty replay. Rejects invalid configs.
    pub fn new(
        env: Box<dyn Env>,
        config: AgentConfig,
        options: TrainerOptions,
    ) -> Result<Self, AgentError> {
        let spec = env.spec().clone();
        config.validate(spec.action_dim(), spec.subgoal_dim())?;
        if options.threads == 0 {
            return Err(ConfigError::invalid("threads", "must be at least 1".into()).into());
        }
        if options.replay_shards == 0 {
            return Err(ConfigError::invalid("replay_shards", "must be at least 1".into()).into());
        }
        let mut root = Rng::seed_from(options.seed);
        let agent = Agent::new(&spec, &config, &mut root);
        let training = (0..config.levels)
            .map(|level| LevelTraining {
                rng: root.fork(),
                batch: Batch::zeros(spec.level_dims(level, config.levels), config.batch_size),
                updates: 0,
                last: None,
            })
            .collect();
        Ok(Self {
            replay: Replay::for_agent(&spec, &config, options.replay_shards),
            hierarchy: Hierarchy::new(&spec, &config),
            exploration: GaussianExploration::new(&spec, &config, root.fork()),
            train_rng: root.fork(),
            test_rng: root.fork(),
            env,
            config,
            options,
            agent,
            training,
            episodes: 0,
            env_steps: 0,
            rounds: 0,
            started: Instant::now(),
            rollout_time: Duration::ZERO,
            update_time: Duration::ZERO,
        })
    }

    pub fn agent(&self) -> &Agent {
        &self.agent
    }

    pub fn config(&self) -> &AgentConfig {
        &self.config
    }

    pub fn spec(&self) -> &EnvSpec {
        self.env.spec()
    }

    pub fn replay(&self) -> &Replay {
        &self.replay
    }

    pub fn episodes(&self) -> u64 {
        self.episodes
    }

    /// One training episode into replay, then every level's updates. Returns whether the end
    /// goal was reached.
    pub fn train_episode(&mut self) -> bool {
        let t0 = Instant::now();
        let outcome = self.hierarchy.run_episode(
            self.env.as_mut(),
            &mut self.agent,
            &mut self.exploration,
            Mode::Train,
            &mut self.train_rng,
            &mut &self.replay,
        );
        self.episodes += 1;
        self.env_steps += outcome.steps as u64;
        let t1 = Instant::now();
        self.rollout_time += t1 - t0;
        self.update_levels();
        self.update_time += t1.elapsed();
        outcome.success
    }

    fn update_levels(&mut self) {
        let updates = self.config.updates_per_episode;
        let replay = &self.replay;
        let work = self
            .agent
            .levels
            .iter_mut()
            .zip(self.training.iter_mut())
            .enumerate()
            .map(|(level, (learner, training))| (learner, training, replay.table(level)));
        if self.options.threads <= 1 || self.config.levels == 1 {
            for (learner, training, table) in work {
                training.update(learner, table, updates);
            }
            return;
        }
        // Levels are independent learning problems; each draws from its own RNG stream, so the
        // result is the same whatever the interleaving.
        let mut work: Vec<_> = work.collect();
        let per_thread = work.len().div_ceil(self.options.threads);
        std::thread::scope(|scope| {
            let mut chunks = work.chunks_mut(per_thread);
            let first = chunks.next();
            for chunk in chunks {
                scope.spawn(move || {
                    for (learner, training, table) in chunk.iter_mut() {
                        training.update(learner, table, updates);
                    }
                });
            }
            for (learner, training, table) in first.into_iter().flatten() {
                training.update(learner, table, updates);
            }
        });
    }

    /// `episodes` greedy test episodes; returns the success rate. Uses its own random stream so
    /// testing never changes what training does.
    pub fn test(&mut self, episodes: usize) -> f32 {
        test_episodes(
            &mut self.hierarchy,
            self.env.as_mut(),
            &mut self.agent,
            &mut self.exploration,
            &mut self.test_rng,
            episodes,
            |_, _| {},
        )
    }

    /// Runs the reference schedule for `episodes` training episodes: `exploration_episodes`
    /// training episodes, then a test round of `test_episodes`, repeated. Calls `on_round` after
    /// each test round; stops early once a round reaches `stop_at` (if given). Setting `interrupt`
    /// (e.g. from a signal handler) ends the run after the current episode, without a final test
    /// round; the agent keeps everything learned so far.
    pub fn run(
        &mut self,
        episodes: u64,
        stop_at: Option<f32>,
        interrupt: &AtomicBool,
        mut on_round: impl FnMut(&RoundReport),
    ) -> Vec<RoundReport> {
        let mut curve = Vec::new();
        let (mut last_steps, mut last_updates) = (self.env_steps, self.total_updates());
        let (mut last_rollout, mut last_update) = (self.rollout_time, self.update_time);
        while self.episodes < episodes {
            let block = (self.config.exploration_episodes as u64).min(episodes - self.episodes);
            for _ in 0..block {
                if interrupt.load(Ordering::Relaxed) {
                    return curve;
                }
                self.train_episode();
            }
            let success_rate = self.test(self.config.test_episodes);
            self.rounds += 1;
            let rate = |n: u64, d: Duration| {
                let s = d.as_secs_f64();
                if s > 0.0 { n as f64 / s } else { 0.0 }
            };
            let report = RoundReport {
                round: self.rounds,
                episodes: self.episodes,
                env_steps: self.env_steps,
                success_rate,
                elapsed_s: self.started.elapsed().as_secs_f64(),
                env_steps_per_s: rate(
                    self.env_steps - last_steps,
                    self.rollout_time - last_rollout,
                ),
                updates_per_s: rate(
                    self.total_updates() - last_updates,
                    self.update_time - last_update,
                ),
                levels: self.level_reports(),
            };
            (last_steps, last_updates) = (self.env_steps, self.total_updates());
            (last_rollout, last_update) = (self.rollout_time, self.update_time);
            on_round(&report);
            let done = stop_at.is_some_and(|target| report.success_rate >= target);
            curve.push(report);
            if done {
                break;
            }
        }
        curve
    }

    fn total_updates(&self) -> u64 {
        self.training.iter().map(|t| t.updates).sum()
    }

    fn level_reports(&self) -> Vec<LevelReport> {
        self.training
            .iter()
            .enumerate()
            .map(|(level, t)| {
                let last = t.last.unwrap_or_default();
                LevelReport {
                    updates: t.updates,
                    replay_len: self.replay.table(level).len(),
                    critic_loss: last.critic_loss,
                    actor_loss: last.actor_loss,
                    mean_q: last.mean_q,
                }
            })
            .collect()
    }
}

/// Greedy test episodes of a saved agent. Calls `on_episode` with each outcome and the final
/// state; returns the success rate.
pub fn evaluate(
    env: &mut dyn Env,
    agent: &mut Agent,
    config: &AgentConfig,
    episodes: usize,
    seed: u64,
    on_episode: impl FnMut(&EpisodeOutcome, &[f32]),
) -> f32 {
    let spec = env.spec().clone();
    let mut rng = Rng::seed_from(seed);
    // Never consulted in test mode, where every level acts greedily.
    let mut exploration = GaussianExploration::new(&spec, config, rng.fork());
    let mut hierarchy = Hierarchy::new(&spec, config);
    test_episodes(
        &mut hierarchy,
        env,
        agent,
        &mut exploration,
        &mut rng,
        episodes,
        on_episode,
    )
}

/// Runs `episodes` greedy test episodes of `policy`; returns the success rate. The rollout never
/// consults `exploration` in test mode.
pub fn test_episodes(
    hierarchy: &mut Hierarchy,
    env: &mut dyn Env,
    agent: &mut impl Policy,
    exploration: &mut GaussianExploration,
    rng: &mut Rng,
    episodes: usize,
    mut on_episode: impl FnMut(&EpisodeOutcome, &[f32]),
) -> f32 {
    let mut successes = 0usize;
    for _ in 0..episodes {
        let outcome =
            hierarchy.run_episode(env, agent, exploration, Mode::Test, rng, &mut NullSink);
        successes += usize::from(outcome.success);
        on_episode(&outcome, env.state());
    }
    successes as f32 / episodes.max(1) as f32
}
