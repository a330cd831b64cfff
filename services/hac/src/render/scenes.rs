//! How each environment looks: the drawing of a state with the end goal (red) and every level's
//! subgoal (one colour per level) in the style of the paper's figure 5, and the short text the
//! legend prints for a state or a goal.

use hac_envs::ur5::{Ur5Arm, WRIST_IN_FOREARM};
use nalgebra::Vector3;

use super::raster::{
    BLACK, Canvas, DARK_GREY, END_GOAL, GREY, LIGHT_GREY, SAND, WHITE, subgoal_colour,
};
use super::record::Frame;

/// One environment's picture.
pub trait Scene {
    /// Width and height of the drawing in pixels.
    fn size(&self) -> (i32, i32);
    /// Draws `frame` with the drawing's top-left corner at `origin`.
    fn draw(&self, canvas: &mut Canvas, origin: (i32, i32), frame: &Frame);
    /// A few words for a state in the legend.
    fn describe_state(&self, state: &[f32]) -> String;
    /// A few words for an end goal or subgoal in the legend.
    fn describe_goal(&self, goal: &[f32]) -> String;
    /// How long a frame shows, in hundredths of a second.
    fn frame_delay(&self) -> u16;
}

/// The scene of environment `env`, if it has one.
pub fn scene_for(env: &str) -> Option<Box<dyn Scene>> {
    Some(match env {
        "pendulum" => Box::new(Pendulum),
        "ur5-reacher" => Box::new(Ur5 {
            arm: Ur5Arm::new(0.0),
        }),
        "mountain-car" => Box::new(MountainCar),
        "cartpole" => Box::new(CartPole),
        "pick-and-place" => Box::new(PickAndPlace),
        _ => Box::new(FourRooms {
            grid: hac_tabular::four_rooms(env).ok()?.grid().clone(),
        }),
    })
}

/// Every goal of a frame with its colour, the end goal first, then subgoals from the top level
/// down (so the lowest level's subgoal is drawn last, on top).
fn goals(frame: &Frame) -> Vec<(&[f32], u8)> {
    let levels = frame.goals.len();
    let mut v = vec![(frame.end_goal(), END_GOAL)];
    v.extend(
        (1..levels)
            .rev()
            .map(|l| (frame.subgoal(l), subgoal_colour(l))),
    );
    v.retain(|(g, _)| !g.is_empty());
    v
}

fn signed(x: f32, decimals: usize) -> String {
    format!("{x:+.decimals$}")
}

fn degrees(angle: f32) -> String {
    // Adding 0 turns a rounded -0 into 0.
    format!("{:+.0}", angle.to_degrees().round() + 0.0)
}

/// Ring radii for the goals of [`goals`]: the end goal's largest, each level below smaller, so
/// that goals at the same place show as nested rings.
fn ring_radius(index: usize, largest: f32, step: f32) -> f32 {
    (largest - step * index as f32).max(2.0)
}

/// The inverted pendulum seen along its hinge: angle 0 points up, positive angles to the right.
struct Pendulum;

const POLE_PX: f32 = 100.0;

impl Scene for Pendulum {
    fn size(&self) -> (i32, i32) {
        (300, 250)
    }

    fn draw(&self, canvas: &mut Canvas, (x, y): (i32, i32), frame: &Frame) {
        let pivot = (x as f32 + 150.0, y as f32 + 125.0);
        let tip = |q: f32| (pivot.0 + POLE_PX * q.sin(), pivot.1 - POLE_PX * q.cos());
        canvas.circle(pivot, POLE_PX, 1.0, LIGHT_GREY);
        canvas.line(
            (pivot.0, pivot.1 - POLE_PX - 12.0),
            (pivot.0, pivot.1 - POLE_PX + 12.0),
            1.0,
            GREY,
        );
        for (i, (goal, colour)) in goals(frame).into_iter().enumerate() {
            let end = tip(goal[0]);
            canvas.line(pivot, end, 2.0, colour);
            canvas.circle(end, ring_radius(i, 15.0, 4.0), 3.0, colour);
        }
        let q = frame.state[1].atan2(frame.state[0]);
        canvas.line(pivot, tip(q), 4.0, BLACK);
        canvas.fill_circle(tip(q), 9.0, BLACK);
        canvas.fill_circle(pivot, 4.0, DARK_GREY);
    }

