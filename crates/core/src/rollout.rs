//! The hierarchy rollout: one episode through k levels, producing HAC's three transition kinds.
//!
//! The recursion follows the paper (and its reference implementation) step for step:
//! - level `i` makes up to `H` attempts at its goal; an attempt of level 0 is one primitive
//!   action, an attempt of level `i > 0` proposes a subgoal and runs level `i - 1` on it;
//! - after every primitive action all levels' goals are checked; a level returns as soon as the
//!   goal of that level or of any level above is reached, the episode's action budget is spent
//!   (or the environment terminates), or it used its `H` attempts (*maxed out* if its own goal
//!   was not reached); in test mode the top level ignores the `H` limit;
//! - per attempt a level stores a hindsight action transition, remembers the attempt for HER, and,
//!   if it tested a subgoal that the level below missed after maxing out, a penalty transition;
//! - when a level returns it replays its attempts relabelled with achieved goals (HER).
//!
//! `terminal` means "do not bootstrap": a reached goal, a penalty, or a next state in which the
//! environment itself ended the episode (only tasks like mountain-car ever do; the paper's tasks
//! never terminate, so for them terminal is exactly "goal reached").
//!
//! Within a level the order of transitions handed to the sink is: per attempt the hindsight
//! action transition then (if any) the penalty; when the level returns, the HER copies grouped by
//! hindsight goal in ascending attempt index.
//!
//! All randomness of the behaviour policy goes through [`Exploration`], so the same code serves
//! training, test episodes, and scripted tests; [`Hierarchy`] owns every buffer, so an episode
//! allocates nothing once the buffers have grown to the episode's size.

use crate::{
    AgentConfig, Bounds, Env, EnvSpec, Mode, Rng, Transition, TransitionKind, TransitionSink,
    within_goal,
};

/// Upper bound on `AgentConfig::num_replay_goals`.
pub const MAX_REPLAY_GOALS: usize = 16;

/// The deterministic (greedy) policy of every level, as the rollout sees it.
pub trait Policy {
    /// Writes level `level`'s greedy output for `(state, goal)` into `action`.
    fn act(&mut self, level: usize, state: &[f32], goal: &[f32], action: &mut [f32]);
}

/// The random choices of the behaviour policy in training episodes.
pub trait Exploration {
    /// Turns level `level`'s greedy output for `state` into its behaviour action, in place; the
    /// result is clipped to `bounds` by the rollout afterwards.
    fn explore(&mut self, level: usize, state: &[f32], bounds: &Bounds, action: &mut [f32]);
    /// Whether the subgoal that level `level` (> 0) just proposed is tested.
    fn test_subgoal(&mut self, level: usize) -> bool;
    /// A uniformly random attempt index in `0..n` whose achieved goal becomes a hindsight goal.
    fn replay_goal_index(&mut self, level: usize, n: usize) -> usize;
}

/// HAC's behaviour policy: with probability `random_action_prob` a uniform action within bounds,
/// otherwise the greedy output plus `N(0, std_d)` noise; subgoals tested with probability lambda.
#[derive(Debug, Clone)]
pub struct GaussianExploration {
    rng: Rng,
    random_action_prob: f32,
    subgoal_test_prob: f32,
    /// Absolute noise std per level and dimension.
    noise_std: Vec<Vec<f32>>,
}

impl GaussianExploration {
    pub fn new(spec: &EnvSpec, config: &AgentConfig, rng: Rng) -> Self {
        let noise_std = (0..config.levels)
            .map(|level| {
                let bounds = spec.level_action_bounds(level);
                if level == 0 {
                    config.action_noise.std(bounds)
                } else {
                    config.subgoal_noise.std(bounds)
                }
            })
            .collect();
        Self {
            rng,
            random_action_prob: config.random_action_prob,
            subgoal_test_prob: config.subgoal_test_prob,
            noise_std,
        }
    }

    /// Draws from `rng` from now on (one training episode's own stream under episode turns).
    pub fn reseed(&mut self, rng: Rng) {
        self.rng = rng;
    }

    /// The stream it draws from next.
    pub fn rng(&self) -> &Rng {
        &self.rng
    }
}

impl Exploration for GaussianExploration {
    fn explore(&mut self, level: usize, _state: &[f32], bounds: &Bounds, action: &mut [f32]) {
        if self.rng.bernoulli(self.random_action_prob) {
            bounds.sample(&mut self.rng, action);
        } else {
            for (a, std) in action.iter_mut().zip(&self.noise_std[level]) {
                *a += std * self.rng.normal();
            }
        }
    }

