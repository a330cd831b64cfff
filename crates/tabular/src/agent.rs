//! The tabular agent: one Q table per level, indexed by (state cell, goal cell, action slot).
//!
//! - Level 0's actions are the four moves.
//! - A level `i > 0` proposes a subgoal *relative to its current cell*: any free cell other than
//!   the current one within Manhattan distance `r_i`. Level `i - 1` gets `H` attempts of at most
//!   `H^(i-1)` moves each, so nothing beyond `H^i` moves can be reached and `r_i = H^i` loses no
//!   reachable subgoal. Storing subgoals as offsets keeps a table at
//!   `cells x cells x slots(r_i)` entries instead of `cells^3` (625^3 on a 25 x 25 grid). When a
//!   table would still exceed [`TabularConfig::max_table_entries`], `r_i` shrinks until it fits.
//! - Values start at `-H` by default (see [`InitialQ`] for why not at 0 like the critic).
//! - Update: `Q += alpha * (y - Q)` with `y = r + gamma * (1 - terminal) * max_a' Q(s', g, a')`
//!   (the max over the choices allowed at `s'`), clipped to `[-H, 0]` like the critic
//!   (docs/ALGORITHM.md).
//!
//! Transitions whose state, goal or action has no place in the tables (a wall cell, a subgoal
//! beyond the radius) are skipped and counted: they describe choices the level can never make.

use std::sync::Arc;

use hac_core::{AgentConfig, ConfigError, Policy, Rng, Transition, TransitionKind, TransitionSink};
use serde::{Deserialize, Serialize};

use crate::grid::{Grid, GridError, MOVES};

/// The value every table entry starts from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum InitialQ {
    /// `-H`: an untried choice ranks with a failed subgoal test, so the greedy policy follows
    /// the paths it knows.
    Pessimistic,
    /// `0`, like the critic's initial output. A network generalises from what it has seen; a
    /// table does not, so every untried (state, goal, action) looks best and the greedy policy
    /// chases unvisited entries instead of known paths (on 10 x 10, 2 levels: about 0.2 greedy
    /// success after 3000 episodes, against 1.0 after 1000 when pessimistic).
    Optimistic,
}

/// Hyperparameters of the tabular learner beyond [`AgentConfig`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TabularConfig {
    /// Step size alpha of the Q-learning update, in (0, 1].
    pub learning_rate: f32,
    /// Where every table entry starts.
    pub initial_q: InitialQ,
    /// Upper bound on the entries (f32 values) of one level's table; caps the subgoal radius.
    pub max_table_entries: usize,
    /// Experience replay: after each training episode's sweep, each level also re-applies the
    /// update to this many transitions drawn uniformly from its earlier ones (the last
    /// `replay_capacity`), re-bootstrapping them from the current values as the neural learner
    /// does with its replay batches. 0: each transition is updated once, when its episode ends.
    /// Transitions the agent skips as contained (see [`Self::all_goals`] and
    /// [`Self::all_segments`]) are not kept: with `all_segments`, an upper level replays its
    /// penalties only, since the stretches of a path are learned once, after their episode.
    #[serde(default)]
    pub replay_updates: usize,
    /// Transitions each level keeps for replay (the oldest are overwritten).
    #[serde(default = "default_replay_capacity")]
    pub replay_capacity: usize,
    /// Hindsight with every goal ("all-goals updating"): a hindsight action transition updates
    /// the entry of its `(state, action)` for every goal cell, with reward and terminal
    /// recomputed against that goal, instead of for its own goal only. The move (or achieved
    /// subgoal) and where it led do not depend on the goal, so every such update is valid
    /// experience; HER's copies, which relabel the same transitions with a few achieved goals,
    /// are then contained in it and skipped. Penalty transitions keep their one goal.
    #[serde(default)]
    pub all_goals: bool,
    /// Hindsight over every stretch of the path ("all-segments updating", the trailing-state
    /// updates of hierarchical Q-learning): after a training episode, each level `i > 0`
    /// learns, for every goal cell, that from any cell of the episode's path the cell reached
    /// `h <= H^i` moves later (the most level `i - 1` can cover in one subgoal) was a subgoal
    /// that got there. The level's own hindsight action transitions are such stretches and its
    /// HER copies relabel them, so both are then contained and skipped; subgoal penalties keep
    /// their goal and are applied after the stretches. Level 0 is not affected.
    ///
    /// On by default: it is what lets the upper levels of 3 learn as fast as those of 2, and
    /// with it the grid worlds show the paper's 3 > 2 > 1 (without it, with HAC's transitions
    /// alone, 2 > 3 > 1; docs/RESULTS.md has both).
    #[serde(default = "default_all_segments")]
    pub all_segments: bool,
}

fn default_replay_capacity() -> usize {
    100_000
}

fn default_all_segments() -> bool {
    true
}

impl Default for TabularConfig {
    fn default() -> Self {
        Self {
            // Moves are deterministic, so level 0 needs no averaging. Measured on 10 x 10 (20
            // trials, greedy success after 600 episodes, 1 / 2 / 3 levels): alpha 1.0 gives
            // 0.48 / 0.96 / 0.85, 0.8 gives 0.54 / 0.95 / 0.82, 0.5 gives 0.48 / 0.86 / 0.73.
            learning_rate: 1.0,
            initial_q: InitialQ::Pessimistic,
            // 128 MiB per level: no cap at all on 10 x 10; radius 6 on 25 x 25.
            max_table_entries: 1 << 25,
            replay_updates: 0,
            replay_capacity: default_replay_capacity(),
            all_goals: false,
            all_segments: default_all_segments(),
        }
    }
}

impl TabularConfig {
    pub fn validate(&self) -> Result<(), ConfigError> {
        if !(self.learning_rate > 0.0 && self.learning_rate <= 1.0) {
            return Err(ConfigError::invalid(
                "learning_rate",
                format!("must be in (0, 1], got {}", self.learning_rate),
            ));
        }
        if self.replay_updates > 0 && self.replay_capacity == 0 {
            return Err(ConfigError::invalid(
                "replay_capacity",
                "must be at least 1 when replay_updates is above 0".into(),
            ));
        }
        Ok(())
    }
}