    fn describe_state(&self, state: &[f32]) -> String {
        let q = state[1].atan2(state[0]);
        format!("ANGLE {} DEG  SPEED {}", degrees(q), signed(state[2], 2))
    }

    fn describe_goal(&self, goal: &[f32]) -> String {
        format!(
            "ANGLE {} DEG  SPEED {}",
            degrees(goal[0]),
            signed(goal[1], 2)
        )
    }

    fn frame_delay(&self) -> u16 {
        // An action lasts 0.02 s: half speed, as browsers slow delays below 2/100 s anyway.
        4
    }
}

/// The UR5's first three joints by forward kinematics, from above (x-y) and from the side
/// (x-z); goals (joint angles) are drawn as ghost arms.
struct Ur5 {
    arm: Ur5Arm,
}

const UR5_PANEL: i32 = 220;
const UR5_GAP: i32 = 10;
const UR5_PX_PER_M: f32 = 105.0;

impl Ur5 {
    /// Base, shoulder, upper-arm origin, elbow and wrist for joint angles `q`.
    fn chain(&self, q: &[f32]) -> [Vector3<f64>; 5] {
        let pose = self.arm.pose(&Vector3::from_fn(|i, _| f64::from(q[i])));
        [
            Vector3::zeros(),
            pose.origin(0),
            pose.origin(1),
            pose.origin(2),
            pose.point(2, &WRIST_IN_FOREARM),
        ]
    }

    /// Draws the arm at `q` in both panels: from above (x right, y up) around the base, and from
    /// the side (x right, z up) above the floor line.
    fn draw_arm(&self, canvas: &mut Canvas, (x, y): (i32, i32), q: &[f32], width: f32, c: u8) {
        let chain = self.chain(q);
        let s = UR5_PX_PER_M;
        let above = (
            (x + UR5_PANEL / 2) as f32,
            (y + 16 + (UR5_PANEL - 16) / 2) as f32,
        );
        let side = (
            (x + UR5_PANEL + UR5_GAP + UR5_PANEL / 2) as f32,
            (y + UR5_PANEL - 20) as f32,
        );
        for (origin, vertical) in [(above, 1), (side, 2)] {
            let project =
                |p: &Vector3<f64>| (origin.0 + s * p.x as f32, origin.1 - s * p[vertical] as f32);
            for pair in chain.windows(2) {
                canvas.line(project(&pair[0]), project(&pair[1]), width, c);
            }
            canvas.fill_circle(project(&chain[3]), width, c);
            canvas.circle(project(&chain[4]), width + 3.0, 2.0, c);
        }
    }
}

impl Scene for Ur5 {
    fn size(&self) -> (i32, i32) {
        (2 * UR5_PANEL + UR5_GAP, UR5_PANEL)
    }

    fn draw(&self, canvas: &mut Canvas, (x, y): (i32, i32), frame: &Frame) {
        let side_x = x + UR5_PANEL + UR5_GAP;
        for px in [x, side_x] {
            canvas.rect(px, y, UR5_PANEL, UR5_PANEL, LIGHT_GREY);
        }
        canvas.text(x + 6, y + 5, "TOP (X-Y)", 2, GREY);
        canvas.text(side_x + 6, y + 5, "SIDE (X-Z)", 2, GREY);
        let floor = y + UR5_PANEL - 20;
        canvas.fill_rect(side_x + 1, floor, UR5_PANEL - 2, 2, GREY);
        for (goal, colour) in goals(frame) {
            self.draw_arm(canvas, (x, y), goal, 2.0, colour);
        }
        self.draw_arm(canvas, (x, y), &frame.state, 4.0, BLACK);
    }

