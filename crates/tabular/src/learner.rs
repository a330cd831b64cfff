//! The tabular learner driven by the core rollout, and the learning-curve experiment.
//!
//! A training episode runs [`Hierarchy::run_episode`] unchanged with the agent as policy and
//! [`TabularExploration`] as behaviour, stores the episode's transitions, then applies one
//! Q-learning update per transition in reverse order of creation: the last transitions carry
//! the rewards, so one backward sweep already propagates them along the trajectory (on 10 x 10,
//! 20 trials, greedy success after 600 episodes: 0.48 / 0.96 / 0.85 for 1 / 2 / 3 levels, against
//! 0.26 / 0.77 / 0.70 in creation order). Keeping the policy fixed within an episode mirrors the
//! reference, which trains between episodes.

use hac_core::{
    AgentConfig, EpisodeOutcome, Hierarchy, Mode, NullSink, Rng, Transition, TransitionKind,
    TransitionSink,
};
use serde::{Deserialize, Serialize};

use crate::agent::{TabularAgent, TabularConfig, TabularError, TabularExploration};
use crate::env::FourRooms;

/// One transition with grid-sized fields (states, goals and subgoals are cells, a move is one
/// value).
#[derive(Debug, Clone, Copy)]
struct Record {
    level: usize,
    kind: TransitionKind,
    state: [f32; 2],
    action: [f32; 2],
    action_len: usize,
    reward: f32,
    next_state: [f32; 2],
    goal: [f32; 2],
    terminal: bool,
}

/// The transitions of one episode, kept until the episode ends; reused across episodes.
#[derive(Debug, Default)]
struct EpisodeBuffer {
    records: Vec<Record>,
}

impl TransitionSink for EpisodeBuffer {
    fn push(&mut self, level: usize, t: &Transition<'_>) {
        let pair = |x: &[f32]| [x[0], x.get(1).copied().unwrap_or(0.0)];
        self.records.push(Record {
            level,
            kind: t.kind,
            state: pair(t.state),
            action: pair(t.action),
            action_len: t.action.len(),
            reward: t.reward,
            next_state: pair(t.next_state),
            goal: pair(t.goal),
            terminal: t.terminal,
        });
    }
}

impl EpisodeBuffer {
    /// Hands every record to `sink`, newest first, and empties the buffer.
    fn drain_newest_first(&mut self, sink: &mut dyn TransitionSink) {
        for r in self.records.iter().rev() {
            sink.push(r.level, &r.transition());
        }
        self.records.clear();
    }
}

impl Record {
    fn transition(&self) -> Transition<'_> {
        Transition {
            kind: self.kind,
            state: &self.state,
            action: &self.action[..self.action_len],
            reward: self.reward,
            next_state: &self.next_state,
            goal: &self.goal,
            terminal: self.terminal,
            extra: &[],
        }
    }
}

/// One level's replay: the last `capacity` transitions, overwritten oldest first.
#[derive(Debug)]
struct ReplayRing {
    records: Vec<Record>,
    next: usize,
    capacity: usize,
}

impl ReplayRing {
    fn push(&mut self, record: Record) {
        if self.records.len() < self.capacity {
            self.records.push(record);
        } else {
            self.records[self.next] = record;
        }
        self.next = (self.next + 1) % self.capacity;
    }
}

/// Experience replay of [`TabularConfig::replay_updates`] transitions per level per episode.
#[derive(Debug)]
struct Replay {
    updates: usize,
    levels: Vec<ReplayRing>,
    rng: Rng,
}

/// k-level tabular HAC on a four-rooms grid.
#[derive(Debug)]
pub struct TabularHac {
    config: AgentConfig,
    hierarchy: Hierarchy,
    agent: TabularAgent,
    exploration: TabularExploration,
    buffer: EpisodeBuffer,
    replay: Option<Replay>,
    /// The last episode's path of cells, for [`TabularConfig::all_segments`]; reused.
    path: Vec<usize>,
}

