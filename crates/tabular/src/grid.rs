//! The four-rooms layout: a square grid of cells, the walls that split it into four rooms, one
//! doorway in each wall segment, and the four moves.
//!
//! Coordinates are `(row, col)` with row 0 at the top. The wall row and the wall column both sit
//! at index `size / 2`; the grid's outer edge is implicit (moving off the grid, like moving into a
//! wall, leaves the agent in place). Rooms are numbered 0 (top left), 1 (top right), 2 (bottom
//! left), 3 (bottom right); doorway cells belong to no room.

use std::collections::VecDeque;

/// The moves, in the order of the primitive action index: up, down, left, right.
pub const MOVES: [[i32; 2]; 4] = [[-1, 0], [1, 0], [0, -1], [0, 1]];

/// Smallest grid with four rooms of at least 2 x 2 cells.
pub const MIN_SIZE: usize = 5;

/// Marks a grid position without a free cell in [`Grid`]'s index.
const NO_CELL: u32 = u32::MAX;

/// One grid position.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct Cell {
    pub row: usize,
    pub col: usize,
}

impl Cell {
    pub fn new(row: usize, col: usize) -> Self {
        Self { row, col }
    }

    /// The cell as the f32 vector `[row, col]` that states, goals and subgoals use.
    pub fn to_f32(self) -> [f32; 2] {
        [self.row as f32, self.col as f32]
    }

    /// The cell `self + offset` if it lies on a `size x size` grid.
    pub fn offset(self, offset: [i32; 2], size: usize) -> Option<Cell> {
        let row = self.row.checked_add_signed(offset[0] as isize)?;
        let col = self.col.checked_add_signed(offset[1] as isize)?;
        (row < size && col < size).then_some(Cell { row, col })
    }
}

/// A grid size that cannot hold four rooms.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("four-rooms grid size {size} is below the minimum {MIN_SIZE}")]
pub struct GridError {
    pub size: usize,
}

/// A square grid with walls; free cells are numbered densely in row-major order, and those
/// numbers index the learner's tables.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Grid {
    size: usize,
    wall_line: usize,
    /// Free cells in row-major order.
    cells: Vec<Cell>,
    /// `row * size + col` -> position in `cells`, or `NO_CELL` for a wall.
    index: Vec<u32>,
}

impl Grid {
    /// The four-rooms layout on a `size x size` grid: a wall row and a wall column through index
    /// `size / 2`, each of the four wall segments opened by one doorway at its middle.
    pub fn four_rooms(size: usize) -> Result<Self, GridError> {
        if size < MIN_SIZE {
            return Err(GridError { size });
        }
        let w = size / 2;
        // Middle of the segment before the crossing (0..w) and of the one after it (w+1..size).
        let doors = [(w - 1) / 2, w + 1 + (size - w - 2) / 2];
        let free = |row: usize, col: usize| match (row == w, col == w) {
            (true, true) => false,
            (true, false) => doors.contains(&col),
            (false, true) => doors.contains(&row),
            (false, false) => true,
        };
        let mut cells = Vec::new();
        let mut index = vec![NO_CELL; size * size];
        for row in 0..size {
            for col in 0..size {
                if free(row, col) {
                    index[row * size + col] = cells.len() as u32;
                    cells.push(Cell { row, col });
                }
            }
        }
        Ok(Self {
            size,
            wall_line: w,
            cells,
            index,
        })
    }

    /// Side length in cells.
    pub fn size(&self) -> usize {
        self.size
    }

    /// Number of free cells (the size of the state space).
    pub fn num_cells(&self) -> usize {
        self.cells.len()
    }

    /// The free cell numbered `i`.
    pub fn cell(&self, i: usize) -> Cell {
        self.cells[i]
    }

    /// All free cells, in index order.
    pub fn cells(&self) -> &[Cell] {
        &self.cells
    }

    /// The number of a free cell; `None` for a wall.
    pub fn index_of(&self, cell: Cell) -> Option<usize> {
        if cell.row >= self.size || cell.col >= self.size {
            return None;
        }
        let i = self.index[cell.row * self.size + cell.col];
        (i != NO_CELL).then_some(i as usize)
    }

    /// The number of the free cell nearest to the point `[row, col]` (rounded); `None` off the
    /// grid, on a wall, or for a vector of another length.
    pub fn index_of_point(&self, point: &[f32]) -> Option<usize> {
        let [row, col] = point else { return None };
        let coord = |x: f32| {
            let r = x.round();
            (r >= 0.0 && r < self.size as f32).then_some(r as usize)
        };
        self.index_of(Cell::new(coord(*row)?, coord(*col)?))
    }

    pub fn is_free(&self, cell: Cell) -> bool {
        self.index_of(cell).is_some()
    }

    /// The room (0..4) of a free cell off the wall lines; `None` for doorways and walls.
    pub fn room_of(&self, cell: Cell) -> Option<usize> {
        let w = self.wall_line;
        if cell.row == w || cell.col == w || !self.is_free(cell) {
            return None;
        }
        Some(2 * usize::from(cell.row > w) + usize::from(cell.col > w))
    }

    /// Where `action` (an index into [`MOVES`]) takes the agent from `cell`: the neighbour if
    /// it is free, else `cell` itself.
    pub fn step(&self, cell: Cell, action: usize) -> Cell {
        match cell.offset(MOVES[action], self.size) {
            Some(next) if self.is_free(next) => next,
            _ => cell,
        }
    }