    fn describe_state(&self, state: &[f32]) -> String {
        self.describe_goal(state)
    }

    fn describe_goal(&self, goal: &[f32]) -> String {
        format!(
            "JOINTS {} {} {} DEG",
            degrees(goal[0]),
            degrees(goal[1]),
            degrees(goal[2])
        )
    }

    fn frame_delay(&self) -> u16 {
        // An action lasts 0.03 s.
        4
    }
}

/// The valley `y = 0.45 sin(3x) + 0.55` over x in [-1.2, 0.6], the car, the flag at 0.45 and
/// every goal's x.
struct MountainCar;

const CAR_X: (f32, f32) = (-1.2, 0.6);
const FLAG_X: f32 = 0.45;

impl MountainCar {
    fn height(x: f32) -> f32 {
        0.45 * (3.0 * x).sin() + 0.55
    }

    /// Screen position of the valley's surface at `x`.
    fn point(&self, (ox, oy): (i32, i32), x: f32) -> (f32, f32) {
        let (w, h) = self.size();
        let u = (x - CAR_X.0) / (CAR_X.1 - CAR_X.0);
        let px = ox as f32 + 10.0 + u * (w - 20) as f32;
        let py = (oy + h - 12) as f32 - Self::height(x) * (h - 50) as f32;
        (px, py)
    }
}

impl Scene for MountainCar {
    fn size(&self) -> (i32, i32) {
        (400, 220)
    }

    fn draw(&self, canvas: &mut Canvas, origin: (i32, i32), frame: &Frame) {
        let (w, h) = self.size();
        let bottom = origin.1 + h;
        let columns = w - 20;
        let xs: Vec<f32> = (0..=columns)
            .map(|i| CAR_X.0 + (CAR_X.1 - CAR_X.0) * i as f32 / columns as f32)
            .collect();
        // One column of ground per pixel, from the surface down.
        for (i, &x) in xs.iter().enumerate() {
            let (_, py) = self.point(origin, x);
            let px = origin.0 + 10 + i as i32;
            canvas.fill_rect(px, py.round() as i32, 1, bottom - py.round() as i32, SAND);
        }
        for pair in xs.windows(2) {
            let (a, b) = (self.point(origin, pair[0]), self.point(origin, pair[1]));
            canvas.line(a, b, 2.0, DARK_GREY);
        }
        let flag = self.point(origin, FLAG_X);
        canvas.line(flag, (flag.0, flag.1 - 34.0), 1.0, DARK_GREY);
        canvas.fill_rect(flag.0 as i32 + 1, flag.1 as i32 - 34, 12, 8, GREY);
        for (i, (goal, colour)) in goals(frame).into_iter().enumerate() {
            let p = self.point(origin, goal[0].clamp(CAR_X.0, CAR_X.1));
            let radius = ring_radius(i, 11.0, 3.0);
            canvas.line((p.0, p.1 - 8.0 - radius), (p.0, p.1 - 48.0), 2.0, colour);
            canvas.circle((p.0, p.1 - 8.0), radius, 2.0, colour);
        }
        let car = self.point(origin, frame.state[0]);
        canvas.fill_circle((car.0, car.1 - 8.0), 7.0, BLACK);
    }

    fn describe_state(&self, state: &[f32]) -> String {
        self.describe_goal(state)
    }

    fn describe_goal(&self, goal: &[f32]) -> String {
        format!("X {}  V {}", signed(goal[0], 2), signed(goal[1], 3))
    }

    fn frame_delay(&self) -> u16 {
        4
    }
}

/// The cart-pole from the side: the rail along x with a tick every metre, the cart and its pole
/// (angle 0 up, positive to the right); every goal is a ghost cart with a ghost pole at its x and
/// angle. Positions beyond the subgoal range (+-2.5 m) are drawn at its edge.
struct CartPole;

const RAIL_HALF_M: f32 = 2.5;
const CARTPOLE_PX_PER_M: f32 = 70.0;
const CART_HALF_W: f32 = 20.0;
const CART_HALF_H: f32 = 10.0;

