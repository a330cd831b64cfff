//! What a HIRO pendulum run's two greedy levels do on a grid of states: the high level's
//! relative goal `[q, qdot]` for the test end goal `[0, 0]` (pole upright and still), and the
//! torque the low level answers it with. docs/RESULTS.md ("HIRO on the pendulum with the HIRO
//! paper's dense reward") reads it.
//!
//! ```sh
//! cargo run --release -p hac-agent --example hiro_pendulum_policy -- runs/A [runs/B ...]
//! ```

use std::path::PathBuf;

use hac_agent::{Agent, RunConfig};
use hac_core::Policy;

fn main() {
    let runs: Vec<PathBuf> = std::env::args().skip(1).map(PathBuf::from).collect();
    assert!(
        !runs.is_empty(),
        "give at least one HIRO pendulum run directory"
    );
    for dir in runs {
        let run = RunConfig::load_run(&dir).unwrap_or_else(|e| panic!("{}: {e}", dir.display()));
        assert!(
            run.hiro().is_some() && run.env == "pendulum",
            "{} is not a HIRO pendulum run",
            dir.display()
        );
        let made = run.make_env().expect("the run's environment");
        let mut agent = Agent::load(&dir.join("weights"), made.spec(), &run)
            .unwrap_or_else(|e| panic!("{}: {e}", dir.display()));
        println!("{}", dir.display());
        println!("  angle from upright q, speed qdot -> high level's goal [q, qdot] -> torque");
        for q in [3.1f32, 2.72, 2.0, 1.0, 0.3, -0.3, -1.0, -2.0, -2.72, -3.1] {
            for qdot in [0.0f32, 3.0, -3.0] {
                let state = [q.cos(), q.sin(), qdot];
                let mut goal = [0.0f32; 2];
                agent.act(1, &state, &[0.0, 0.0], &mut goal);
                let mut torque = [0.0f32; 1];
                agent.act(0, &state, &goal, &mut torque);
                println!(
                    "  q {q:5.2} qdot {qdot:4.1} -> [{:6.2}, {:6.2}] -> {:5.2}",
                    goal[0], goal[1], torque[0]
                );
            }
        }
    }
}
