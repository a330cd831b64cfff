//! Does a HIRO run's low level (level 0) learn its own job, reaching the relative goals it is
//! given? (docs/ALGORITHM.md, "HIRO"; docs/RESULTS.md, "HAC against HIRO".)
//!
//! From the environment's own initial states (seeded), the low level is given relative goals
//! drawn uniformly from the high level's relative-goal box `[-r, r]` (a fixed seed; the same
//! states and goals for every behaviour), `GOALS` goals one after another per episode, each
//! for `c` primitive steps. Between steps the goal moves with the state by the goal transition,
//! `g' = p(s) + g - p(s')`, as in training; the reward of a step is the intrinsic one,
//! `-||p(s) + g - p(s')||`; angles are taken along the circle
//! (`EnvSpec::relative_goal_angles`). At the end of each `c`-step segment what is left of the
//! goal, `||g_c||`, is how far the low level stopped from the target it was given. Reported per
//! behaviour, over all segments: the mean of `||g_0||` (how far the targets were), of `||g_c||`
//! and of each dimension's `|g_c|`, the share of segments ending within the subgoal thresholds,
//! and the mean intrinsic return per segment (the sum of its `c` rewards).
//!
//! Behaviours: the greedy level 0 of each run directory given; the same fed a decoy goal (another
//! goal drawn from the same box, moved with the state like the real one) while the real one is
//! measured, which tells whether the level uses its goal input; then uniform random actions and
//! a zero action (no torque, no push) as baselines.
//!
//! ```sh
//! cargo run --release -p hac-agent --example hiro_low_level -- \
//!     [--episodes 100] [--goals 10] [--seed 0] [--scale 1] RUN...
//! ```
//!
//! `--scale F` draws the goals from `[-F r, F r]` instead (F in (0, 1]): on the pendulum most
//! of the full box is out of reach in `c` steps (its speeds go to +-15 rad/s, while over the 0.2
//! s of 10 steps the motor alone changes the speed by at most 1.6 rad/s and gravity by at most
//! 3.9 more), so a smaller box tells whether the low level reaches goals it can reach.
//!
//! `RUN` is a directory written by `hac train --algo hiro` (its `config.toml` and
//! `weights/level0.safetensors`); every run must be of the same environment and `c`.

use std::path::PathBuf;

use hac_agent::{Agent, RunConfig};
use hac_core::hiro::{goal_radius, goal_transition, intrinsic_reward};
use hac_core::{Env, EnvSpec, Policy, Rng};

struct Options {
    episodes: usize,
    goals: usize,
    seed: u64,
    /// Goals are drawn from `[-scale r, scale r]`.
    scale: f32,
    runs: Vec<PathBuf>,
}

fn options() -> Options {
    let mut options = Options {
        episodes: 100,
        goals: 10,
        seed: 0,
        scale: 1.0,
        runs: Vec::new(),
    };
    let mut args = std::env::args().skip(1);
    while let Some(arg) = args.next() {
        let mut value = |name: &str| -> f64 {
            args.next()
                .and_then(|v| v.parse().ok())
                .unwrap_or_else(|| panic!("{name} takes a number"))
        };
        match arg.as_str() {
            "--episodes" => options.episodes = value("--episodes") as usize,
            "--goals" => options.goals = value("--goals") as usize,
            "--seed" => options.seed = value("--seed") as u64,
            "--scale" => options.scale = value("--scale") as f32,
            _ if arg.starts_with("--") => panic!("unknown option {arg}"),
            _ => options.runs.push(PathBuf::from(arg)),
        }
    }
    assert!(
        options.episodes > 0 && options.goals > 0,
        "--episodes and --goals must be at least 1"
    );
    assert!(
        options.scale > 0.0 && options.scale <= 1.0,
        "--scale is in (0, 1]"
    );
    options
}

/// How a behaviour acts at level 0.
enum Behaviour {
    Greedy(Box<Agent>),
    /// The greedy level 0 fed a decoy: another goal drawn from the same box (its own stream),
    /// moved with the state like the real one, while the real one is measured. Does the level
    /// use its goal input, or would it do as well without it?
    Decoy(Box<Agent>),
    Uniform(Rng),
    Zero,
}

impl Behaviour {
    /// `goal` is the goal measured, `decoy` the decoy's.
    fn act(
        &mut self,
        spec: &EnvSpec,
        state: &[f32],
        goal: &[f32],
        decoy: &[f32],
        action: &mut [f32],
    ) {
        match self {
            Self::Greedy(agent) => agent.act(0, state, goal, action),
            Self::Decoy(agent) => agent.act(0, state, decoy, action),
            Self::Uniform(rng) => {
                for (d, a) in action.iter_mut().enumerate() {
                    *a = rng.uniform(spec.action_bounds.low[d], spec.action_bounds.high[d]);
                }
            }
            Self::Zero => action.fill(0.0),
        }
        spec.action_bounds.clip(action);
    }
}

/// Sums over all segments.
#[derive(Default)]
struct Totals {
    segments: usize,
    start: f64,
    end: f64,
    end_per_dim: Vec<f64>,
    within: usize,
    intrinsic: f64,
}

fn norm(v: &[f32]) -> f64 {
    v.iter().map(|x| f64::from(*x).powi(2)).sum::<f64>().sqrt()
}