impl CartPole {
    /// Screen position of the hinge of a cart at `x`.
    fn hinge(&self, (ox, oy): (i32, i32), x: f32) -> (f32, f32) {
        let (w, h) = self.size();
        let x = x.clamp(-RAIL_HALF_M, RAIL_HALF_M);
        (
            ox as f32 + w as f32 / 2.0 + CARTPOLE_PX_PER_M * x,
            oy as f32 + h as f32 / 2.0,
        )
    }

    /// A cart outline or body and its pole: the state solid, goals as outlines.
    fn draw_cart(
        &self,
        canvas: &mut Canvas,
        origin: (i32, i32),
        x: f32,
        q: f32,
        solid: bool,
        c: u8,
    ) {
        let hinge = self.hinge(origin, x);
        let tip = (
            hinge.0 + CARTPOLE_PX_PER_M * q.sin(),
            hinge.1 - CARTPOLE_PX_PER_M * q.cos(),
        );
        let (left, top) = (
            (hinge.0 - CART_HALF_W).round() as i32,
            (hinge.1 - CART_HALF_H).round() as i32,
        );
        let (w, h) = ((2.0 * CART_HALF_W) as i32, (2.0 * CART_HALF_H) as i32);
        if solid {
            canvas.fill_rect(left, top, w, h, c);
            canvas.line(hinge, tip, 4.0, c);
            canvas.fill_circle(hinge, 4.0, DARK_GREY);
        } else {
            canvas.rect(left, top, w, h, c);
            canvas.rect(left + 1, top + 1, w - 2, h - 2, c);
            canvas.line(hinge, tip, 2.0, c);
            canvas.circle(tip, 5.0, 2.0, c);
        }
    }
}

impl Scene for CartPole {
    fn size(&self) -> (i32, i32) {
        (500, 200)
    }

    fn draw(&self, canvas: &mut Canvas, origin: (i32, i32), frame: &Frame) {
        let left = self.hinge(origin, -RAIL_HALF_M);
        let right = self.hinge(origin, RAIL_HALF_M);
        canvas.line(left, right, 2.0, GREY);
        for metre in -2..=2 {
            let (px, py) = self.hinge(origin, metre as f32);
            let half = if metre == 0 { 8.0 } else { 5.0 };
            canvas.line((px, py - half), (px, py + half), 1.0, GREY);
        }
        for (goal, colour) in goals(frame) {
            self.draw_cart(canvas, origin, goal[0], goal[1], false, colour);
        }
        let q = frame.state[2].atan2(frame.state[1]);
        self.draw_cart(canvas, origin, frame.state[0], q, true, BLACK);
    }

    fn describe_state(&self, state: &[f32]) -> String {
        let q = state[2].atan2(state[1]);
        format!(
            "X {}  ANGLE {} DEG  V {}  SPEED {}",
            signed(state[0], 2),
            degrees(q),
            signed(state[3], 2),
            signed(state[4], 2)
        )
    }

    /// End goals are `[x, q, qdot]`, subgoals `[x, q, xdot, qdot]`.
    fn describe_goal(&self, goal: &[f32]) -> String {
        let speeds = match *goal {
            [_, _, xdot, qdot] => format!("V {}  SPEED {}", signed(xdot, 2), signed(qdot, 2)),
            _ => format!("SPEED {}", signed(goal[2], 2)),
        };
        format!(
            "X {}  ANGLE {} DEG  {speeds}",
            signed(goal[0], 2),
            degrees(goal[1])
        )
    }

    fn frame_delay(&self) -> u16 {
        // An action lasts 0.02 s, as the pendulum's.
        4
    }
}

/// The gripper and the block from above (x-y) and from the side (x-z): the table, the two pads
/// and the hand's point, the block, the end goal (a ring where the block should be) and each
/// level's subgoal (a ring for the block and a square for the hand, joined by a line).
struct PickAndPlace;