    /// Shortest-path lengths in moves from `from` to every free cell (by cell number); `None`
    /// for cells it cannot reach.
    pub fn distances_from(&self, from: Cell) -> Vec<Option<usize>> {
        let mut dist = vec![None; self.cells.len()];
        let Some(start) = self.index_of(from) else {
            return dist;
        };
        dist[start] = Some(0);
        let mut queue = VecDeque::from([start]);
        while let Some(i) = queue.pop_front() {
            let d = dist[i].unwrap_or(0);
            for action in 0..MOVES.len() {
                let j = self.index_of(self.step(self.cells[i], action));
                if let Some(j) = j.filter(|&j| dist[j].is_none()) {
                    dist[j] = Some(d + 1);
                    queue.push_back(j);
                }
            }
        }
        dist
    }

    /// The longest shortest path between two free cells, in moves.
    pub fn diameter(&self) -> usize {
        self.cells
            .iter()
            .flat_map(|&c| self.distances_from(c))
            .map(|d| d.unwrap_or(0))
            .max()
            .unwrap_or(0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ten_by_ten_layout() {
        let g = Grid::four_rooms(10).unwrap();
        // 81 room cells (5x5, 5x4, 4x5, 4x4) plus the four doorways.
        assert_eq!(g.num_cells(), 85);
        for i in 0..10 {
            let on_row = g.is_free(Cell::new(5, i));
            let on_col = g.is_free(Cell::new(i, 5));
            assert_eq!(on_row, i == 2 || i == 7, "wall row at col {i}");
            assert_eq!(on_col, i == 2 || i == 7, "wall col at row {i}");
        }
        assert_eq!(g.room_of(Cell::new(0, 0)), Some(0));
        assert_eq!(g.room_of(Cell::new(0, 9)), Some(1));
        assert_eq!(g.room_of(Cell::new(9, 0)), Some(2));
        assert_eq!(g.room_of(Cell::new(9, 9)), Some(3));
        assert_eq!(g.room_of(Cell::new(2, 5)), None, "doorway");
        assert_eq!(g.room_of(Cell::new(5, 5)), None, "wall");
    }

    #[test]
    fn rejects_grids_too_small_for_four_rooms() {
        assert_eq!(Grid::four_rooms(4), Err(GridError { size: 4 }));
        assert!(Grid::four_rooms(MIN_SIZE).is_ok());
    }

    /// Every wall segment has exactly one opening, and it joins the two rooms beside it.
    #[test]
    fn one_doorway_between_each_pair_of_adjacent_rooms() {
        for size in [5, 10, 11, 25] {
            let g = Grid::four_rooms(size).unwrap();
            let w = size / 2;
            let mut joined = Vec::new();
            for i in (0..size).filter(|&i| i != w) {
                for (door, across) in [
                    (Cell::new(i, w), [[0, -1], [0, 1]]),
                    (Cell::new(w, i), [[-1, 0], [1, 0]]),
                ] {
                    if g.is_free(door) {
                        let rooms = across.map(|o| g.room_of(door.offset(o, size).unwrap()));
                        joined.push((rooms[0].unwrap(), rooms[1].unwrap()));
                    }
                }
            }
            joined.sort_unstable();
            assert_eq!(joined, [(0, 1), (0, 2), (1, 3), (2, 3)], "size {size}");
        }
    }

    #[test]
    fn every_free_cell_is_reachable() {
        for size in [5, 10, 25] {
            let g = Grid::four_rooms(size).unwrap();
            let dist = g.distances_from(g.cell(0));
            assert!(dist.iter().all(Option::is_some), "size {size}");
        }
    }

    #[test]
    fn walls_and_edges_block_moves() {
        let g = Grid::four_rooms(10).unwrap();
        let corner = Cell::new(0, 0);
        assert_eq!(g.step(corner, 0), corner, "off the top");
        assert_eq!(g.step(corner, 2), corner, "off the left");
        assert_eq!(g.step(corner, 1), Cell::new(1, 0));
        assert_eq!(g.step(corner, 3), Cell::new(0, 1));
        // (0, 4) is beside the wall column; (2, 4) beside its doorway.
        assert_eq!(g.step(Cell::new(0, 4), 3), Cell::new(0, 4));
        assert_eq!(g.step(Cell::new(2, 4), 3), Cell::new(2, 5));
        assert_eq!(g.step(Cell::new(4, 0), 1), Cell::new(4, 0));
        assert_eq!(g.step(Cell::new(4, 2), 1), Cell::new(5, 2));
        assert_eq!(g.step(Cell::new(9, 9), 1), Cell::new(9, 9));
    }

    #[test]
    fn points_round_to_cells() {
        let g = Grid::four_rooms(10).unwrap();
        assert_eq!(g.index_of_point(&[0.4, -0.4]), Some(0));
        assert_eq!(g.index_of_point(&[5.0, 5.0]), None, "wall");
        assert_eq!(g.index_of_point(&[-0.6, 0.0]), None, "off the grid");
        assert_eq!(g.index_of_point(&[10.0, 0.0]), None, "off the grid");
        assert_eq!(g.index_of_point(&[f32::NAN, 0.0]), None);
        assert_eq!(g.index_of_point(&[1.0]), None);
    }

    #[test]
    fn diameters() {
        assert_eq!(Grid::four_rooms(10).unwrap().diameter(), 18);
        assert_eq!(Grid::four_rooms(25).unwrap().diameter(), 48);
    }
}