/// Why a tabular agent cannot be built.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TabularError {
    #[error(transparent)]
    Config(#[from] ConfigError),
    #[error(transparent)]
    Grid(#[from] GridError),
    #[error(
        "level {level} needs a table of {entries} entries even with the smallest action set, \
         above max_table_entries = {max}"
    )]
    TableTooLarge {
        level: usize,
        entries: usize,
        max: usize,
    },
}

/// The subgoals of one level `> 0`: offsets within a Manhattan radius, numbered as table slots,
/// and per cell the slots that land on another free cell.
#[derive(Debug, Clone)]
struct SubgoalSet {
    radius: usize,
    /// Half-width of the box of offsets that can stay on the grid: `min(radius, size - 1)`.
    extent: usize,
    offsets: Vec<[i32; 2]>,
    /// `(dr + extent) * (2 extent + 1) + (dc + extent)` -> slot, or `u32::MAX` beyond the radius.
    slot_of: Vec<u32>,
    /// Allowed slots of cell `s`: `allowed[allowed_start[s]..allowed_start[s + 1]]`.
    allowed_start: Vec<u32>,
    allowed: Vec<u32>,
    /// `is_allowed[s * slots + a]`: slot `a` is among cell `s`'s allowed slots.
    is_allowed: Vec<bool>,
}

impl SubgoalSet {
    /// Number of slots for `radius` on a `size x size` grid.
    fn slot_count(size: usize, radius: usize) -> usize {
        let e = radius.min(size - 1) as i64;
        let r = radius as i64;
        (-e..=e)
            .map(|dr| (r - dr.abs()).min(e) * 2 + 1)
            .map(|n| n as usize)
            .sum()
    }

    fn new(grid: &Grid, radius: usize) -> Self {
        let extent = radius.min(grid.size() - 1);
        let (e, r) = (extent as i32, radius as i32);
        let width = 2 * extent + 1;
        let mut offsets = Vec::new();
        let mut slot_of = vec![u32::MAX; width * width];
        for dr in -e..=e {
            for dc in -e..=e {
                if dr.abs() + dc.abs() <= r {
                    slot_of[((dr + e) * (2 * e + 1) + dc + e) as usize] = offsets.len() as u32;
                    offsets.push([dr, dc]);
                }
            }
        }
        let mut allowed_start = vec![0];
        let mut allowed = Vec::new();
        let mut is_allowed = vec![false; grid.num_cells() * offsets.len()];
        for (s, &cell) in grid.cells().iter().enumerate() {
            for (slot, &o) in offsets.iter().enumerate() {
                if o != [0, 0] && cell.offset(o, grid.size()).is_some_and(|c| grid.is_free(c)) {
                    allowed.push(slot as u32);
                    is_allowed[s * offsets.len() + slot] = true;
                }
            }
            allowed_start.push(allowed.len() as u32);
        }
        Self {
            radius,
            extent,
            offsets,
            slot_of,
            allowed_start,
            allowed,
            is_allowed,
        }
    }

    /// Manhattan radius of the subgoals.
    fn radius(&self) -> usize {
        self.radius
    }

    /// Number of slots (offsets within the radius that fit the grid's extent).
    fn slots(&self) -> usize {
        self.offsets.len()
    }

    fn slot(&self, offset: [i32; 2]) -> Option<usize> {
        let e = self.extent as i32;
        if offset[0].abs() > e || offset[1].abs() > e {
            return None;
        }
        let i = ((offset[0] + e) * (2 * e + 1) + offset[1] + e) as usize;
        let slot = self.slot_of[i];
        (slot != u32::MAX).then_some(slot as usize)
    }

    /// The slot of subgoal cell `to` proposed from cell `from`, if within the radius.
    fn slot_between(&self, grid: &Grid, from: usize, to: usize) -> Option<usize> {
        let (from, to) = (grid.cell(from), grid.cell(to));
        self.slot([
            to.row as i32 - from.row as i32,
            to.col as i32 - from.col as i32,
        ])
    }
}

/// What one level chooses among.
#[derive(Debug, Clone)]
enum ActionSpace {
    Moves,
    Subgoals(SubgoalSet),
}

const ALL_MOVES: [u32; 4] = [0, 1, 2, 3];

impl ActionSpace {
    fn slots(&self) -> usize {
        match self {
            ActionSpace::Moves => MOVES.len(),
            ActionSpace::Subgoals(set) => set.slots(),
        }
    }

    /// Whether the level may choose slot `a` from cell `s`.
    fn is_allowed(&self, s: usize, a: usize) -> bool {
        match self {
            ActionSpace::Moves => true,
            ActionSpace::Subgoals(set) => set.is_allowed[s * set.slots() + a],
        }
    }

    /// The slots the level may choose from cell `s`.
    fn allowed(&self, s: usize) -> &[u32] {
        match self {
            ActionSpace::Moves => &ALL_MOVES,
            ActionSpace::Subgoals(set) => {
                &set.allowed[set.allowed_start[s] as usize..set.allowed_start[s + 1] as usize]
            }
        }
    }

    /// Writes the action of `slot` taken from cell `s`: the move index, or the subgoal cell.
    fn write(&self, grid: &Grid, s: usize, slot: usize, out: &mut [f32]) {
        match self {
            ActionSpace::Moves => out[0] = slot as f32,
            ActionSpace::Subgoals(set) => {
                let target = grid.cell(s).offset(set.offsets[slot], grid.size());
                out.copy_from_slice(&target.expect("allowed slots stay on the grid").to_f32());
            }
        }
    }

    /// The slot of `action` taken from cell `s`, if the table has one.
    fn slot_of(&self, grid: &Grid, s: usize, action: &[f32]) -> Option<usize> {
        match self {
            ActionSpace::Moves => {
                let a = action.first()?.round();
                (0.0..MOVES.len() as f32).contains(&a).then_some(a as usize)
            }
            ActionSpace::Subgoals(set) => set.slot_between(grid, s, grid.index_of_point(action)?),
        }
    }
}

/// What the agent and its exploration share: the state space and every level's action space.
#[derive(Debug)]
struct Spaces {
    grid: Grid,
    levels: Vec<ActionSpace>,
}

/// One level's learning statistics, for learning curves.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct LevelStats {
    /// Q-learning updates applied to the level so far.
    pub updates: u64,
    /// Mean squared temporal-difference error `(y - Q)^2` (before the update) over the current
    /// window, the tabular counterpart of the critic's loss; 0 for an empty window.
    pub mean_sq_td_error: f32,
    /// Mean value `Q` (before the update) of the entries updated in the current window.
    pub mean_q: f32,
}