const PNP_PANEL: (i32, i32) = (240, 220);
const PNP_GAP: i32 = 10;
const PNP_PX_PER_M: f32 = 400.0;

impl PickAndPlace {
    /// Screen position of world point `p` in the top panel (`side` false: x right, y up, the
    /// table's centre in the middle) or the side panel (x right, z up from the table line).
    fn project(&self, (x, y): (i32, i32), p: [f32; 3], side: bool) -> (f32, f32) {
        let s = PNP_PX_PER_M;
        if side {
            let ox = (x + PNP_PANEL.0 + PNP_GAP + PNP_PANEL.0 / 2) as f32;
            (ox + s * p[0], self.table_y(y) - s * p[2])
        } else {
            let (ox, oy) = (
                (x + PNP_PANEL.0 / 2) as f32,
                (y + 16 + (PNP_PANEL.1 - 16) / 2) as f32,
            );
            (ox + s * p[0], oy - s * p[1])
        }
    }

    fn table_y(&self, y: i32) -> f32 {
        (y + PNP_PANEL.1 - 20) as f32
    }

    /// An axis-aligned box of world half extents `half` (x, then y or z) around `centre`.
    fn fill_box(
        &self,
        canvas: &mut Canvas,
        origin: (i32, i32),
        centre: [f32; 3],
        half: [f32; 2],
        side: bool,
        colour: u8,
    ) {
        let (cx, cy) = self.project(origin, centre, side);
        let (hx, hy) = (half[0] * PNP_PX_PER_M, half[1] * PNP_PX_PER_M);
        canvas.fill_rect(
            (cx - hx).round() as i32,
            (cy - hy).round() as i32,
            (2.0 * hx).round() as i32,
            (2.0 * hy).round() as i32,
            colour,
        );
    }
}

impl Scene for PickAndPlace {
    fn size(&self) -> (i32, i32) {
        (2 * PNP_PANEL.0 + PNP_GAP, PNP_PANEL.1)
    }

    fn draw(&self, canvas: &mut Canvas, (x, y): (i32, i32), frame: &Frame) {
        let origin = (x, y);
        let side_x = x + PNP_PANEL.0 + PNP_GAP;
        for px in [x, side_x] {
            canvas.rect(px, y, PNP_PANEL.0, PNP_PANEL.1, LIGHT_GREY);
        }
        canvas.text(x + 6, y + 5, "TOP (X-Y)", 2, GREY);
        canvas.text(side_x + 6, y + 5, "SIDE (X-Z)", 2, GREY);
        // The table: the workspace's outline from above, its top face from the side.
        let (a, b) = (
            self.project(origin, [-0.25, 0.25, 0.0], false),
            self.project(origin, [0.25, -0.25, 0.0], false),
        );
        canvas.fill_rect(
            a.0 as i32,
            a.1 as i32,
            (b.0 - a.0) as i32,
            (b.1 - a.1) as i32,
            SAND,
        );
        let table = self.table_y(y) as i32;
        canvas.fill_rect(side_x + 1, table, PNP_PANEL.0 - 2, 18, SAND);
        canvas.fill_rect(side_x + 1, table, PNP_PANEL.0 - 2, 2, DARK_GREY);

        let state = &frame.state;
        let block = [state[4], state[5], state[6]];
        let half = 0.025;
        self.fill_box(canvas, origin, block, [half, half], false, BLACK);
        self.fill_box(canvas, origin, block, [half, half], true, BLACK);
        // The pads: 0.03 along x, 0.01 along y, 0.04 tall from the hand's point up.
        let hand = [state[0], state[1], state[2]];
        let offset = 0.5 * (state[3] + 0.01);
        for sign in [1.0, -1.0] {
            let pad = [hand[0], hand[1] + sign * offset, hand[2] + 0.02];
            self.fill_box(canvas, origin, pad, [0.015, 0.005], false, DARK_GREY);
        }
        let pads = [hand[0], hand[1], hand[2] + 0.02];
        self.fill_box(canvas, origin, pads, [0.015, 0.02], true, DARK_GREY);
        // The arm above the hand, from the side.
        let top = self.project(origin, [hand[0], 0.0, hand[2] + 0.04], true);
        canvas.line(top, (top.0, y as f32 + 20.0), 2.0, GREY);

        for (i, (goal, colour)) in goals(frame).into_iter().enumerate() {
            let radius = ring_radius(i, 12.0, 3.0);
            let block_goal = if goal.len() >= 7 {
                let hand_goal = [goal[0], goal[1], goal[2]];
                for side in [false, true] {
                    let h = self.project(origin, hand_goal, side);
                    let b = self.project(origin, [goal[4], goal[5], goal[6]], side);
                    canvas.line(h, b, 1.0, colour);
                    canvas.rect(h.0 as i32 - 4, h.1 as i32 - 4, 9, 9, colour);
                }
                [goal[4], goal[5], goal[6]]
            } else {
                [goal[0], goal[1], goal[2]]
            };
            for side in [false, true] {
                let c = self.project(origin, block_goal, side);
                canvas.circle(c, radius, 2.0, colour);
            }
        }
    }