    fn test_subgoal(&mut self, _level: usize) -> bool {
        self.rng.bernoulli(self.subgoal_test_prob)
    }

    fn replay_goal_index(&mut self, _level: usize, n: usize) -> usize {
        self.rng.below(n)
    }
}

/// What one episode did.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct EpisodeOutcome {
    /// The end goal was reached.
    pub success: bool,
    /// Primitive actions executed.
    pub steps: usize,
}

/// What one level did over one or more episodes: how often it was given a goal and reached it,
/// how many attempts it made, and (in training) how its subgoal tests went. The diagnostic of
/// a hierarchy that does not learn: it says which level fails to reach the goals the level above
/// sets it (`hac eval` prints it per level).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize)]
pub struct LevelCounts {
    /// Times the level was given a goal and ran until it returned control upward.
    pub calls: u64,
    /// Calls that ended with the level's own goal reached.
    pub reached: u64,
    /// Calls that used all `H` attempts without reaching the level's goal.
    pub maxed_out: u64,
    /// Attempts: primitive actions at level 0, subgoals proposed above.
    pub attempts: u64,
    /// Subgoals this level proposed that were tested (levels above 0, training episodes only):
    /// chosen with probability lambda, or every subgoal while a level above tests its own.
    pub tested: u64,
    /// Tested subgoals that the level below missed after maxing out: the penalty transitions.
    pub penalties: u64,
}

impl LevelCounts {
    /// Adds `other`'s counts to these.
    pub fn add(&mut self, other: &LevelCounts) {
        self.calls += other.calls;
        self.reached += other.reached;
        self.maxed_out += other.maxed_out;
        self.attempts += other.attempts;
        self.tested += other.tested;
        self.penalties += other.penalties;
    }

    /// The share of calls that reached the level's goal (0 with no calls).
    pub fn reached_rate(&self) -> f64 {
        ratio(self.reached, self.calls)
    }

    /// The share of calls that used all `H` attempts without reaching the goal (0 with no
    /// calls).
    pub fn maxed_out_rate(&self) -> f64 {
        ratio(self.maxed_out, self.calls)
    }

    /// The share of tested subgoals that were penalised (0 with none tested).
    pub fn penalty_rate(&self) -> f64 {
        ratio(self.penalties, self.tested)
    }

    /// Attempts per call (0 with no calls).
    pub fn attempts_per_call(&self) -> f64 {
        ratio(self.attempts, self.calls)
    }
}

fn ratio(num: u64, den: u64) -> f64 {
    if den == 0 {
        0.0
    } else {
        num as f64 / den as f64
    }
}

/// Attempts of one level since it was last called, kept for hindsight goal replay.
#[derive(Debug, Default)]
struct HerList {
    len: usize,
    states: Vec<f32>,
    actions: Vec<f32>,
    next_states: Vec<f32>,
    achieved: Vec<f32>,
    /// Whether the attempt ended in a state where the environment terminated.
    ended: Vec<bool>,
}

/// Per-level scratch that must survive the recursive call into the level below.
#[derive(Debug)]
struct LevelState {
    /// State at the start of the current attempt.
    state: Vec<f32>,
    /// The action (subgoal) proposed in the current attempt.
    action: Vec<f32>,
    /// The hindsight action of the current attempt.
    hindsight: Vec<f32>,
    /// Achieved goal of the current attempt, in this level's goal space.
    achieved: Vec<f32>,
    /// The level's goal for the current call.
    goal: Vec<f32>,
    /// Whether the goal was reached at the last check.
    reached: bool,
    /// Whether the last call used all `H` attempts without reaching the goal.
    maxed_out: bool,
    her: HerList,
    /// What this level did in the current (or last) episode.
    counts: LevelCounts,
}

/// The box `clip_hindsight_actions` clips hindsight actions into: the subgoal bounds, open on
/// the dimensions that are angles (which the projection wraps, and a clip would move along the
/// circle).
fn hindsight_clip_bounds(spec: &EnvSpec) -> Bounds {
    let angles = spec.relative_goal_angles();
    let mut bounds = spec.subgoal_bounds.clone();
    for d in (0..angles.len()).filter(|&d| angles[d]) {
        bounds.low[d] = f32::NEG_INFINITY;
        bounds.high[d] = f32::INFINITY;
    }
    bounds
}