/// Sums behind [`LevelStats`]; the window is what [`TabularAgent::start_stats_window`] opens.
#[derive(Debug, Clone, Copy, Default)]
struct LevelCounters {
    updates: u64,
    window: u64,
    sq_td_error: f64,
    q: f64,
}

/// Tabular HAC ("hierarchical Q-learning"): the greedy [`Policy`] of every level and, as a
/// [`TransitionSink`], the Q-learning update of every transition it receives.
#[derive(Debug)]
pub struct TabularAgent {
    shared: Arc<Spaces>,
    /// Per level, `Q[((s * cells) + g) * slots + a]`.
    pub(crate) tables: Vec<Vec<f32>>,
    /// Per level, `best[s * cells + g]`: the largest `Q(s, g, a)` over the slots allowed at `s`,
    /// the bootstrap value of every update whose next state is `s`. Kept in step with the
    /// table by [`Self::set`] (and rebuilt by [`Self::rebuild_best`] when a table is replaced),
    /// so that a bootstrap reads one value instead of scanning up to thousands of slots.
    best: Vec<Vec<f32>>,
    /// The value every entry starts from ([`InitialQ`]).
    pub(crate) initial_value: f32,
    horizon: f32,
    gamma: f32,
    learning_rate: f32,
    /// [`TabularConfig::all_goals`].
    all_goals: bool,
    /// [`TabularConfig::all_segments`].
    all_segments: bool,
    /// `H`, for the reach `H^i` of a level's subgoal.
    horizon_steps: usize,
    /// Breaks ties between equal values (untried actions all start at 0).
    rng: Rng,
    updates: u64,
    skipped: u64,
    counters: Vec<LevelCounters>,
}

impl TabularAgent {
    /// Tables for `config.levels` levels on `grid`, all values 0.
    pub fn new(
        grid: &Grid,
        config: &AgentConfig,
        tabular: &TabularConfig,
        rng: Rng,
    ) -> Result<Self, TabularError> {
        config.validate(1, 2)?;
        tabular.validate()?;
        let cells = grid.num_cells();
        let per_slot = cells * cells;
        let max = tabular.max_table_entries;
        let mut levels = Vec::with_capacity(config.levels);
        for level in 0..config.levels {
            let space = if level == 0 {
                ActionSpace::Moves
            } else {
                let reach = config.horizon.saturating_pow(level as u32);
                let full = reach.min(2 * (grid.size() - 1));
                let radius = (1..=full)
                    .rev()
                    .find(|&r| {
                        per_slot.saturating_mul(SubgoalSet::slot_count(grid.size(), r)) <= max
                    })
                    .ok_or(TabularError::TableTooLarge {
                        level,
                        entries: per_slot.saturating_mul(SubgoalSet::slot_count(grid.size(), 1)),
                        max,
                    })?;
                ActionSpace::Subgoals(SubgoalSet::new(grid, radius))
            };
            let entries = per_slot.saturating_mul(space.slots());
            if entries > max {
                return Err(TabularError::TableTooLarge {
                    level,
                    entries,
                    max,
                });
            }
            levels.push(space);
        }
        let init = match tabular.initial_q {
            InitialQ::Pessimistic => -(config.horizon as f32),
            InitialQ::Optimistic => 0.0,
        };
        let tables = levels
            .iter()
            .map(|s| vec![init; per_slot * s.slots()])
            .collect();
        let levels_len = levels.len();
        let counters = vec![LevelCounters::default(); levels_len];
        let mut agent = Self {
            shared: Arc::new(Spaces {
                grid: grid.clone(),
                levels,
            }),
            tables,
            initial_value: init,
            horizon: config.horizon as f32,
            gamma: config.gamma,
            learning_rate: tabular.learning_rate,
            all_goals: tabular.all_goals,
            all_segments: tabular.all_segments,
            horizon_steps: config.horizon,
            best: vec![Vec::new(); levels_len],
            rng,
            updates: 0,
            skipped: 0,
            counters,
        };
        for level in 0..levels_len {
            agent.rebuild_best(level);
        }
        Ok(agent)
    }

    /// Recomputes level `level`'s [`Self::best`] from its table.
    pub(crate) fn rebuild_best(&mut self, level: usize) {
        let cells = self.shared.grid.num_cells();
        let mut best = std::mem::take(&mut self.best[level]);
        best.clear();
        best.extend((0..cells * cells).map(|i| self.max_allowed(level, i / cells, i % cells)));
        self.best[level] = best;
    }

    /// The largest `Q(s, g, a)` over the slots allowed at `s` (`-inf` if none is).
    fn max_allowed(&self, level: usize, s: usize, g: usize) -> f32 {
        let row = &self.tables[level][self.row(level, s, g)..];
        self.shared.levels[level]
            .allowed(s)
            .iter()
            .map(|&a| row[a as usize])
            .fold(f32::NEG_INFINITY, f32::max)
    }

    /// The behaviour policy's random choices for this agent (see [`TabularExploration`]).
    pub fn exploration(&self, config: &AgentConfig, rng: Rng) -> TabularExploration {
        TabularExploration {
            shared: Arc::clone(&self.shared),
            rng,
            random_action_prob: config.random_action_prob,
            subgoal_test_prob: config.subgoal_test_prob,
        }
    }

    pub fn num_levels(&self) -> usize {
        self.tables.len()
    }

    /// The Manhattan radius of level `level`'s subgoals (`None` at level 0).
    pub fn subgoal_radius(&self, level: usize) -> Option<usize> {
        match &self.shared.levels[level] {
            ActionSpace::Moves => None,
            ActionSpace::Subgoals(set) => Some(set.radius()),
        }
    }

    /// Entries of level `level`'s table.
    pub fn table_entries(&self, level: usize) -> usize {
        self.tables[level].len()
    }

    /// Q-learning updates applied so far.
    pub fn updates(&self) -> u64 {
        self.updates
    }

    /// Transitions skipped because the tables have no place for them.
    pub fn skipped(&self) -> u64 {
        self.skipped
    }

