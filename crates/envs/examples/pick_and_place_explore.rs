//! What exploration alone does to the block in pick-and-place: how often a 200-action episode
//! moves it at all, by more than a goal's threshold (3 cm), or lifts it, under four behaviours:
//!
//! - uniform random actions (every action drawn from the action box);
//! - an untrained level 0 as HAC explores with it: with probability `random_action_prob` (0.2)
//!   a uniform action, else the network's output plus Gaussian noise of 0.1 x the half range,
//!   where an untrained network's output is close to constant over an episode (a constant drawn
//!   per episode; or 0, the centre of the box);
//! - the constant plus noise alone, without random actions.
//!
//! Hindsight end goals are where the block ended up: in an episode that never moves it, every
//! hindsight goal is the block's start, and the critics never see a goal that takes contact.
//!
//! And what contact does to it: the share of episodes whose block was ever faster than 2 m/s
//! (the hand itself peaks at 1.875 m/s), and whose block ended outside the hand's workspace (x or
//! y beyond +-0.25 m: out of the gripper's reach for the rest of the episode, and beyond every
//! end goal).
//!
//! `cargo run --release -p hac-envs --example pick_and_place_explore [EPISODES]
//! [--max-corrective-velocity V]` (V: the physics setting of that name, m/s; default the task's)

use hac_core::{Env, Rng};
use hac_envs::pick_and_place::{PickAndPlace, PickAndPlacePhysics, WORKSPACE_HIGH};

const ACTIONS: usize = 200;
const NOISE: f32 = 0.1;
const RANDOM_ACTION_PROB: f32 = 0.2;

#[derive(Clone, Copy)]
enum Behaviour {
    Uniform,
    Untrained { random: bool, centred: bool },
}

impl Behaviour {
    fn name(self) -> &'static str {
        match self {
            Self::Uniform => "uniform random actions",
            Self::Untrained {
                random: true,
                centred: false,
            } => "untrained level 0: 0.2 uniform, else a constant + noise",
            Self::Untrained {
                random: true,
                centred: true,
            } => "untrained level 0: 0.2 uniform, else 0 + noise",
            Self::Untrained {
                random: false,
                centred: false,
            } => "a constant + noise, no random actions",
            Self::Untrained {
                random: false,
                centred: true,
            } => "0 + noise, no random actions",
        }
    }

    fn act(self, rng: &mut Rng, constant: &[f32; 4], action: &mut [f32; 4]) {
        match self {
            Self::Untrained { random, .. } if !(random && rng.bernoulli(RANDOM_ACTION_PROB)) => {
                for (a, c) in action.iter_mut().zip(constant) {
                    *a = (c + NOISE * rng.normal()).clamp(-1.0, 1.0);
                }
            }
            _ => action.iter_mut().for_each(|a| *a = rng.uniform(-1.0, 1.0)),
        }
    }
}

fn main() {
    let mut episodes = 1000;
    let mut physics = PickAndPlacePhysics::default();
    let mut args = std::env::args().skip(1);
    while let Some(arg) = args.next() {
        if arg == "--max-corrective-velocity" {
            physics.max_corrective_velocity = args
                .next()
                .and_then(|v| v.parse().ok())
                .expect("--max-corrective-velocity takes a speed in m/s");
        } else {
            episodes = arg.parse().expect("EPISODES is a number");
        }
    }
    let mut env = PickAndPlace::with_physics(physics);
    println!(
        "{episodes} episodes of {ACTIONS} actions each, from the task's own initial states; {physics:?}"
    );
    println!(
        "| behaviour | block moved > 5 mm | moved > 3 cm | lifted > 1 cm | block faster than 2 m/s | ended out of the hand's reach | fastest block |"
    );
    println!("| --- | --- | --- | --- | --- | --- | --- |");
    for behaviour in [
        Behaviour::Uniform,
        Behaviour::Untrained {
            random: true,
            centred: false,
        },
        Behaviour::Untrained {
            random: true,
            centred: true,
        },
        Behaviour::Untrained {
            random: false,
            centred: false,
        },
        Behaviour::Untrained {
            random: false,
            centred: true,
        },
    ] {
        let mut rng = Rng::seed_from(7);
        let (mut moved, mut moved_far, mut lifted) = (0, 0, 0);
        let (mut fast, mut out, mut fastest) = (0, 0, 0.0f32);
        let mut action = [0.0f32; 4];
        for _ in 0..episodes {
            env.reset(&mut rng);
            let start: [f32; 3] = env.state()[4..7].try_into().expect("a block position");
            let constant = match behaviour {
                Behaviour::Untrained { centred: false, .. } => {
                    [(); 4].map(|()| rng.uniform(-1.0, 1.0))
                }
                _ => [0.0; 4],
            };
            let (mut farthest, mut highest, mut peak) = (0.0f32, 0.0f32, 0.0f32);
            for _ in 0..ACTIONS {
                behaviour.act(&mut rng, &constant, &mut action);
                env.step(&action);
                let block = &env.state()[4..7];
                let d = block
                    .iter()
                    .zip(&start)
                    .map(|(b, s)| (b - s) * (b - s))
                    .sum::<f32>()
                    .sqrt();
                farthest = farthest.max(d);
                highest = highest.max(block[2] - start[2]);
                let v = &env.state()[14..17];
                peak = peak.max(v.iter().map(|v| v * v).sum::<f32>().sqrt());
            }
            let end = &env.state()[4..6];
            out +=
                usize::from(end[0].abs() > WORKSPACE_HIGH[0] || end[1].abs() > WORKSPACE_HIGH[1]);
            fast += usize::from(peak > 2.0);
            fastest = fastest.max(peak);
            moved += usize::from(farthest > 0.005);
            moved_far += usize::from(farthest > 0.03);
            lifted += usize::from(highest > 0.01);
        }
        let pct = |n: usize| format!("{n} ({:.1}%)", 100.0 * n as f64 / episodes as f64);
        println!(
            "| {} | {} | {} | {} | {} | {} | {fastest:.1} m/s |",
            behaviour.name(),
            pct(moved),
            pct(moved_far),
            pct(lifted),
            pct(fast),
            pct(out)
        );
    }
}