    /// The state's first seven values are a subgoal's: hand, opening, block.
    fn describe_state(&self, state: &[f32]) -> String {
        self.describe_goal(&state[0..7])
    }

    /// Positions in centimetres: the block's for an end goal; the hand's, the opening and the
    /// block's for a subgoal.
    fn describe_goal(&self, goal: &[f32]) -> String {
        let cm = |v: &[f32]| {
            v.iter()
                .map(|x| format!("{:+.0}", (x * 100.0).round() + 0.0))
                .collect::<Vec<_>>()
                .join(" ")
        };
        if goal.len() >= 7 {
            format!(
                "HAND {} OPEN {:.0} BLOCK {} CM",
                cm(&goal[0..3]),
                goal[3] * 100.0,
                cm(&goal[4..7])
            )
        } else {
            format!("BLOCK {} CM", cm(&goal[0..3]))
        }
    }

    fn frame_delay(&self) -> u16 {
        // An action lasts 0.04 s.
        4
    }
}

/// The grid: walls dark, the end goal a red cell, each subgoal a ring in its level's colour, the
/// agent a black disc.
struct FourRooms {
    grid: hac_tabular::Grid,
}

impl FourRooms {
    fn cell_px(&self) -> i32 {
        (300 / self.grid.size() as i32).min(28)
    }

    /// Centre of the cell nearest to `point` (`[row, col]`).
    fn centre(&self, (x, y): (i32, i32), point: &[f32]) -> (f32, f32) {
        let c = self.cell_px() as f32;
        let last = (self.grid.size() - 1) as f32;
        let (row, col) = (
            point[0].round().clamp(0.0, last),
            point[1].round().clamp(0.0, last),
        );
        (x as f32 + (col + 0.5) * c, y as f32 + (row + 0.5) * c)
    }
}

impl Scene for FourRooms {
    fn size(&self) -> (i32, i32) {
        let side = self.cell_px() * self.grid.size() as i32 + 1;
        (side, side)
    }

    fn draw(&self, canvas: &mut Canvas, (x, y): (i32, i32), frame: &Frame) {
        let c = self.cell_px();
        let n = self.grid.size();
        for row in 0..n {
            for col in 0..n {
                let (px, py) = (x + col as i32 * c, y + row as i32 * c);
                let free = self.grid.is_free(hac_tabular::Cell::new(row, col));
                canvas.fill_rect(px, py, c + 1, c + 1, if free { WHITE } else { DARK_GREY });
                if free {
                    canvas.rect(px, py, c + 1, c + 1, LIGHT_GREY);
                }
            }
        }
        let levels = frame.goals.len();
        let end = self.centre((x, y), frame.end_goal());
        let half = c as f32 / 2.0 - 2.0;
        canvas.fill_rect(
            (end.0 - half) as i32,
            (end.1 - half) as i32,
            (2.0 * half) as i32 + 1,
            (2.0 * half) as i32 + 1,
            END_GOAL,
        );
        let (largest, step, thickness) = if c >= 20 {
            (c as f32 * 0.42, 4.0, 3.0)
        } else {
            (c as f32 * 0.45, 2.0, 2.0)
        };
        for level in (1..levels).rev() {
            let centre = self.centre((x, y), frame.subgoal(level));
            // Lower levels get smaller rings, so that rings on one cell stay apart.
            let radius = ring_radius(levels - 1 - level, largest, step);
            canvas.circle(centre, radius, thickness + 1.0, WHITE);
            canvas.circle(centre, radius, thickness, subgoal_colour(level));
        }
        let agent = self.centre((x, y), &frame.state);
        canvas.fill_circle(agent, (c as f32 * 0.28).max(2.0), BLACK);
    }