    /// Level `level`'s update count, and its TD error and values over the current window.
    pub fn level_stats(&self, level: usize) -> LevelStats {
        let c = &self.counters[level];
        let n = c.window.max(1) as f64;
        LevelStats {
            updates: c.updates,
            mean_sq_td_error: (c.sq_td_error / n) as f32,
            mean_q: (c.q / n) as f32,
        }
    }

    /// Starts a new window for [`Self::level_stats`]' averages at every level.
    pub fn start_stats_window(&mut self) {
        for c in &mut self.counters {
            (c.window, c.sq_td_error, c.q) = (0, 0.0, 0.0);
        }
    }

    /// The (clipped) subgoal radius and number of table slots of level `level`.
    pub(crate) fn layout(&self, level: usize) -> (Option<usize>, usize) {
        let space = &self.shared.levels[level];
        (self.subgoal_radius(level), space.slots())
    }

    pub(crate) fn grid(&self) -> &Grid {
        &self.shared.grid
    }

    /// The value of taking `action` towards `goal` from `state` at level `level`, if the table has
    /// a place for it.
    pub fn value(&self, level: usize, state: &[f32], goal: &[f32], action: &[f32]) -> Option<f32> {
        let (grid, space) = (&self.shared.grid, &self.shared.levels[level]);
        let s = grid.index_of_point(state)?;
        let g = grid.index_of_point(goal)?;
        let a = space.slot_of(grid, s, action)?;
        Some(self.tables[level][self.row(level, s, g) + a])
    }

    /// Start of the row of `(s, g)` in level `level`'s table.
    fn row(&self, level: usize, s: usize, g: usize) -> usize {
        (s * self.shared.grid.num_cells() + g) * self.shared.levels[level].slots()
    }

    /// Whether a transition of `kind` at `level` is contained in updates the agent makes anyway
    /// ([`TabularConfig::all_goals`], [`TabularConfig::all_segments`]), so that updating it
    /// would change nothing.
    pub fn contained(&self, level: usize, kind: TransitionKind) -> bool {
        match kind {
            TransitionKind::SubgoalPenalty => false,
            // Its state, action and next state are those of a hindsight action transition of
            // the same level, which updates them for every goal.
            TransitionKind::HindsightGoal => self.all_goals || (self.all_segments && level > 0),
            // One of the stretches of the path.
            TransitionKind::HindsightAction => self.all_segments && level > 0,
        }
    }

    /// Applies one Q-learning update (with [`TabularConfig::all_goals`], one per goal cell);
    /// `false` if the transition has no place in the tables.
    pub fn update(&mut self, level: usize, t: &Transition<'_>) -> bool {
        if self.contained(level, t.kind) {
            return true;
        }
        let all_goals = self.all_goals && t.kind != TransitionKind::SubgoalPenalty;
        let (grid, space) = (&self.shared.grid, &self.shared.levels[level]);
        let indices = grid.index_of_point(t.state).and_then(|s| {
            let g = grid.index_of_point(t.goal)?;
            let next = grid.index_of_point(t.next_state)?;
            Some((s, g, next, space.slot_of(grid, s, t.action)?))
        });
        let Some((s, g, next, a)) = indices else {
            self.skipped += 1;
            return false;
        };
        if all_goals {
            self.apply_every_goal(level, s, a, next);
        } else {
            self.apply(level, s, g, a, next, t.reward, t.terminal);
        }
        true
    }

    /// [`Self::apply`] for every goal cell `g`, with the reward and terminal of `g`: 0 and
    /// terminal if `next` is `g`, else -1.
    fn apply_every_goal(&mut self, level: usize, s: usize, a: usize, next: usize) {
        for goal in 0..self.shared.grid.num_cells() {
            // Reached means standing on the goal cell (the grid's threshold is half a cell).
            let (reward, terminal) = if goal == next {
                (0.0, true)
            } else {
                (-1.0, false)
            };
            self.apply(level, s, goal, a, next, reward, terminal);
        }
    }

    /// `Q(s, g, a) += alpha (y - Q)` with `y = r + gamma (1 - terminal) max_a' Q(next, g, a')`
    /// clipped to `[-H, 0]`.
    #[allow(clippy::too_many_arguments)]
    fn apply(
        &mut self,
        level: usize,
        s: usize,
        g: usize,
        a: usize,
        next: usize,
        reward: f32,
        terminal: bool,
    ) {
        let cells = self.shared.grid.num_cells();
        let bootstrap = if terminal {
            0.0
        } else {
            self.best[level][next * cells + g]
        };
        let target = (reward + self.gamma * bootstrap).clamp(-self.horizon, 0.0);
        self.set(level, s, g, a, target);
    }

    /// Moves `Q(s, g, a)` of level `level` towards `target` by the learning rate, and keeps
    /// [`Self::best`] in step.
    fn set(&mut self, level: usize, s: usize, g: usize, a: usize, target: f32) {
        let i = self.row(level, s, g) + a;
        let q = &mut self.tables[level][i];
        let old = *q;
        let c = &mut self.counters[level];
        c.updates += 1;
        c.window += 1;
        c.sq_td_error += f64::from((target - old) * (target - old));
        c.q += f64::from(old);
        *q += self.learning_rate * (target - old);
        let new = *q;
        self.updates += 1;
        if self.shared.levels[level].is_allowed(s, a) {
            let cells = self.shared.grid.num_cells();
            let best = self.best[level][s * cells + g];
            if new >= best {
                self.best[level][s * cells + g] = new;
            } else if old == best {
                // The maximum went down: another slot may hold it now.
                self.best[level][s * cells + g] = self.max_allowed(level, s, g);
            }
        }
    }

    /// [`TabularConfig::all_segments`] at level `level > 0` for one episode's `path` of cells
    /// (the start cell, then the cell after every move): newest stretch end first, every start
    /// within `H^level` moves before it, every goal cell. Returns the number of stretches
    /// applied; those whose end lies beyond the level's (capped) subgoal radius are skipped and
    /// counted in [`Self::skipped`], like any transition without a place in the table.
    pub fn update_segments(&mut self, level: usize, path: &[usize]) -> usize {
        let shared = Arc::clone(&self.shared);
        let ActionSpace::Subgoals(set) = &shared.levels[level] else {
            return 0;
        };
        let window = self.horizon_steps.saturating_pow(level as u32);
        let mut applied = 0;
        for t in (1..path.len()).rev() {
            // Every stretch ending here bootstraps from `best` at `next`, which the updates
            // below never change (they start elsewhere).
            let next = path[t];
            for &s in path[t - window.min(t)..t].iter().rev() {
                if s == next {
                    continue;
                }
                match set.slot_between(&shared.grid, s, next) {
                    Some(a) => {
                        self.apply_every_goal(level, s, a, next);
                        applied += 1;
                    }
                    None => self.skipped += 1,
                }
            }
        }
        applied
    }

