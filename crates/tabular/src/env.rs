//! The four-rooms task as a [`hac_core::Env`]: cells encoded as f32 `[row, col]`, the primitive
//! action as one f32 index.

use hac_core::{AgentConfig, Bounds, Env, EnvSpec, Mode, Rng, StateError, horizon_covering};

use crate::grid::{Cell, Grid, GridError, MOVES};

/// The discrete grid world of the paper's discrete tasks (docs/ENVIRONMENTS.md, four-rooms).
///
/// - State, end goal and subgoal: the agent's cell `[row, col]`; both projections are the
///   identity, and the thresholds of 0.5 make "reached" mean "in the same cell".
/// - Primitive action: one value in `[0, 3]`, rounded to the nearest index of up, down, left,
///   right; a move into a wall or off the grid leaves the agent in place.
/// - Start: uniform over the room cells (doorways excluded). End goal, in training and in test:
///   uniform over the room cells of the three rooms the agent is not in.
/// - Budget: `max_actions = 3 x` the grid's diameter (the longest shortest path), so that a
///   detour or two still succeeds while an aimless walk rarely does. A run can set its own
///   (`max_actions`); the default H of every level count follows it (the covering rule).
#[derive(Debug, Clone)]
pub struct FourRooms {
    grid: Grid,
    spec: EnvSpec,
    /// Room cells by room, as cell numbers.
    rooms: [Vec<usize>; 4],
    pos: Cell,
    state: [f32; 2],
}

impl FourRooms {
    /// Registry name of the 10 x 10 grid.
    pub const NAME: &'static str = "four-rooms";
    /// Registry name of the 25 x 25 grid.
    pub const NAME_25: &'static str = "four-rooms-25";

    /// The task on a `size x size` grid.
    pub fn new(size: usize) -> Result<Self, GridError> {
        let name = match size {
            10 => Self::NAME.to_string(),
            _ => format!("four-rooms-{size}"),
        };
        let grid = Grid::four_rooms(size)?;
        let mut rooms: [Vec<usize>; 4] = Default::default();
        for (i, &cell) in grid.cells().iter().enumerate() {
            if let Some(room) = grid.room_of(cell) {
                rooms[room].push(i);
            }
        }
        let last = (size - 1) as f32;
        let spec = EnvSpec {
            name,
            description: format!(
                "four rooms grid world, {size}x{size}: reach a cell in another room by moving \
                 up, down, left or right"
            ),
            state_dim: 2,
            action_bounds: Bounds::new(vec![0.0], vec![(MOVES.len() - 1) as f32]),
            end_goal_dim: 2,
            end_goal_thresholds: vec![0.5, 0.5],
            subgoal_bounds: Bounds::new(vec![0.0, 0.0], vec![last, last]),
            subgoal_thresholds: vec![0.5, 0.5],
            end_goal_angles: Vec::new(),
            subgoal_angles: Vec::new(),
            subgoal_wrapped: Vec::new(),
            state_bounds: Bounds::new(vec![0.0, 0.0], vec![last, last]),
            end_goal_bounds: Bounds::new(vec![0.0, 0.0], vec![last, last]),
            achieved_subgoal_bounds: Bounds::new(vec![0.0, 0.0], vec![last, last]),
            max_actions: 3 * grid.diameter(),
            physics_steps_per_action: 1,
        };
        let pos = grid.cell(rooms[0][0]);
        Ok(Self {
            grid,
            spec,
            rooms,
            pos,
            state: pos.to_f32(),
        })
    }

    pub fn grid(&self) -> &Grid {
        &self.grid
    }

    /// The agent's cell.
    pub fn position(&self) -> Cell {
        self.pos
    }

    /// Puts the agent on `cell`; `false` (and no change) for a wall or a cell off the grid.
    pub fn set_position(&mut self, cell: Cell) -> bool {
        if !self.grid.is_free(cell) {
            return false;
        }
        self.pos = cell;
        self.state = cell.to_f32();
        true
    }