    fn describe_state(&self, state: &[f32]) -> String {
        self.describe_goal(state)
    }

    fn describe_goal(&self, goal: &[f32]) -> String {
        format!("ROW {} COL {}", goal[0].round(), goal[1].round())
    }

    fn frame_delay(&self) -> u16 {
        // One move per frame, slow enough to follow.
        20
    }
}

#[cfg(test)]
mod tests {
    use std::f32::consts::PI;

    use super::*;

    fn frame(state: Vec<f32>, goals: Vec<Vec<f32>>) -> Frame {
        Frame {
            step: 0,
            state,
            goals,
        }
    }

    fn count(c: &Canvas, colour: u8) -> usize {
        c.pixels().iter().filter(|&&p| p == colour).count()
    }

    #[test]
    fn every_environment_has_a_scene_that_draws_every_goal() {
        let cases = [
            (
                "pendulum",
                frame(
                    vec![-1.0, 0.0, 0.5],
                    vec![vec![1.0, 0.0], vec![0.5, 0.0], vec![0.0, 0.0]],
                ),
            ),
            (
                "ur5-reacher",
                frame(
                    vec![0.3, -0.5, 0.4, 0.0, 0.0, 0.0],
                    vec![vec![1.0, -0.3, 0.2, 0.0, 0.0, 0.0], vec![-1.5, -0.5, 0.5]],
                ),
            ),
            (
                "mountain-car",
                frame(vec![-0.5, 0.0], vec![vec![-0.9, 0.01], vec![0.48, 0.04]]),
            ),
            (
                "pick-and-place",
                frame(
                    vec![
                        0.05, 0.0, 0.1, 0.05, 0.05, 0.0, 0.125, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0,
                        0.0, 0.0, 0.0, 0.0, 0.0, 0.0,
                    ],
                    vec![
                        vec![0.1, 0.1, 0.0, 0.1, 0.1, 0.1, 0.025],
                        vec![-0.1, -0.1, 0.2],
                    ],
                ),
            ),
            (
                "cartpole",
                frame(
                    vec![0.3, -1.0, 0.0, 0.0, 0.0],
                    vec![
                        vec![-1.0, 0.5, 0.0, 0.0],
                        vec![1.0, -0.5, 0.0, 0.0],
                        vec![0.5, 0.0, 0.0],
                    ],
                ),
            ),
            (
                "four-rooms",
                frame(
                    vec![1.0, 1.0],
                    vec![vec![2.0, 3.0], vec![6.0, 2.0], vec![8.0, 8.0]],
                ),
            ),
            (
                "four-rooms-25",
                frame(vec![1.0, 1.0], vec![vec![3.0, 3.0], vec![20.0, 20.0]]),
            ),
        ];
        for (env, f) in cases {
            let scene = scene_for(env).unwrap_or_else(|| panic!("{env} has no scene"));
            let (w, h) = scene.size();
            let mut c = Canvas::new(w as usize + 20, h as usize + 20, WHITE);
            scene.draw(&mut c, (10, 10), &f);
            assert!(count(&c, BLACK) > 10, "{env}: the state is drawn");
            assert!(count(&c, END_GOAL) > 5, "{env}: the end goal is drawn");
            for level in 1..f.goals.len() {
                assert!(
                    count(&c, subgoal_colour(level)) > 5,
                    "{env}: level {level}'s subgoal is drawn"
                );
            }
            assert!(!scene.describe_state(&f.state).is_empty());
            assert!(!scene.describe_goal(f.end_goal()).is_empty());
        }
        assert!(scene_for("acrobot").is_none());
    }