    /// Whether [`Self::update_segments`] is part of learning ([`TabularConfig::all_segments`]).
    pub fn all_segments(&self) -> bool {
        self.all_segments
    }
}

impl Policy for TabularAgent {
    /// The allowed action of highest value, ties broken uniformly at random. A goal without a
    /// place in the table (never produced by this crate's exploration) gets a random action.
    fn act(&mut self, level: usize, state: &[f32], goal: &[f32], action: &mut [f32]) {
        let shared = &*self.shared;
        let Some(s) = shared.grid.index_of_point(state) else {
            // Off the state space (only an unrelated environment gets here): a random move, or
            // the state itself as subgoal.
            match shared.levels[level] {
                ActionSpace::Moves => action[0] = self.rng.below(MOVES.len()) as f32,
                ActionSpace::Subgoals(_) => action.copy_from_slice(&state[..action.len()]),
            }
            return;
        };
        let space = &shared.levels[level];
        let allowed = space.allowed(s);
        let slot = match shared.grid.index_of_point(goal) {
            Some(g) => {
                let row = &self.tables[level][self.row(level, s, g)..];
                let (mut best, mut best_value, mut ties) = (allowed[0], f32::NEG_INFINITY, 0u32);
                for &a in allowed {
                    let v = row[a as usize];
                    if v > best_value {
                        (best, best_value, ties) = (a, v, 1);
                    } else if v == best_value {
                        // Reservoir sampling: each of the tied actions ends up chosen with
                        // probability 1 / ties.
                        ties += 1;
                        if self.rng.below(ties as usize) == 0 {
                            best = a;
                        }
                    }
                }
                best
            }
            None => allowed[self.rng.below(allowed.len())],
        };
        space.write(&shared.grid, s, slot as usize, action);
    }
}

impl TransitionSink for TabularAgent {
    fn push(&mut self, level: usize, transition: &Transition<'_>) {
        self.update(level, transition);
    }
}

/// HAC's behaviour policy for discrete choices: with probability `random_action_prob` a
/// uniformly random move (level 0) or a uniformly random allowed subgoal around the current cell
/// (levels above), otherwise the greedy choice; subgoals tested with probability lambda; replay
/// goals uniform.
#[derive(Debug)]
pub struct TabularExploration {
    shared: Arc<Spaces>,
    rng: Rng,
    random_action_prob: f32,
    subgoal_test_prob: f32,
}