    /// Uniform draw over the room cells of every room but `except`.
    fn sample_room_cell(&self, rng: &mut Rng, except: Option<usize>) -> Cell {
        let rooms = || (0..4).filter(move |&r| Some(r) != except);
        let total: usize = rooms().map(|r| self.rooms[r].len()).sum();
        let mut k = rng.below(total);
        for r in rooms() {
            if k < self.rooms[r].len() {
                return self.grid.cell(self.rooms[r][k]);
            }
            k -= self.rooms[r].len();
        }
        unreachable!("k is below the total number of cells")
    }
}

impl Env for FourRooms {
    fn spec(&self) -> &EnvSpec {
        &self.spec
    }

    fn set_max_actions(&mut self, max_actions: usize) {
        self.spec.max_actions = max_actions;
    }

    fn set_subgoal_bounds(&mut self, bounds: Bounds) {
        self.spec.subgoal_bounds = bounds;
    }

    /// The paper's reference values where they apply to a tabular learner (lambda 0.3, 20% random
    /// actions, 3 replay goals, gamma 0.98, the test schedule) and H covering the budget. The
    /// network fields keep the paper's values so that a function-approximation agent can run here
    /// too; the tabular learner ignores them.
    fn default_config(&self, levels: usize) -> AgentConfig {
        // The paper's reference settings; the network fields are unused by the tabular learner.
        AgentConfig::reference(levels, horizon_covering(self.spec.max_actions, levels))
    }

    fn reset(&mut self, rng: &mut Rng) {
        let cell = self.sample_room_cell(rng, None);
        self.set_position(cell);
    }

    fn state(&self) -> &[f32] {
        &self.state
    }

    fn step(&mut self, action: &[f32]) {
        // NaN rounds to NaN, which the cast turns into 0.
        let index = action[0].round().clamp(0.0, (MOVES.len() - 1) as f32) as usize;
        self.pos = self.grid.step(self.pos, index);
        self.state = self.pos.to_f32();
    }

    fn project_end_goal(&self, state: &[f32], out: &mut [f32]) {
        out.copy_from_slice(state);
    }

    fn project_subgoal(&self, state: &[f32], out: &mut [f32]) {
        out.copy_from_slice(state);
    }

    /// A room cell in another room than the agent's (any room cell when it stands in a doorway).
    fn sample_end_goal(&self, rng: &mut Rng, _mode: Mode, out: &mut [f32]) {
        let room = self.grid.room_of(self.pos);
        out.copy_from_slice(&self.sample_room_cell(rng, room).to_f32());
    }

