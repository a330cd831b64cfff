//! Cartpole and pick-and-place through the real daemons: a learner serving gRPC and shared
//! memory, a shared-memory trainer, a gRPC trainer and an evaluator, with nothing but `--env`.
//! Its own test binary, so that it never shares the machine with the learning tests of
//! `shm.rs` and `distributed.rs`, whose free-running actors learn more slowly under load.

use std::path::PathBuf;
use std::time::Duration;
mod common;

use common::{
    Processes, USING_SHM, actor, assert_exactly_once, count, log, refused_while_running,
    shm_learner as learner, summary,
};

const DEADLINE: Duration = Duration::from_secs(150);

fn scratch(name: &str) -> PathBuf {
    common::scratch("hac-tasks-test", name)
}

#[test]
fn cartpole_and_pick_and_place_run_distributed_with_no_extra_flags() {
    // The two contact-free and contact tasks through the same daemons and both transports, with
    // only the environment named: a shared-memory trainer, a gRPC trainer and an evaluator. A
    // short budget: this checks the wiring (every value admitted, exactly once, curve, best
    // weights), not learning.
    for env in ["cartpole", "pick-and-place"] {
        let dir = scratch(env);
        let out = dir.join("out");
        let (learner, url) = learner(
            &[
                "--env",
                env,
                "--levels",
                "2",
                "--episodes",
                "6",
                "--set",
                "test_episodes=2",
                "--out",
                out.to_str().unwrap(),
            ],
            &dir,
            "learner",
        );
        let mut processes = Processes(vec![("learner".into(), learner)]);
        processes.0.push(actor(
            &url,
            "evaluator",
            &["--role", "evaluator", "--eval-every", "3"],
            &dir,
        ));
        processes
            .0
            .push(actor(&url, "shm-0", &["--transport", "shm"], &dir));
        processes
            .0
            .push(actor(&url, "grpc-0", &["--transport", "grpc"], &dir));
        processes.all_succeed(&dir, DEADLINE);

        let s = summary(&out);
        assert_exactly_once(&s);
        // Admission by meaning checks every value against the task's boxes: nothing honest
        // may be refused.
        assert!(refused_while_running(&s).is_empty(), "{env}: {s}");
        assert!(count(&s, "episodes_ingested") >= 6, "{env}: {s}");
        assert!(count(&s, "transitions") > 0, "{env}: {s}");
        let csv = std::fs::read_to_string(out.join("curve.csv")).unwrap();
        assert!(csv.lines().count() >= 2, "{env}: an evaluation\n{csv}");
        assert!(
            out.join("weights/best/best.json").exists(),
            "{env}: the best weights"
        );
        assert!(log(&dir, "shm-0").contains(USING_SHM), "{env}");
        assert!(!log(&dir, "grpc-0").contains(USING_SHM), "{env}");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