/// Runs episodes through k levels; owns every buffer so that episodes allocate nothing.
#[derive(Debug)]
pub struct Hierarchy {
    spec: EnvSpec,
    horizon: usize,
    num_replay_goals: usize,
    /// The subgoal bounds with the angle dimensions opened up, when hindsight actions are
    /// clipped into them (`clip_hindsight_actions`).
    hindsight_clip: Option<Bounds>,
    levels: Vec<LevelState>,
    /// The current observation.
    state: Vec<f32>,
    /// Scratch for goal checks.
    projected: Vec<f32>,
    /// The end-goal projection of the episode's first state, and of its last.
    start_achieved: Vec<f32>,
    final_achieved: Vec<f32>,
    steps: usize,
    success: bool,
}

/// Borrowed collaborators of one episode.
struct Episode<'a> {
    env: &'a mut dyn Env,
    policy: &'a mut dyn Policy,
    exploration: &'a mut dyn Exploration,
    sink: &'a mut dyn TransitionSink,
    mode: Mode,
}

impl Hierarchy {
    /// A rollout for `config.levels` levels of an environment described by `spec`.
    pub fn new(spec: &EnvSpec, config: &AgentConfig) -> Self {
        let k = config.levels;
        assert!(k >= 1, "a hierarchy needs at least one level");
        assert!(
            config.num_replay_goals <= MAX_REPLAY_GOALS,
            "too many replay goals"
        );
        for (angles, dim) in [
            (&spec.end_goal_angles, spec.end_goal_dim),
            (&spec.subgoal_angles, spec.subgoal_dim()),
        ] {
            assert!(
                angles.is_empty() || angles.len() == dim,
                "{}: angle flags for {} of {dim} goal dimensions",
                spec.name,
                angles.len()
            );
        }
        let levels = (0..k)
            .map(|level| {
                let dims = spec.level_dims(level, k);
                LevelState {
                    state: vec![0.0; dims.state],
                    action: vec![0.0; dims.action],
                    hindsight: vec![0.0; dims.action],
                    achieved: vec![0.0; dims.goal],
                    goal: vec![0.0; dims.goal],
                    reached: false,
                    maxed_out: false,
                    her: HerList::default(),
                    counts: LevelCounts::default(),
                }
            })
            .collect();
        Self {
            spec: spec.clone(),
            horizon: config.horizon,
            num_replay_goals: config.num_replay_goals,
            hindsight_clip: config
                .clip_hindsight_actions
                .then(|| hindsight_clip_bounds(spec)),
            levels,
            state: vec![0.0; spec.state_dim],
            projected: vec![0.0; spec.end_goal_dim.max(spec.subgoal_dim())],
            start_achieved: vec![0.0; spec.end_goal_dim],
            final_achieved: vec![0.0; spec.end_goal_dim],
            steps: 0,
            success: false,
        }
    }

    pub fn num_levels(&self) -> usize {
        self.levels.len()
    }

    /// The end goal of the current (or last) episode.
    pub fn end_goal(&self) -> &[f32] {
        &self.levels[self.levels.len() - 1].goal
    }

    /// The end-goal projection of the current (or last) episode's first state: what the end
    /// goal measured before the agent acted (`hac eval` compares it with the last state's).
    pub fn start_achieved(&self) -> &[f32] {
        &self.start_achieved
    }

    /// The end-goal projection of the current (or last) episode's last state.
    pub fn final_achieved(&self) -> &[f32] {
        &self.final_achieved
    }

    /// The spec of the environment this rollout was made for.
    pub fn spec(&self) -> &EnvSpec {
        &self.spec
    }

    /// What level `level` did in the current (or last) episode.
    pub fn level_counts(&self, level: usize) -> &LevelCounts {
        &self.levels[level].counts
    }

    /// Resets `env`, draws an end goal for `mode`, and runs one episode. In `Mode::Train` every
    /// transition goes to `sink` and exploration decides the behaviour; in `Mode::Test` every level
    /// is greedy and nothing is stored.
    pub fn run_episode(
        &mut self,
        env: &mut dyn Env,
        policy: &mut dyn Policy,
        exploration: &mut dyn Exploration,
        mode: Mode,
        rng: &mut Rng,
        sink: &mut dyn TransitionSink,
    ) -> EpisodeOutcome {
        env.reset(rng);
        let top = self.levels.len() - 1;
        env.sample_end_goal(rng, mode, &mut self.levels[top].goal);
        self.run_from_current(env, policy, exploration, mode, sink)
    }