    /// `[row, col]` of a free cell. A wall cell is reported as out of range on its column
    /// (core's error has no variant for "inside the bounds but blocked").
    fn set_physical_state(&mut self, state: &[f64]) -> Result<(), StateError> {
        const ENV: &str = "four-rooms";
        let &[row, col] = state else {
            return Err(StateError::WrongLength {
                env: ENV,
                expected: 2,
                got: state.len(),
            });
        };
        let high = (self.grid.size() - 1) as f64;
        for (index, value) in [(0, row), (1, col)] {
            // `contains` is false for NaN.
            if !(0.0..=high).contains(&value) || value.fract() != 0.0 {
                return Err(StateError::OutOfRange {
                    env: ENV,
                    index,
                    value,
                    low: 0.0,
                    high,
                });
            }
        }
        if self.set_position(Cell::new(row as usize, col as usize)) {
            Ok(())
        } else {
            Err(StateError::OutOfRange {
                env: ENV,
                index: 1,
                value: col,
                low: col,
                high: col,
            })
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spec_matches_the_grid() {
        let env = FourRooms::new(10).unwrap();
        let spec = env.spec();
        assert_eq!(spec.name, "four-rooms");
        assert_eq!(spec.state_dim, 2);
        assert_eq!(spec.action_bounds, Bounds::new(vec![0.0], vec![3.0]));
        assert_eq!(spec.subgoal_bounds, Bounds::new(vec![0.0; 2], vec![9.0; 2]));
        assert_eq!(spec.max_actions, 3 * env.grid().diameter());
        assert_eq!(FourRooms::new(25).unwrap().spec().name, "four-rooms-25");
    }

    #[test]
    fn start_and_goal_lie_in_different_rooms() {
        let mut env = FourRooms::new(10).unwrap();
        let mut rng = Rng::seed_from(7);
        let mut goal = [0.0; 2];
        let mut seen_rooms = [false; 4];
        for _ in 0..2000 {
            env.reset(&mut rng);
            let start = env.position();
            let start_room = env.grid().room_of(start).expect("start in a room");
            env.sample_end_goal(&mut rng, Mode::Train, &mut goal);
            let g = env.grid().cell(env.grid().index_of_point(&goal).unwrap());
            let goal_room = env.grid().room_of(g).expect("goal in a room");
            assert_ne!(start_room, goal_room);
            seen_rooms[goal_room] = true;
        }
        assert_eq!(seen_rooms, [true; 4]);
    }

    #[test]
    fn goal_from_a_doorway_is_any_room_cell() {
        let mut env = FourRooms::new(10).unwrap();
        env.set_physical_state(&[2.0, 5.0]).unwrap();
        let mut rng = Rng::seed_from(1);
        let mut goal = [0.0; 2];
        env.sample_end_goal(&mut rng, Mode::Test, &mut goal);
        let g = env.grid().index_of_point(&goal).unwrap();
        assert!(env.grid().room_of(env.grid().cell(g)).is_some());
    }

    #[test]
    fn same_seed_same_episode() {
        let run = |seed| {
            let mut env = FourRooms::new(10).unwrap();
            let mut rng = Rng::seed_from(seed);
            env.reset(&mut rng);
            let mut trace = vec![env.position()];
            for _ in 0..50 {
                let a = rng.uniform(0.0, 3.0);
                env.step(&[a]);
                trace.push(env.position());
            }
            trace
        };
        assert_eq!(run(3), run(3));
        assert_ne!(run(3), run(4));
    }

    #[test]
    fn actions_round_to_moves_and_walls_block() {
        let mut env = FourRooms::new(10).unwrap();
        env.set_physical_state(&[0.0, 4.0]).unwrap();
        env.step(&[3.2]);
        assert_eq!(env.position(), Cell::new(0, 4), "wall to the right");
        env.step(&[0.6]);
        assert_eq!(env.position(), Cell::new(1, 4), "0.6 rounds to down");
        env.step(&[f32::NAN]);
        assert_eq!(env.position(), Cell::new(0, 4), "NaN acts as up");
        env.step(&[-5.0]);
        assert_eq!(env.position(), Cell::new(0, 4), "off the top");
        assert_eq!(env.state(), &[0.0, 4.0]);
    }

    #[test]
    fn set_physical_state_refuses_walls_and_bad_values() {
        let mut env = FourRooms::new(10).unwrap();
        assert!(matches!(
            env.set_physical_state(&[1.0]),
            Err(StateError::WrongLength { got: 1, .. })
        ));
        for bad in [[5.0, 5.0], [0.0, 10.0], [0.5, 0.0], [f64::NAN, 0.0]] {
            assert!(env.set_physical_state(&bad).is_err(), "{bad:?}");
        }
        assert_eq!(env.position(), Cell::new(0, 0));
    }

    #[test]
    fn default_configs_validate() {
        for size in [10, 25] {
            let env = FourRooms::new(size).unwrap();
            for levels in 1..=8 {
                let c = env.default_config(levels);
                c.validate(1, 2).unwrap();
                assert!(c.horizon.pow(levels as u32) >= env.spec().max_actions);
            }
        }
    }
}