impl TabularHac {
    /// A fresh learner (all values 0) for `env` with `config.levels` levels.
    pub fn new(
        env: &FourRooms,
        config: AgentConfig,
        tabular: &TabularConfig,
        rng: &mut Rng,
    ) -> Result<Self, TabularError> {
        let agent = TabularAgent::new(env.grid(), &config, tabular, rng.fork())?;
        let exploration = agent.exploration(&config, rng.fork());
        let hierarchy = Hierarchy::new(hac_core::Env::spec(env), &config);
        // Only a replaying learner draws a stream for it: without replay, runs stay as before.
        let replay = (tabular.replay_updates > 0).then(|| Replay {
            updates: tabular.replay_updates,
            levels: (0..config.levels)
                .map(|_| ReplayRing {
                    records: Vec::new(),
                    next: 0,
                    capacity: tabular.replay_capacity.max(1),
                })
                .collect(),
            rng: rng.fork(),
        });
        Ok(Self {
            config,
            hierarchy,
            agent,
            exploration,
            buffer: EpisodeBuffer::default(),
            replay,
            path: Vec::new(),
        })
    }

    pub fn config(&self) -> &AgentConfig {
        &self.config
    }

    pub fn agent(&self) -> &TabularAgent {
        &self.agent
    }

    /// One training episode (behaviour policy, subgoal testing), then its updates.
    pub fn train_episode(&mut self, env: &mut FourRooms, rng: &mut Rng) -> EpisodeOutcome {
        let outcome = self.collect_episode(env, rng);
        self.learn();
        outcome
    }

    /// The rollout half of [`Self::train_episode`]: one training episode whose transitions are
    /// kept for [`Self::learn`].
    pub fn collect_episode(&mut self, env: &mut FourRooms, rng: &mut Rng) -> EpisodeOutcome {
        self.hierarchy.run_episode(
            env,
            &mut self.agent,
            &mut self.exploration,
            Mode::Train,
            rng,
            &mut self.buffer,
        )
    }

    /// The update half of [`Self::train_episode`]: with [`TabularConfig::all_segments`], the
    /// stretches of the episode's path at every level above 0; then one Q-learning update per
    /// collected transition, newest first (penalties after the stretches, so that a failed test
    /// has the last word in its episode). [`TabularAgent::level_stats`] then describes these
    /// updates.
    pub fn learn(&mut self) {
        self.agent.start_stats_window();
        if let Some(replay) = &mut self.replay {
            // Transitions the agent skips as contained would be no-op draws.
            for r in &self.buffer.records {
                if !self.agent.contained(r.level, r.kind) {
                    replay.levels[r.level].push(*r);
                }
            }
        }
        if self.agent.all_segments() && self.agent.num_levels() > 1 {
            self.trace_path();
            for level in 1..self.agent.num_levels() {
                self.agent.update_segments(level, &self.path);
            }
        }
        self.buffer.drain_newest_first(&mut self.agent);
        if let Some(replay) = &mut self.replay {
            for (level, ring) in replay.levels.iter().enumerate() {
                if ring.records.is_empty() {
                    continue;
                }
                for _ in 0..replay.updates {
                    let r = &ring.records[replay.rng.below(ring.records.len())];
                    self.agent.push(level, &r.transition());
                }
            }
        }
    }

    /// Fills [`Self::path`] from level 0's hindsight action transitions, one per move in the
    /// order made: the first one's state, then every next state.
    fn trace_path(&mut self) {
        self.path.clear();
        let grid = self.agent.grid();
        // Every state of a four-rooms episode is a free cell.
        let cell = |p: &[f32]| {
            grid.index_of_point(p)
                .expect("four-rooms states are free cells")
        };
        let moves = self
            .buffer
            .records
            .iter()
            .filter(|r| r.level == 0 && r.kind == TransitionKind::HindsightAction);
        for r in moves {
            if self.path.is_empty() {
                self.path.push(cell(&r.state));
            }
            self.path.push(cell(&r.next_state));
        }
    }

    /// One greedy test episode; learns nothing.
    pub fn test_episode(&mut self, env: &mut FourRooms, rng: &mut Rng) -> EpisodeOutcome {
        self.hierarchy.run_episode(
            env,
            &mut self.agent,
            &mut self.exploration,
            Mode::Test,
            rng,
            &mut NullSink,
        )
    }

    /// Fraction of `episodes` greedy test episodes that reach the end goal.
    pub fn success_rate(&mut self, env: &mut FourRooms, rng: &mut Rng, episodes: usize) -> f32 {
        let wins = (0..episodes)
            .filter(|_| self.test_episode(env, rng).success)
            .count();
        wins as f32 / episodes.max(1) as f32
    }
}