    /// Runs one episode from the environment's current state towards `end_goal` (no reset).
    pub fn run_episode_from(
        &mut self,
        env: &mut dyn Env,
        end_goal: &[f32],
        policy: &mut dyn Policy,
        exploration: &mut dyn Exploration,
        mode: Mode,
        sink: &mut dyn TransitionSink,
    ) -> EpisodeOutcome {
        let top = self.levels.len() - 1;
        self.levels[top].goal.copy_from_slice(end_goal);
        self.run_from_current(env, policy, exploration, mode, sink)
    }

    fn run_from_current(
        &mut self,
        env: &mut dyn Env,
        policy: &mut dyn Policy,
        exploration: &mut dyn Exploration,
        mode: Mode,
        sink: &mut dyn TransitionSink,
    ) -> EpisodeOutcome {
        self.state.copy_from_slice(env.state());
        env.project_end_goal(&self.state, &mut self.start_achieved);
        self.steps = 0;
        self.success = false;
        for level in &mut self.levels {
            level.reached = false;
            level.maxed_out = false;
            level.counts = LevelCounts::default();
        }
        let mut episode = Episode {
            env,
            policy,
            exploration,
            sink,
            mode,
        };
        let top = self.levels.len() - 1;
        self.run_level(&mut episode, top, false);
        episode
            .env
            .project_end_goal(&self.state, &mut self.final_achieved);
        EpisodeOutcome {
            success: self.success,
            steps: self.steps,
        }
    }

    /// Runs level `i` until it returns; `tested` means a level above is testing its subgoal, so
    /// this level acts greedily. Returns the highest level whose goal was reached at the last
    /// primitive action.
    fn run_level(&mut self, ep: &mut Episode<'_>, i: usize, tested: bool) -> Option<usize> {
        let top = self.levels.len() - 1;
        let train = ep.mode == Mode::Train;
        self.levels[i].her.len = 0;
        self.levels[i].maxed_out = false;
        let mut attempts = 0;
        loop {
            let bounds = self.spec.level_action_bounds(i);
            let lv = &mut self.levels[i];
            lv.state.copy_from_slice(&self.state);
            ep.policy.act(i, &self.state, &lv.goal, &mut lv.action);
            let mut test_next = tested;
            if train && !tested {
                ep.exploration
                    .explore(i, &self.state, bounds, &mut lv.action);
                if i > 0 {
                    test_next = ep.exploration.test_subgoal(i);
                }
            }
            bounds.clip(&mut lv.action);
            // A tested subgoal, whether this level chose to test it or a test above propagates.
            lv.counts.tested += u64::from(i > 0 && test_next);

            let highest_reached = if i > 0 {
                let (below, this) = self.levels.split_at_mut(i);
                below[i - 1].goal.copy_from_slice(&this[0].action);
                self.run_level(ep, i - 1, test_next)
            } else {
                ep.env.step(&self.levels[0].action);
                self.steps += 1;
                self.state.copy_from_slice(ep.env.state());
                self.check_goals(&*ep.env)
            };
            attempts += 1;

            let terminated = ep.env.terminated();
            if train {
                self.store_attempt(ep, i, test_next, terminated);
            }

            let budget_spent = self.steps >= self.spec.max_actions || terminated;
            let higher_reached = highest_reached.is_some_and(|h| h >= i);
            let out_of_attempts = attempts >= self.horizon && !(ep.mode == Mode::Test && i == top);
            if higher_reached || budget_spent || out_of_attempts {
                let lv = &mut self.levels[i];
                lv.maxed_out = attempts >= self.horizon && !lv.reached;
                lv.counts.calls += 1;
                lv.counts.attempts += attempts as u64;
                lv.counts.reached += u64::from(lv.reached);
                lv.counts.maxed_out += u64::from(lv.maxed_out);
                if train {
                    self.replay_goals(ep, i);
                }
                return highest_reached;
            }
        }
    }

    /// Checks every level's goal against the current state; returns the highest level reached.
    fn check_goals(&mut self, env: &dyn Env) -> Option<usize> {
        let top = self.levels.len() - 1;
        let mut highest = None;
        for (l, level) in self.levels.iter_mut().enumerate() {
            let projected = if l == top {
                let p = &mut self.projected[..self.spec.end_goal_dim];
                env.project_end_goal(&self.state, p);
                &*p
            } else {
                let p = &mut self.projected[..self.spec.subgoal_dim()];
                env.project_subgoal(&self.state, p);
                &*p
            };
            let (threshold, angles) = self.spec.goal_test(l == top);
            level.reached = within_goal(projected, &level.goal, threshold, angles);
            if level.reached {
                highest = Some(l);
            }
        }
        if self.levels[top].reached {
            self.success = true;
        }
        highest
    }

