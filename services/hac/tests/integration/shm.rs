//! Shared memory with the real `hac` binary: a learner serving gRPC and iceoryx2 at once, with
//! actors on both; a shared-memory actor killed with SIGKILL and started again; two runs side by
//! side on one host.

use crate::common;
use std::path::PathBuf;
use std::time::Duration;

use common::{
    Processes, USING_SHM, actor, assert_exactly_once, count, log, refused_while_running,
    shm_learner as learner, summary,
};

const DEADLINE: Duration = Duration::from_secs(150);

fn scratch(name: &str) -> PathBuf {
    common::scratch("hac-shm-test", name)
}

#[test]
fn a_learner_two_shm_trainers_a_grpc_trainer_and_an_evaluator_learn_mountain_car() {
    let dir = scratch("run");
    let out = dir.join("out");
    let mut args = common::MOUNTAIN_CAR_TO_LEARN.to_vec();
    args.extend(["--set", "test_episodes=20", "--out", out.to_str().unwrap()]);
    let (learner, url) = learner(&args, &dir, "learner");
    let mut processes = Processes(vec![("learner".into(), learner)]);
    // The evaluator first: a learner with an evaluator waits for the last evaluation.
    processes.0.push(actor(
        &url,
        "evaluator",
        &["--role", "evaluator", "--eval-every", "20"],
        &dir,
    ));
    processes
        .0
        .push(actor(&url, "shm-0", &["--transport", "shm"], &dir));
    processes
        .0
        .push(actor(&url, "shm-1", &["--transport", "shm"], &dir));
    processes
        .0
        .push(actor(&url, "grpc-0", &["--transport", "grpc"], &dir));
    processes.all_succeed(&dir, common::LEARNING_DEADLINE);

    let (episodes, best) = common::assert_learned_mountain_car(&out, &dir, "learner");
    eprintln!("mountain-car over shm and gRPC: {best} after {episodes} episodes");
    let s = summary(&out);
    assert_exactly_once(&s);
    assert!(refused_while_running(&s).is_empty(), "{s}");

    // Who used what: the shm trainers and the evaluator (auto) shared memory, the other gRPC.
    let learner_log = log(&dir, "learner");
    assert!(
        learner_log.contains("serving shared memory"),
        "{learner_log}"
    );
    assert_eq!(
        learner_log.matches("actor registered").count(),
        4,
        "{learner_log}"
    );
    for name in ["shm-0", "shm-1", "evaluator"] {
        assert!(
            log(&dir, name).contains(USING_SHM),
            "{name}\n{}",
            log(&dir, name)
        );
    }
    assert!(!log(&dir, "grpc-0").contains(USING_SHM));
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_shm_trainer_killed_mid_run_rejoins_and_every_stored_message_is_stored_once() {
    let dir = scratch("kill");
    let out = dir.join("out");
    let (learner, url) = learner(
        &[
            "--env",
            "mountain-car",
            "--levels",
            "2",
            "--episodes",
            "80",
            "--set",
            "test_episodes=5",
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
        &["--role", "evaluator", "--eval-every", "20"],
        &dir,
    ));
    for name in ["trainer-0", "trainer-1"] {
        processes
            .0
            .push(actor(&url, name, &["--transport", "shm"], &dir));
    }
    // Mid-run: once the first evaluation is on the curve (20 episodes trained).
    common::wait_for_lines(&out.join("curve.csv"), 2, &dir, DEADLINE);
    let (_, victim) = processes
        .0
        .iter_mut()
        .find(|(n, _)| n == "trainer-1")
        .unwrap();
    victim.kill().unwrap(); // SIGKILL: its shared memory stays behind, its node is dead
    assert!(!victim.wait().unwrap().success());
    processes.0.retain(|(n, _)| n != "trainer-1");
    // Started again at once, with the same id: it must not trip over what the dead one left.
    std::fs::rename(dir.join("trainer-1.log"), dir.join("trainer-1-killed.log")).unwrap();
    let (_, again) = actor(&url, "trainer-1", &["--transport", "shm"], &dir);
    processes.0.push(("trainer-1-again".into(), again));
    processes.all_succeed(&dir, DEADLINE);

    let s = summary(&out);
    assert_exactly_once(&s);
    assert!(
        count(&s, "episodes") >= 80,
        "training went on to the budget: {s}"
    );
    let learner_log = log(&dir, "learner");
    assert_eq!(
        learner_log
            .matches("actor registered actor=trainer-1")
            .count(),
        2,
        "{learner_log}"
    );
    let again = log(&dir, "trainer-1");
    assert!(
        again.contains(USING_SHM),
        "the restarted trainer uses shared memory\n{again}"
    );

    assert!(again.contains("actor stopped"), "{again}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn two_runs_side_by_side_on_one_host_do_not_see_each_others_data() {
    let dir = scratch("pair");
    // The same run twice (same config, same digest), each learner with its own trainer that
    // shares memory with it.
    let run = [
        "--env",
        "mountain-car",
        "--levels",
        "2",
        "--episodes",
        "30",
        "--set",
        "test_episodes=5",
    ];
    let mut processes = Processes(Vec::new());
    let mut outs = Vec::new();
    for (learner_name, actor_name) in [("learner-a", "trainer-a"), ("learner-b", "trainer-b")] {
        let out = dir.join(learner_name);
        let mut args = run.to_vec();
        args.extend_from_slice(&["--out", out.to_str().unwrap()]);
        let (child, url) = learner(&args, &dir, learner_name);
        processes.0.push((learner_name.into(), child));
        processes
            .0
            .push(actor(&url, actor_name, &["--transport", "shm"], &dir));
        outs.push((out, learner_name, actor_name));
    }
    processes.all_succeed(&dir, DEADLINE);

    for (out, learner_name, actor_name) in &outs {
        let s = summary(out);
        assert_exactly_once(&s);
        // A message of the other run would be refused here as from an unknown actor.
        assert!(refused_while_running(&s).is_empty(), "{learner_name}: {s}");
        assert!(count(&s, "episodes_ingested") >= 30, "{learner_name}: {s}");
        let learner_log = log(&dir, learner_name);
        assert_eq!(
            learner_log.matches("actor registered").count(),
            1,
            "{learner_log}"
        );
        assert!(learner_log.contains(&format!("actor registered actor={actor_name}")));
        assert!(log(&dir, actor_name).contains(USING_SHM));
    }
    // Two namespaces: the same digest, two addresses.
    let namespace = |name: &str| {
        let text = log(&dir, name);
        let line = text
            .lines()
            .find(|l| l.contains("serving shared memory"))
            .unwrap_or_else(|| panic!("{text}"))
            .to_string();
        line.split("namespace=")
            .nth(1)
            .and_then(|rest| rest.split_whitespace().next())
            .map(str::to_string)
            .unwrap_or_else(|| panic!("{line}"))
    };
    let (a, b) = (namespace("learner-a"), namespace("learner-b"));
    assert_ne!(a, b);
    assert_eq!(a.split('-').next(), b.split('-').next(), "same run digest");
    let _ = std::fs::remove_dir_all(&dir);
}

/// HIRO on the distributed path: its actors roll HIRO out and stream both levels' transitions,
/// the high level's with their low-level steps, over shared memory and gRPC at once; the
/// learner stores every one (none refused) and trains both levels.
#[test]
fn hiro_streams_over_shared_memory_and_grpc_and_both_levels_train() {
    let dir = scratch("hiro");
    let out = dir.join("out");
    let args = [
        "--algo",
        "hiro",
        "--env",
        "pendulum",
        "--levels",
        "2",
        "--episodes",
        "8",
        "--set",
        "test_episodes=2",
        "--set",
        "exploration_episodes=4",
        "--set",
        "hiro.updates_per_step=0.05",
        "--out",
        out.to_str().unwrap(),
    ];
    let (learner, url) = learner(&args, &dir, "learner");
    let mut processes = Processes(vec![("learner".into(), learner)]);
    processes
        .0
        .push(actor(&url, "shm-0", &["--transport", "shm"], &dir));
    processes
        .0
        .push(actor(&url, "grpc-0", &["--transport", "grpc"], &dir));
    processes.all_succeed(&dir, DEADLINE);

    let s = summary(&out);
    assert_exactly_once(&s);
    assert_eq!(refused_while_running(&s), Vec::<String>::new(), "{s}");
    assert!(count(&s, "episodes_ingested") >= 8, "{s}");
    let config = std::fs::read_to_string(out.join("config.toml")).unwrap();
    assert!(config.contains("algo = \"hiro\""), "{config}");
    for actor in ["shm-0", "grpc-0"] {
        let log = log(&dir, actor);
        assert!(log.contains("actor stopped"), "{actor}:\n{log}");
    }
    let shm_log = log(&dir, "shm-0");
    assert!(
        shm_log.contains(USING_SHM),
        "shm-0 did not use shared memory:\n{shm_log}"
    );
    // Both levels stored and trained: for each ingested episode of T primitive steps (1000,
    // fewer if it reached its goal), T low-level transitions and ceil(T / 10) high-level ones
    // (one per c = 10 steps), and 50 and 5 updates. (The batches of an episode cut off by the
    // run's end may be stored without its end.)
    let episodes = count(&s, "episodes_ingested");
    let steps = count(&s, "env_steps_ingested");
    assert!(steps > 0 && steps <= 1000 * episodes, "{s}");
    let levels = s["levels"].as_array().expect("per-level figures");
    let (low, high) = (&levels[0], &levels[1]);
    let (low_t, high_t) = (count(low, "transitions"), count(high, "transitions"));
    assert!(low_t >= steps && 10 * high_t >= steps, "{s}");
    assert!(high_t <= low_t / 10 + episodes, "{s}");
    assert!(
        count(low, "updates") >= 8 * 50 && count(high, "updates") >= 8 * 5,
        "{s}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}