    #[test]
    fn the_pendulum_pole_points_along_its_angle() {
        let scene = Pendulum;
        let mut c = Canvas::new(300, 250, WHITE);
        // q = pi/2 (cos 0, sin 1): the pole lies to the right of the pivot at (150, 125).
        scene.draw(
            &mut c,
            (0, 0),
            &frame(vec![0.0, 1.0, 0.0], vec![vec![-PI / 2.0, 0.0]]),
        );
        assert_eq!(c.get(200, 125), Some(BLACK));
        assert_eq!(c.get(100, 125), Some(END_GOAL), "the goal pole points left");
        assert_ne!(c.get(150, 75), Some(BLACK));
        assert_eq!(
            scene.describe_goal(&[PI, 1.0]),
            "ANGLE +180 DEG  SPEED +1.00"
        );
    }

    #[test]
    fn the_cartpole_draws_cart_and_pole_where_they_are() {
        let scene = CartPole;
        let mut c = Canvas::new(500, 200, WHITE);
        // The cart at x = 1 m (hinge at (320, 100)) with its pole hanging (cos -1, sin 0); the
        // end goal upright over x = -1 m (hinge at (180, 100)).
        scene.draw(
            &mut c,
            (0, 0),
            &frame(vec![1.0, -1.0, 0.0, 0.0, 0.0], vec![vec![-1.0, 0.0, 0.0]]),
        );
        assert_eq!(
            c.get(320, 100 + 50),
            Some(BLACK),
            "the pole hangs below the cart"
        );
        assert_ne!(c.get(320, 100 - 50), Some(BLACK));
        assert_eq!(
            c.get(180, 100 - 50),
            Some(END_GOAL),
            "the goal pole stands up"
        );
        assert_eq!(
            c.get(180 - 20, 100),
            Some(END_GOAL),
            "the goal cart's outline"
        );
        assert_eq!(
            scene.describe_goal(&[0.5, PI, 1.0]),
            "X +0.50  ANGLE +180 DEG  SPEED +1.00"
        );
        assert_eq!(
            scene.describe_goal(&[-0.5, 0.0, 1.0, -2.0]),
            "X -0.50  ANGLE +0 DEG  V +1.00  SPEED -2.00"
        );
        assert_eq!(
            scene.describe_state(&[0.25, 0.0, 1.0, -0.5, 3.0]),
            "X +0.25  ANGLE +90 DEG  V -0.50  SPEED +3.00"
        );
    }

    #[test]
    fn four_rooms_marks_the_agent_goal_and_walls_in_their_cells() {
        let scene = scene_for("four-rooms").unwrap();
        let mut c = Canvas::new(400, 400, WHITE);
        scene.draw(
            &mut c,
            (0, 0),
            &frame(vec![0.0, 0.0], vec![vec![0.0, 3.0], vec![9.0, 9.0]]),
        );
        // 28-pixel cells: the agent at the centre of (0, 0), the goal fills (9, 9), (5, 5) is wall,
        // the subgoal ring crosses the middle row of (0, 3) near its left edge.
        assert_eq!(c.get(14, 14), Some(BLACK));
        assert_eq!(c.get(9 * 28 + 14, 9 * 28 + 14), Some(END_GOAL));
        assert_eq!(c.get(5 * 28 + 14, 5 * 28 + 14), Some(DARK_GREY));
        let ring_row: Vec<_> = (3 * 28..4 * 28).map(|x| c.get(x, 14)).collect();
        assert!(ring_row.contains(&Some(subgoal_colour(1))));
    }
}