fn measure(env: &mut dyn Env, behaviour: &mut Behaviour, c: usize, o: &Options) -> Totals {
    let spec = env.spec().clone();
    let angles = spec.relative_goal_angles();
    let radius: Vec<f32> = goal_radius(&spec).iter().map(|r| o.scale * r).collect();
    let g = spec.subgoal_dim();
    let (mut goal, mut next_goal) = (vec![0.0; g], vec![0.0; g]);
    let (mut decoy, mut next_decoy) = (vec![0.0; g], vec![0.0; g]);
    let (mut achieved, mut next_achieved) = (vec![0.0; g], vec![0.0; g]);
    let mut action = vec![0.0; spec.action_dim()];
    let mut state = vec![0.0; spec.state_dim];
    // The same initial states and goals for every behaviour.
    let mut episodes_rng = Rng::seed_from(o.seed);
    let mut goals_rng = Rng::seed_from(o.seed.wrapping_add(1));
    let mut decoys_rng = Rng::seed_from(o.seed.wrapping_add(3));
    let mut t = Totals {
        end_per_dim: vec![0.0; g],
        ..Totals::default()
    };
    for _ in 0..o.episodes {
        env.reset(&mut episodes_rng);
        state.copy_from_slice(env.state());
        env.project_subgoal(&state, &mut achieved);
        for _ in 0..o.goals {
            for ((x, y), r) in goal.iter_mut().zip(&mut decoy).zip(&radius) {
                *x = goals_rng.uniform(-r, *r);
                *y = decoys_rng.uniform(-r, *r);
            }
            t.start += norm(&goal);
            let mut ended = false;
            for _ in 0..c {
                behaviour.act(&spec, &state, &goal, &decoy, &mut action);
                env.step(&action);
                state.copy_from_slice(env.state());
                env.project_subgoal(&state, &mut next_achieved);
                t.intrinsic +=
                    f64::from(intrinsic_reward(&achieved, &goal, &next_achieved, &angles));
                goal_transition(&achieved, &goal, &next_achieved, &angles, &mut next_goal);
                goal_transition(&achieved, &decoy, &next_achieved, &angles, &mut next_decoy);
                std::mem::swap(&mut goal, &mut next_goal);
                std::mem::swap(&mut decoy, &mut next_decoy);
                std::mem::swap(&mut achieved, &mut next_achieved);
                if env.terminated() {
                    ended = true;
                    break;
                }
            }
            t.segments += 1;
            t.end += norm(&goal);
            for (sum, x) in t.end_per_dim.iter_mut().zip(&goal) {
                *sum += f64::from(x.abs());
            }
            let within = goal
                .iter()
                .zip(&spec.subgoal_thresholds)
                .all(|(x, threshold)| x.abs() <= *threshold);
            t.within += usize::from(within);
            if ended {
                break;
            }
        }
    }
    t
}

fn main() {
    let o = options();
    assert!(!o.runs.is_empty(), "give at least one HIRO run directory");
    let mut env: Option<(String, Box<dyn Env>, usize)> = None;
    let mut behaviours: Vec<(String, Behaviour)> = Vec::new();
    let mut decoys: Vec<(String, Behaviour)> = Vec::new();
    for dir in &o.runs {
        let run = RunConfig::load_run(dir).unwrap_or_else(|e| panic!("{}: {e}", dir.display()));
        let hiro = run
            .hiro()
            .unwrap_or_else(|| panic!("{} is not a HIRO run", dir.display()));
        let made = run.make_env().expect("the run's environment");
        let load = || {
            Agent::load(&dir.join("weights"), made.spec(), &run)
                .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        };
        let agent = load();
        decoys.push((
            format!("level 0 of {}, fed a decoy goal", dir.display()),
            Behaviour::Decoy(Box::new(load())),
        ));
        match &env {
            None => env = Some((run.env.clone(), made, hiro.c)),
            Some((name, _, c)) => assert!(
                *name == run.env && *c == hiro.c,
                "{}: another environment or c than the first run's",
                dir.display()
            ),
        }
        behaviours.push((
            format!("level 0 of {}", dir.display()),
            Behaviour::Greedy(Box::new(agent)),
        ));
    }
    let (name, mut env, c) = env.expect("a run");
    behaviours.append(&mut decoys);
    behaviours.push((
        "uniform random actions".into(),
        Behaviour::Uniform(Rng::seed_from(o.seed.wrapping_add(2))),
    ));
    behaviours.push(("zero action".into(), Behaviour::Zero));
    let spec = env.spec().clone();
    println!(
        "{name}: {} episodes x {} goals of c = {c} steps, goals uniform in [-{} r, {} r], \
         r = {:?}, seed {}; angle dims along the circle: {:?}",
        o.episodes,
        o.goals,
        o.scale,
        o.scale,
        goal_radius(&spec),
        o.seed,
        spec.relative_goal_angles()
    );
    let dims: Vec<String> = (0..spec.subgoal_dim())
        .map(|d| format!("mean abs g_c[{d}]"))
        .collect();
    println!(
        "| behaviour | segments | mean norm g_0 | mean norm g_c | {} | within thresholds | mean intrinsic return per segment |",
        dims.join(" | ")
    );
    println!("|{}", " --- |".repeat(6 + dims.len()));
    for (label, behaviour) in &mut behaviours {
        let t = measure(env.as_mut(), behaviour, c, &o);
        let n = t.segments as f64;
        let per_dim: Vec<String> = t
            .end_per_dim
            .iter()
            .map(|s| format!("{:.3}", s / n))
            .collect();
        println!(
            "| {label} | {} | {:.3} | {:.3} | {} | {:.1}% | {:.2} |",
            t.segments,
            t.start / n,
            t.end / n,
            per_dim.join(" | "),
            100.0 * t.within as f64 / n,
            t.intrinsic / n
        );
    }
}