    /// Stores the hindsight action transition and (if due) the penalty of level `i`'s last
    /// attempt, and remembers the attempt for HER. `terminated`: the environment ended the episode
    /// in the attempt's next state, so nothing follows it and the target must not bootstrap.
    fn store_attempt(
        &mut self,
        ep: &mut Episode<'_>,
        i: usize,
        tested_subgoal: bool,
        terminated: bool,
    ) {
        let top = self.levels.len() - 1;
        let (below, rest) = self.levels.split_at_mut(i);
        let lv = &mut rest[0];
        let lower = below.last();

        // The subgoal counts as the action taken only if the level below reached it.
        match lower {
            Some(lower) if !lower.reached => {
                ep.env.project_subgoal(&self.state, &mut lv.hindsight);
                if let Some(bounds) = &self.hindsight_clip {
                    bounds.clip(&mut lv.hindsight);
                }
            }
            _ => lv.hindsight.copy_from_slice(&lv.action),
        }
        let (reward, terminal) = if lv.reached {
            (0.0, true)
        } else {
            (-1.0, terminated)
        };
        ep.sink.push(
            i,
            &Transition {
                kind: TransitionKind::HindsightAction,
                state: &lv.state,
                action: &lv.hindsight,
                reward,
                next_state: &self.state,
                goal: &lv.goal,
                terminal,
                extra: &[],
            },
        );

        if i == top {
            ep.env.project_end_goal(&self.state, &mut lv.achieved);
        } else {
            ep.env.project_subgoal(&self.state, &mut lv.achieved);
        }
        let her = &mut lv.her;
        let n = her.len;
        for (buf, src) in [
            (&mut her.states, &lv.state),
            (&mut her.actions, &lv.hindsight),
            (&mut her.next_states, &self.state),
            (&mut her.achieved, &lv.achieved),
        ] {
            // Truncate first so that a list reused across calls overwrites instead of growing.
            buf.truncate(n * src.len());
            buf.extend_from_slice(src);
        }
        her.ended.truncate(n);
        her.ended.push(terminated);
        her.len = n + 1;

        if tested_subgoal && lower.is_some_and(|l| l.maxed_out) {
            lv.counts.penalties += 1;
            ep.sink.push(
                i,
                &Transition {
                    kind: TransitionKind::SubgoalPenalty,
                    state: &lv.state,
                    action: &lv.action,
                    reward: -(self.horizon as f32),
                    next_state: &self.state,
                    goal: &lv.goal,
                    terminal: true,
                    extra: &[],
                },
            );
        }
    }

    /// HER: relabels every attempt of level `i`'s call with `num_replay_goals` achieved goals
    /// (random ones plus the last attempt's), then forgets the attempts.
    fn replay_goals(&mut self, ep: &mut Episode<'_>, i: usize) {
        let top = self.levels.len() - 1;
        let lv = &mut self.levels[i];
        let n = lv.her.len;
        let goals = self.num_replay_goals.min(n);
        if goals == 0 {
            return;
        }
        // A fixed array keeps this allocation-free; the config caps the count.
        let mut picks = [0usize; MAX_REPLAY_GOALS];
        let picks = &mut picks[..goals];
        for p in picks[..goals - 1].iter_mut() {
            *p = ep.exploration.replay_goal_index(i, n);
        }
        picks[goals - 1] = n - 1;
        picks.sort_unstable();
        let (threshold, angles) = self.spec.goal_test(i == top);
        let her = &lv.her;
        let (sd, ad, gd) = (self.spec.state_dim, lv.action.len(), lv.goal.len());
        for &pick in picks.iter() {
            let goal = &her.achieved[pick * gd..(pick + 1) * gd];
            for j in 0..n {
                let achieved = &her.achieved[j * gd..(j + 1) * gd];
                let reached = within_goal(achieved, goal, threshold, angles);
                ep.sink.push(
                    i,
                    &Transition {
                        kind: TransitionKind::HindsightGoal,
                        state: &her.states[j * sd..(j + 1) * sd],
                        action: &her.actions[j * ad..(j + 1) * ad],
                        reward: if reached { 0.0 } else { -1.0 },
                        next_state: &her.next_states[j * sd..(j + 1) * sd],
                        goal,
                        terminal: reached || her.ended[j],
                        extra: &[],
                    },
                );
            }
        }
        lv.her.len = 0;
    }
}