/// A learning-curve experiment: `trials` independent learners of `levels` levels on a
/// `size x size` four-rooms grid, each trained for `episodes` episodes and tested greedily on
/// `test_episodes` episodes before training and after every `eval_every` training episodes.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CurveSpec {
    pub size: usize,
    pub levels: usize,
    pub trials: usize,
    pub episodes: usize,
    pub eval_every: usize,
    pub test_episodes: usize,
    pub seed: u64,
}

/// Mean greedy success over the trials, after `episodes[j]` training episodes.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SuccessCurve {
    pub episodes: Vec<usize>,
    pub mean_success: Vec<f32>,
}

/// Runs `spec` with the environment's default hyperparameters for `spec.levels` levels.
pub fn success_curve(
    spec: &CurveSpec,
    tabular: &TabularConfig,
) -> Result<SuccessCurve, TabularError> {
    let env = FourRooms::new(spec.size)?;
    let config = hac_core::Env::default_config(&env, spec.levels);
    success_curve_with(spec, &config, tabular)
}

/// Runs `spec` with explicit hyperparameters (`config.levels` overrides `spec.levels`).
/// Deterministic for `spec.seed`; trial `t` draws from its own generator, forked in order.
pub fn success_curve_with(
    spec: &CurveSpec,
    config: &AgentConfig,
    tabular: &TabularConfig,
) -> Result<SuccessCurve, TabularError> {
    let eval_every = spec.eval_every.max(1);
    let points: Vec<usize> = (0..=spec.episodes)
        .filter(|e| e % eval_every == 0 || *e == spec.episodes)
        .collect();
    let mut sums = vec![0.0f64; points.len()];
    let mut seeds = Rng::seed_from(spec.seed);
    for _ in 0..spec.trials {
        let mut rng = seeds.fork();
        let mut eval_rng = rng.fork();
        let mut env = FourRooms::new(spec.size)?;
        let mut learner = TabularHac::new(&env, config.clone(), tabular, &mut rng)?;
        let mut trained = 0;
        for (sum, &point) in sums.iter_mut().zip(&points) {
            while trained < point {
                learner.train_episode(&mut env, &mut rng);
                trained += 1;
            }
            *sum += f64::from(learner.success_rate(&mut env, &mut eval_rng, spec.test_episodes));
        }
    }
    let trials = spec.trials.max(1) as f64;
    Ok(SuccessCurve {
        episodes: points,
        mean_success: sums.iter().map(|s| (s / trials) as f32).collect(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn curve_points_and_determinism() {
        let spec = CurveSpec {
            size: 5,
            levels: 2,
            trials: 2,
            episodes: 25,
            eval_every: 10,
            test_episodes: 5,
            seed: 9,
        };
        let a = success_curve(&spec, &TabularConfig::default()).unwrap();
        assert_eq!(a.episodes, [0, 10, 20, 25]);
        assert!(a.mean_success.iter().all(|s| (0.0..=1.0).contains(s)));
        assert_eq!(a, success_curve(&spec, &TabularConfig::default()).unwrap());
    }

    #[test]
    fn replay_adds_its_updates_per_level_and_stays_deterministic() {
        let env = FourRooms::new(5).unwrap();
        let config = hac_core::Env::default_config(&env, 2);
        let run = |tabular: &TabularConfig| {
            let mut rng = Rng::seed_from(3);
            let mut env = FourRooms::new(5).unwrap();
            let mut hac = TabularHac::new(&env, config.clone(), tabular, &mut rng).unwrap();
            let mut sweeps = 0;
            for _ in 0..5 {
                let before = hac.agent().updates();
                hac.collect_episode(&mut env, &mut rng);
                sweeps += hac.buffer.records.len() as u64;
                hac.learn();
                assert!(hac.agent().updates() > before);
            }
            (
                hac.agent().updates() + hac.agent().skipped(),
                sweeps,
                hac.agent().tables.clone(),
            )
        };
        // Every transition updated as it comes (no stretches of the path).
        let one_by_one = TabularConfig {
            all_segments: false,
            ..TabularConfig::default()
        };
        let (plain, sweeps, _) = run(&one_by_one);
        assert_eq!(
            plain, sweeps,
            "without replay each transition is updated once"
        );
        let replaying = TabularConfig {
            replay_updates: 7,
            replay_capacity: 50,
            ..one_by_one.clone()
        };
        let (updates, sweeps, tables) = run(&replaying);
        // Every level has transitions from the first episode on: 7 more per level per episode.
        assert_eq!(updates, sweeps + 5 * 2 * 7);
        assert_eq!(tables, run(&replaying).2, "deterministic for a seed");
        let bad = TabularConfig {
            replay_capacity: 0,
            ..replaying
        };
        assert!(matches!(bad.validate(), Err(e) if e.key == "replay_capacity"));

        // With the stretches of the path, the upper level's hindsight action and HER
        // transitions are contained in them: its ring keeps only penalties, level 0 keeps all.
        let segments = TabularConfig {
            all_segments: true,
            replay_updates: 7,
            replay_capacity: 10_000,
            ..TabularConfig::default()
        };
        let mut rng = Rng::seed_from(3);
        let mut env = FourRooms::new(5).unwrap();
        let mut hac = TabularHac::new(&env, config.clone(), &segments, &mut rng).unwrap();
        let (mut level0, mut penalties) = (0, 0);
        for _ in 0..20 {
            hac.collect_episode(&mut env, &mut rng);
            let records = &hac.buffer.records;
            level0 += records.iter().filter(|r| r.level == 0).count();
            penalties += records
                .iter()
                .filter(|r| r.level == 1 && r.kind == TransitionKind::SubgoalPenalty)
                .count();
            hac.learn();
        }
        let rings = &hac.replay.as_ref().unwrap().levels;
        assert_eq!(rings[0].records.len(), level0);
        assert_eq!(rings[1].records.len(), penalties);
        assert!(
            rings[1]
                .records
                .iter()
                .all(|r| r.kind == TransitionKind::SubgoalPenalty)
        );
    }

    #[test]
    fn all_segments_learn_from_the_episode_path_of_moves() {
        let env = FourRooms::new(5).unwrap();
        let config = hac_core::Env::default_config(&env, 3);
        let tabular = TabularConfig {
            all_segments: true,
            ..TabularConfig::default()
        };
        let mut rng = Rng::seed_from(4);
        let mut env = FourRooms::new(5).unwrap();
        let mut hac = TabularHac::new(&env, config.clone(), &tabular, &mut rng).unwrap();
        for _ in 0..3 {
            let outcome = hac.collect_episode(&mut env, &mut rng);
            hac.trace_path();
            // The start cell, then one cell per move, each the same as or next to the last.
            assert_eq!(hac.path.len(), outcome.steps + 1);
            let grid = hac.agent().grid();
            for w in hac.path.windows(2) {
                let (a, b) = (grid.cell(w[0]), grid.cell(w[1]));
                assert!(a.row.abs_diff(b.row) + a.col.abs_diff(b.col) <= 1);
            }
            let starts = hac_core::Env::state(&env);
            assert_eq!(
                grid.cell(*hac.path.last().unwrap()).to_f32(),
                [starts[0], starts[1]]
            );
            // Updates: level 0's transitions one by one, the stretches of both upper levels
            // for every goal, penalties one by one; nothing else of the upper levels.
            let records = &hac.buffer.records;
            let one_by_one = records
                .iter()
                .filter(|r| r.level == 0 || r.kind == TransitionKind::SubgoalPenalty)
                .count() as u64;
            let mut probe =
                TabularAgent::new(env.grid(), &config, &tabular, Rng::seed_from(0)).unwrap();
            let stretches =
                (probe.update_segments(1, &hac.path) + probe.update_segments(2, &hac.path)) as u64;
            let before = hac.agent().updates();
            hac.learn();
            let cells = env.grid().num_cells() as u64;
            assert_eq!(
                hac.agent().updates() - before,
                one_by_one + stretches * cells
            );
        }
        assert_eq!(hac.agent().skipped(), 0, "radius H^i holds every stretch");
    }

    #[test]
    fn bad_sizes_and_configs_are_errors() {
        let spec = CurveSpec {
            size: 3,
            levels: 2,
            trials: 1,
            episodes: 1,
            eval_every: 1,
            test_episodes: 1,
            seed: 0,
        };
        assert!(matches!(
            success_curve(&spec, &TabularConfig::default()),
            Err(TabularError::Grid(_))
        ));
        let spec = CurveSpec { size: 5, ..spec };
        let bad = TabularConfig {
            learning_rate: 0.0,
            ..TabularConfig::default()
        };
        assert!(matches!(
            success_curve(&spec, &bad),
            Err(TabularError::Config(e)) if e.key == "learning_rate"
        ));
    }
}
