//! Cartpole and pick-and-place through the real daemons: a learner serving gRPC and shared
//! memory, a shared-memory trainer, a gRPC trainer and an evaluator, with nothing but `--env`.
//! Its own test binary, so that it never shares the machine with the learning tests of
//! `shm.rs` and `distributed.rs`, whose free-running actors learn more slowly under load.

use std::path::{Path, PathBuf};
use std::process::Child;
use std::time::Duration;
mod common;

use common::{Processes, count, hac, listening_addr, summary};

const DEADLINE: Duration = Duration::from_secs(150);
const USING_SHM: &str = "sending over shared memory";

fn scratch(name: &str) -> PathBuf {
    common::scratch("hac-tasks-test", name)
}

fn log(logs: &Path, name: &str) -> String {
    std::fs::read_to_string(logs.join(format!("{name}.log"))).unwrap()
}

fn learner(args: &[&str], logs: &Path, name: &str) -> (Child, String) {
    let mut all = vec!["learner", "--shm", "--listen", "127.0.0.1:0"];
    all.extend_from_slice(args);
    let mut child = hac(&all, logs, name);
    let addr = listening_addr(&mut child, logs);
    (child, format!("http://{addr}"))
}

fn actor(url: &str, name: &str, extra: &[&str], logs: &Path) -> (String, Child) {
    let mut args = vec!["actor", "--learner", url, "--id", name];
    args.extend_from_slice(extra);
    (name.to_string(), hac(&args, logs, name))
}

/// Every message that reached the learner was stored, a duplicate or refused, and every
/// transition counted at ingest is in replay once; nothing was refused while the run went on.
fn assert_exactly_once_and_nothing_refused(env: &str, s: &serde_json::Value) {
    let rejected = s["rejected"].as_object().unwrap();
    let refused: u64 = rejected.values().map(|v| v.as_u64().unwrap()).sum();
    assert_eq!(
        count(s, "messages"),
        count(s, "batches") + count(s, "episodes_ingested") + count(s, "duplicates") + refused,
        "{env}: {s}"
    );
    assert_eq!(
        count(s, "transitions"),
        count(s, "transitions_in_replay"),
        "{env}: {s}"
    );
    // Admission by meaning checks every value against the task's boxes: nothing honest may be
    // refused (`finished`: messages still in flight when the run ended).
    assert!(
        rejected.keys().all(|reason| reason == "finished"),
        "{env}: {s}"
    );
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
        assert_exactly_once_and_nothing_refused(env, &s);
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