impl hac_core::Exploration for TabularExploration {
    fn explore(
        &mut self,
        level: usize,
        state: &[f32],
        bounds: &hac_core::Bounds,
        action: &mut [f32],
    ) {
        if !self.rng.bernoulli(self.random_action_prob) {
            return;
        }
        let shared = &*self.shared;
        let space = &shared.levels[level];
        if let ActionSpace::Moves = space {
            action[0] = self.rng.below(MOVES.len()) as f32;
            return;
        }
        match shared.grid.index_of_point(state) {
            // Off the state space (only an unrelated environment gets here).
            None => {
                bounds.sample(&mut self.rng, action);
                action.iter_mut().for_each(|a| *a = a.round());
            }
            Some(s) => {
                let allowed = space.allowed(s);
                let slot = allowed[self.rng.below(allowed.len())];
                space.write(&shared.grid, s, slot as usize, action);
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

#[cfg(test)]
mod tests {
    use hac_core::{Exploration, TransitionKind};

    use super::*;
    use crate::grid::Cell;

    fn config(levels: usize, horizon: usize) -> AgentConfig {
        let env = crate::FourRooms::new(10).unwrap();
        AgentConfig {
            horizon,
            ..hac_core::Env::default_config(&env, levels)
        }
    }

    /// Values from 0 and alpha 0.5, so that expected values are easy to write down; every
    /// transition updated as it comes (no stretches of the path).
    fn easy() -> TabularConfig {
        TabularConfig {
            learning_rate: 0.5,
            initial_q: InitialQ::Optimistic,
            all_segments: false,
            ..TabularConfig::default()
        }
    }

    fn agent(levels: usize, horizon: usize) -> TabularAgent {
        let grid = Grid::four_rooms(10).unwrap();
        TabularAgent::new(&grid, &config(levels, horizon), &easy(), Rng::seed_from(0)).unwrap()
    }

    #[test]
    fn pessimistic_tables_start_at_minus_h() {
        let grid = Grid::four_rooms(10).unwrap();
        let a = TabularAgent::new(
            &grid,
            &config(2, 8),
            &TabularConfig::default(),
            Rng::seed_from(0),
        )
        .unwrap();
        assert!(a.tables.iter().flatten().all(|&q| q == -8.0));
    }

    fn transition<'a>(
        state: &'a [f32],
        action: &'a [f32],
        reward: f32,
        next_state: &'a [f32],
        goal: &'a [f32],
        terminal: bool,
    ) -> Transition<'a> {
        Transition {
            kind: TransitionKind::HindsightAction,
            state,
            action,
            reward,
            next_state,
            goal,
            terminal,
            extra: &[],
        }
    }

    #[test]
    fn slot_count_matches_the_built_set() {
        let grid = Grid::four_rooms(10).unwrap();
        for r in [1, 2, 4, 9, 16, 18] {
            let set = SubgoalSet::new(&grid, r);
            assert_eq!(set.slots(), SubgoalSet::slot_count(10, r), "radius {r}");
        }
        assert_eq!(SubgoalSet::slot_count(10, 1), 5);
        assert_eq!(SubgoalSet::slot_count(10, 2), 13);
        assert_eq!(SubgoalSet::slot_count(10, 18), 19 * 19);
    }

    #[test]
    fn radius_is_h_to_the_level_capped_by_the_grid_and_the_budget() {
        let a = agent(3, 4);
        assert_eq!(a.subgoal_radius(0), None);
        assert_eq!(a.subgoal_radius(1), Some(4));
        assert_eq!(a.subgoal_radius(2), Some(16));
        assert_eq!(a.table_entries(0), 85 * 85 * 4);

        let grid = Grid::four_rooms(25).unwrap();
        let tabular = TabularConfig::default();
        let c = AgentConfig {
            horizon: 13,
            ..config(2, 13)
        };
        let big = TabularAgent::new(&grid, &c, &tabular, Rng::seed_from(0)).unwrap();
        let r = big.subgoal_radius(1).unwrap();
        assert!(r < 13);
        assert!(big.table_entries(1) <= tabular.max_table_entries);
        let cells = grid.num_cells();
        assert!(cells * cells * SubgoalSet::slot_count(25, r + 1) > tabular.max_table_entries);

        let tiny = TabularConfig {
            max_table_entries: 100,
            ..tabular
        };
        assert!(matches!(
            TabularAgent::new(&grid, &c, &tiny, Rng::seed_from(0)),
            Err(TabularError::TableTooLarge { level: 0, .. })
        ));
    }

    #[test]
    fn allowed_subgoals_are_other_free_cells_within_the_radius() {
        let grid = Grid::four_rooms(10).unwrap();
        let set = SubgoalSet::new(&grid, 3);
        let space = ActionSpace::Subgoals(set);
        for s in 0..grid.num_cells() {
            let from = grid.cell(s);
            let mut targets = Vec::new();
            for &slot in space.allowed(s) {
                let mut out = [0.0; 2];
                space.write(&grid, s, slot as usize, &mut out);
                let t = grid.cell(grid.index_of_point(&out).expect("a free cell"));
                assert_ne!(t, from);
                assert!(from.row.abs_diff(t.row) + from.col.abs_diff(t.col) <= 3);
                assert_eq!(space.slot_of(&grid, s, &out), Some(slot as usize));
                targets.push(t);
            }
            let expected = grid
                .cells()
                .iter()
                .filter(|t| {
                    let d = from.row.abs_diff(t.row) + from.col.abs_diff(t.col);
                    d > 0 && d <= 3
                })
                .count();
            assert_eq!(targets.len(), expected, "from {from:?}");
        }
    }

    #[test]
    fn update_moves_towards_the_clipped_target() {
        let mut a = agent(1, 8);
        let (s, next, goal) = ([0.0, 0.0], [0.0, 1.0], [0.0, 3.0]);
        // Non-terminal -1 with all values 0: target -1, halfway there at alpha 0.5.
        assert!(a.update(0, &transition(&s, &[3.0], -1.0, &next, &goal, false)));
        assert_eq!(a.value(0, &s, &goal, &[3.0]), Some(-0.5));
        // Terminal 0 pulls back towards 0 without bootstrapping.
        assert!(a.update(0, &transition(&s, &[3.0], 0.0, &next, &goal, true)));
        assert_eq!(a.value(0, &s, &goal, &[3.0]), Some(-0.25));
        // A penalty far below -H is clipped to -H = -8.
        assert!(a.update(0, &transition(&s, &[1.0], -50.0, &next, &goal, true)));
        assert_eq!(a.value(0, &s, &goal, &[1.0]), Some(-4.0));
        assert_eq!(a.updates(), 3);
        // Errors before each update: 1, 0.5 and 8 (the clipped penalty, from 0).
        let stats = a.level_stats(0);
        assert_eq!(stats.updates, 3);
        assert!((stats.mean_sq_td_error - (1.0 + 0.25 + 64.0) / 3.0).abs() < 1e-5);
        assert!((stats.mean_q - (0.0 - 0.5 + 0.0) / 3.0).abs() < 1e-6);
        a.start_stats_window();
        let stats = a.level_stats(0);
        assert_eq!(
            (stats.updates, stats.mean_sq_td_error, stats.mean_q),
            (3, 0.0, 0.0)
        );
    }

    #[test]
    fn all_goals_updates_every_goal_against_its_own_reward_and_skips_her_copies() {
        let grid = Grid::four_rooms(10).unwrap();
        let tabular = TabularConfig {
            all_goals: true,
            ..easy()
        };
        let mut a = TabularAgent::new(&grid, &config(2, 8), &tabular, Rng::seed_from(0)).unwrap();
        let (s, next, own_goal) = ([0.0, 0.0], [0.0, 1.0], [0.0, 3.0]);
        // A move towards (0, 3) that lands on (0, 1): for goal (0, 1) it is a success (target 0),
        // for every other goal a step (target -1 + gamma * 0 from values at 0).
        assert!(a.update(0, &transition(&s, &[3.0], -1.0, &next, &own_goal, false)));
        let cells = grid.num_cells() as u64;
        assert_eq!(a.updates(), cells);
        assert_eq!(a.value(0, &s, &own_goal, &[3.0]), Some(-0.5));
        assert_eq!(a.value(0, &s, &next, &[3.0]), Some(0.0));
        assert_eq!(a.value(0, &s, &[8.0, 8.0], &[3.0]), Some(-0.5));
        // Other actions and states are untouched.
        assert_eq!(a.value(0, &s, &own_goal, &[1.0]), Some(0.0));
        assert_eq!(a.value(0, &next, &own_goal, &[3.0]), Some(0.0));

        // A HER copy of the same move is contained in the update above: nothing changes.
        let her = Transition {
            kind: TransitionKind::HindsightGoal,
            ..transition(&s, &[3.0], 0.0, &next, &next, true)
        };
        assert!(a.update(0, &her));
        assert_eq!(a.updates(), cells);

        // A subgoal-testing penalty keeps its one goal (level 1 proposes (0, 3) from (0, 0)).
        let penalty = Transition {
            kind: TransitionKind::SubgoalPenalty,
            ..transition(&s, &own_goal, -8.0, &next, &[8.0, 8.0], true)
        };
        assert!(a.update(1, &penalty));
        assert_eq!(a.updates(), cells + 1);
        assert_eq!(a.value(1, &s, &[8.0, 8.0], &own_goal), Some(-4.0));
        assert_eq!(a.value(1, &s, &[8.0, 1.0], &own_goal), Some(0.0));

        // The default learns the transition for its own goal only.
        let mut one = agent(1, 8);
        assert!(one.update(0, &transition(&s, &[3.0], -1.0, &next, &own_goal, false)));
        assert_eq!(one.updates(), 1);
        assert_eq!(one.value(0, &s, &[8.0, 8.0], &[3.0]), Some(0.0));
    }

    #[test]
    fn all_segments_updates_every_stretch_within_reach_for_every_goal() {
        let grid = Grid::four_rooms(10).unwrap();
        let tabular = TabularConfig {
            learning_rate: 1.0,
            all_segments: true,
            ..TabularConfig::default()
        };
        // Two levels, H = 2: level 1's subgoals reach 2 moves, values start at -2.
        let mut a = TabularAgent::new(&grid, &config(2, 2), &tabular, Rng::seed_from(0)).unwrap();
        let c = |r: f32, col: f32| [r, col];
        let at = |p: [f32; 2]| grid.index_of_point(&p).unwrap();
        // Right along the top row, (0, 0) to (0, 3).
        let path: Vec<usize> = (0..4).map(|col| at(c(0.0, col as f32))).collect();
        // Stretch ends 3, 2, 1 with starts 2 + 2 + 1 moves back.
        assert_eq!(a.update_segments(1, &path), 5);
        let cells = grid.num_cells() as u64;
        assert_eq!((a.updates(), a.skipped()), (5 * cells, 0));
        let goal = c(0.0, 3.0);
        // Reaching the goal's cell: target 0, from one and from two moves away.
        assert_eq!(a.value(1, &c(0.0, 2.0), &goal, &goal), Some(0.0));
        assert_eq!(a.value(1, &c(0.0, 1.0), &goal, &goal), Some(0.0));
        // Newest first: (0, 2) already leads to the goal when (0, 1) -> (0, 2) bootstraps from it.
        assert_eq!(a.value(1, &c(0.0, 1.0), &goal, &c(0.0, 2.0)), Some(-1.0));
        assert_eq!(a.value(1, &c(0.0, 0.0), &goal, &c(0.0, 1.0)), Some(-1.0));
        assert_eq!(a.value(1, &c(0.0, 0.0), &goal, &c(0.0, 2.0)), Some(-1.0));
        // Any other goal: -1 + gamma * -2, clipped to -H.
        assert_eq!(a.value(1, &c(0.0, 2.0), &c(8.0, 8.0), &goal), Some(-2.0));
        // Level 0 and untravelled starts are untouched.
        assert_eq!(a.value(0, &c(0.0, 2.0), &goal, &[3.0]), Some(-2.0));
        assert_eq!(a.value(1, &c(1.0, 0.0), &goal, &c(0.0, 1.0)), Some(-2.0));

        // Back and forth: a stretch that ends where it starts is no subgoal.
        let before = a.updates();
        let there_and_back = [at(c(7.0, 7.0)), at(c(7.0, 8.0)), at(c(7.0, 7.0))];
        assert_eq!(a.update_segments(1, &there_and_back), 2);
        assert_eq!(a.updates(), before + 2 * cells);

        // Three levels, H = 2, and a table cap that keeps level 2's radius at 2 although its
        // stretches reach 4 moves: the longer ones have no place and are skipped.
        let grid = Grid::four_rooms(10).unwrap();
        let capped = TabularConfig {
            max_table_entries: grid.num_cells() * grid.num_cells() * SubgoalSet::slot_count(10, 2),
            ..tabular
        };
        let mut b = TabularAgent::new(&grid, &config(3, 2), &capped, Rng::seed_from(0)).unwrap();
        assert_eq!(b.subgoal_radius(2), Some(2));
        let row: Vec<usize> = (0..5).map(|col| at(c(0.0, col as f32))).collect();
        // Ends 4, 3, 2, 1 with 4, 3, 2, 1 starts within H^2 = 4 moves; 2 + 1 are beyond 2 cells.
        assert_eq!(b.update_segments(2, &row), 10 - 3);
        assert_eq!(b.skipped(), 3);
    }

    #[test]
    fn all_segments_contain_the_upper_levels_hindsight_transitions() {
        let grid = Grid::four_rooms(10).unwrap();
        let tabular = TabularConfig {
            all_segments: true,
            ..TabularConfig::default()
        };
        let mut a = TabularAgent::new(&grid, &config(2, 8), &tabular, Rng::seed_from(0)).unwrap();
        let (s, next, goal) = ([0.0, 0.0], [0.0, 1.0], [0.0, 3.0]);
        let her = Transition {
            kind: TransitionKind::HindsightGoal,
            ..transition(&s, &next, 0.0, &next, &next, true)
        };
        // Level 1's hindsight action and HER transitions: contained, nothing changes.
        assert!(a.update(1, &transition(&s, &next, -1.0, &next, &goal, false)));
        assert!(a.update(1, &her));
        assert_eq!(a.updates(), 0);
        // Level 1's penalties and everything at level 0 are updated as before.
        let penalty = Transition {
            kind: TransitionKind::SubgoalPenalty,
            ..transition(&s, &goal, -8.0, &next, &goal, true)
        };
        assert!(a.update(1, &penalty));
        assert!(a.update(0, &transition(&s, &[3.0], -1.0, &next, &goal, false)));
        let her_0 = Transition {
            kind: TransitionKind::HindsightGoal,
            ..transition(&s, &[3.0], 0.0, &next, &next, true)
        };
        assert!(a.update(0, &her_0));
        assert_eq!(a.updates(), 3);
        assert!(!a.contained(1, TransitionKind::SubgoalPenalty));
        assert!(!a.contained(0, TransitionKind::HindsightGoal));
    }

    #[test]
    fn the_cached_maximum_follows_every_update_up_and_down() {
        let grid = Grid::four_rooms(10).unwrap();
        for (learning_rate, initial_q) in
            [(1.0, InitialQ::Pessimistic), (0.5, InitialQ::Optimistic)]
        {
            let tabular = TabularConfig {
                learning_rate,
                initial_q,
                all_segments: false,
                ..TabularConfig::default()
            };
            let mut a =
                TabularAgent::new(&grid, &config(3, 3), &tabular, Rng::seed_from(0)).unwrap();
            let mut rng = Rng::seed_from(1);
            let cells = grid.cells().to_vec();
            let pick = |rng: &mut Rng| cells[rng.below(cells.len())];
            for _ in 0..20_000 {
                let level = rng.below(3);
                let (s, next, goal) = (pick(&mut rng), pick(&mut rng), pick(&mut rng));
                // Subgoals anywhere within reach, the state itself included (a slot that is
                // never allowed); rewards that raise and lower values, penalties among them.
                let action = if level == 0 {
                    [rng.below(4) as f32, 0.0]
                } else {
                    let r = 3usize.pow(level as u32) as i32;
                    let d = |rng: &mut Rng| rng.below(2 * r as usize + 1) as i32 - r;
                    let (dr, dc) = (d(&mut rng), d(&mut rng));
                    [(s.row as i32 + dr) as f32, (s.col as i32 + dc) as f32]
                };
                let width = if level == 0 { 1 } else { 2 };
                let reward = [-1.0, 0.0, -3.0][rng.below(3)];
                let (s, next, goal) = (s.to_f32(), next.to_f32(), goal.to_f32());
                let t = Transition {
                    kind: if reward == -3.0 {
                        TransitionKind::SubgoalPenalty
                    } else {
                        TransitionKind::HindsightAction
                    },
                    ..transition(&s, &action[..width], reward, &next, &goal, reward != -1.0)
                };
                a.update(level, &t);
            }
            assert!(a.updates() > 10_000);
            let cached = a.best.clone();
            for level in 0..3 {
                a.rebuild_best(level);
            }
            assert_eq!(cached, a.best, "alpha {learning_rate}");
        }
    }

    #[test]
    fn bootstrap_takes_the_best_allowed_action_at_the_next_state() {
        let mut a = agent(1, 8);
        let (s, next, goal) = ([1.0, 0.0], [0.0, 0.0], [0.0, 3.0]);
        for action in 0..4 {
            let v = -(action as f32) - 2.0;
            let a_vec = [action as f32];
            let t = transition(&next, &a_vec, v, &next, &goal, true);
            for _ in 0..40 {
                a.update(0, &t);
            }
        }
        let best_next = a.value(0, &next, &goal, &[0.0]).unwrap();
        assert!((best_next + 2.0).abs() < 1e-4);
        a.update(0, &transition(&s, &[0.0], -1.0, &next, &goal, false));
        let expected = 0.5 * (-1.0 + 0.98 * best_next);
        assert!((a.value(0, &s, &goal, &[0.0]).unwrap() - expected).abs() < 1e-6);
    }

    #[test]
    fn transitions_without_a_place_are_skipped() {
        let mut a = agent(2, 3);
        let (s, goal) = ([0.0, 0.0], [0.0, 3.0]);
        // A subgoal 4 cells away from a level with radius 3; a wall as state.
        assert!(!a.update(1, &transition(&s, &[0.0, 4.0], -1.0, &s, &goal, false)));
        assert!(!a.update(0, &transition(&[5.0, 5.0], &[0.0], -1.0, &s, &goal, false)));
        assert_eq!((a.updates(), a.skipped()), (0, 2));
    }

    #[test]
    fn greedy_action_is_the_argmax() {
        let mut a = agent(2, 5);
        let (s, goal) = ([0.0, 0.0], [0.0, 4.0]);
        // Make every move but "right" look bad.
        for m in [0.0, 1.0, 2.0] {
            a.update(0, &transition(&s, &[m], -10.0, &s, &goal, true));
        }
        let mut out = [0.0];
        for _ in 0..20 {
            a.act(0, &s, &goal, &mut out);
            assert_eq!(out, [3.0]);
        }
        // Level 1: every allowed subgoal at 0 except (0, 2) and (2, 0); (0, 2) is better.
        let all: Vec<[f32; 2]> = (0..5)
            .flat_map(|r| (0..5).map(move |c| [r as f32, c as f32]))
            .collect();
        for sg in &all {
            let v = if *sg == [0.0, 2.0] { -1.0 } else { -3.0 };
            for _ in 0..30 {
                a.update(1, &transition(&s, sg, v, &s, &goal, true));
            }
        }
        let mut out = [0.0; 2];
        a.act(1, &s, &goal, &mut out);
        assert_eq!(out, [0.0, 2.0]);
    }

    #[test]
    fn ties_are_broken_at_random() {
        let mut a = agent(1, 8);
        let mut seen = [false; 4];
        let mut out = [0.0];
        for _ in 0..100 {
            a.act(0, &[3.0, 3.0], &[8.0, 8.0], &mut out);
            seen[out[0] as usize] = true;
        }
        assert_eq!(seen, [true; 4]);
    }

    #[test]
    fn exploration_draws_random_subgoals_around_the_cell_acted_from() {
        let mut a = agent(3, 3);
        let c = AgentConfig {
            random_action_prob: 1.0,
            ..config(3, 3)
        };
        let mut x = a.exploration(&c, Rng::seed_from(5));
        let grid = Grid::four_rooms(10).unwrap();
        let bounds = hac_core::Bounds::new(vec![0.0; 2], vec![9.0; 2]);
        let from = Cell::new(6, 7);
        let mut distinct = std::collections::HashSet::new();
        for _ in 0..500 {
            let mut out = [0.0; 2];
            a.act(1, &from.to_f32(), &[0.0, 0.0], &mut out);
            x.explore(1, &from.to_f32(), &bounds, &mut out);
            let t = grid.cell(grid.index_of_point(&out).expect("a free cell"));
            let d = from.row.abs_diff(t.row) + from.col.abs_diff(t.col);
            assert!((1..=3).contains(&d), "{t:?}");
            distinct.insert(t);
        }
        // Every free cell within 3 moves of (6, 7) is drawn: the room's 4 x 4 block is cut by
        // the wall row, so count them directly.
        let expected = grid
            .cells()
            .iter()
            .filter(|t| (1..=3).contains(&(from.row.abs_diff(t.row) + from.col.abs_diff(t.col))))
            .count();
        assert_eq!(distinct.len(), expected);

        let mut seen = [false; 4];
        for _ in 0..100 {
            let mut out = [0.0];
            x.explore(
                0,
                &from.to_f32(),
                &hac_core::Bounds::new(vec![0.0], vec![3.0]),
                &mut out,
            );
            seen[out[0] as usize] = true;
        }
        assert_eq!(seen, [true; 4]);
    }
}
