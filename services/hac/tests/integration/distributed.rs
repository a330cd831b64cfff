//! Distributed runs with the real `hac` binary over loopback gRPC: a learner service, three
//! trainer actors and an evaluator learning mountain-car from nothing; and the faults: an actor
//! killed with SIGKILL and started again, a learner killed with SIGKILL and started again on the
//! same address.

use crate::common;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use common::{Processes, all_logs, count, hac, learner, log, summary};

const DEADLINE: Duration = Duration::from_secs(120);

fn scratch(name: &str) -> PathBuf {
    common::scratch("hac-distributed-test", name)
}

#[test]
fn a_learner_three_trainers_and_an_evaluator_learn_mountain_car() {
    let dir = scratch("run");
    let out = dir.join("out");
    let out_s = out.to_str().unwrap();
    let mut processes = Processes(Vec::new());
    let mut args = vec!["learner"];
    args.extend(common::MOUNTAIN_CAR_TO_LEARN);
    args.extend([
        "--set",
        "test_episodes=20",
        "--listen",
        "127.0.0.1:0",
        "--out",
        out_s,
    ]);
    let (learner, addr) = learner(&args, &dir, "learner");
    processes.0.push(("learner".into(), learner));
    let url = format!("http://{addr}");

    // The evaluator first: a learner with an evaluator waits for the last evaluation.
    let actors: [(&str, &[&str]); 4] = [
        ("evaluator", &["--role", "evaluator", "--eval-every", "20"]),
        ("trainer-0", &["--role", "trainer"]),
        ("trainer-1", &["--role", "trainer"]),
        ("trainer-2", &["--role", "trainer"]),
    ];
    for (name, extra) in actors {
        let mut args = vec!["actor", "--learner", &url, "--id", name];
        args.extend_from_slice(extra);
        processes.0.push((name.into(), hac(&args, &dir, name)));
    }

    processes.all_succeed(&dir, common::LEARNING_DEADLINE);

    for file in [
        "config.toml",
        "curve.csv",
        "summary.json",
        "weights/level0.safetensors",
        "weights/level1.safetensors",
    ] {
        assert!(
            out.join(file).is_file(),
            "missing {file}\n{}",
            all_logs(&dir)
        );
    }
    let (episodes, best) = common::assert_learned_mountain_car(&out, &dir, "learner");
    eprintln!("mountain-car, 3 trainers and an evaluator: {best} after {episodes} episodes");
    let summary = std::fs::read_to_string(out.join("summary.json")).unwrap();
    assert!(summary.contains("\"episodes_ingested\""), "{summary}");
    let learner_log = log(&dir, "learner");
    assert_eq!(
        learner_log.matches("actor registered").count(),
        4,
        "{learner_log}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn with_one_episode_in_flight_three_trainers_take_turns() {
    let dir = scratch("turns");
    let out = dir.join("out");
    let out_s = out.to_str().unwrap();
    let mut processes = Processes(Vec::new());
    let (learner, addr) = learner(
        &[
            "learner",
            "--env",
            "mountain-car",
            "--levels",
            "2",
            "--episodes",
            "30",
            "--episodes-in-flight",
            "1",
            "--listen",
            "127.0.0.1:0",
            "--out",
            out_s,
        ],
        &dir,
        "learner",
    );
    processes.0.push(("learner".into(), learner));
    let url = format!("http://{addr}");
    for name in ["trainer-0", "trainer-1", "trainer-2"] {
        let args = ["actor", "--learner", &url, "--id", name];
        processes.0.push((name.into(), hac(&args, &dir, name)));
    }
    processes.all_succeed(&dir, DEADLINE);

    let summary = summary(&out);
    let turns = &summary["episode_turns"];
    assert_eq!(turns["episodes_in_flight"], 1, "{summary}");
    assert_eq!(turns["expired"], 0, "{summary}");
    // Every episode was played in a turn (a turn granted as the run ended may go unused).
    let episodes = count(&summary, "episodes_ingested");
    let granted = turns["granted"].as_u64().unwrap();
    assert!(episodes >= 30, "{summary}");
    assert!(
        (episodes..=episodes + 3).contains(&granted),
        "{granted} turns for {episodes} episodes\n{summary}"
    );
    // Turns go in the order asked: no trainer is starved.
    for name in ["trainer-0", "trainer-1", "trainer-2"] {
        let log = std::fs::read_to_string(dir.join(format!("{name}.log"))).unwrap();
        let played: u64 = log
            .split("actor stopped")
            .nth(1)
            .and_then(|tail| tail.split(" episodes=").nth(1))
            .and_then(|v| v.split_whitespace().next())
            .and_then(|v| v.parse().ok())
            .unwrap_or_else(|| panic!("no episode count in {name}'s log:\n{log}"));
        assert!(played >= 5, "{name} played {played} of {episodes}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// Starts `hac learner` with `args` and returns it with its `host:port`.

#[test]
fn an_actor_killed_mid_run_rejoins_and_every_stored_message_is_stored_once() {
    let dir = scratch("actor");
    let out = dir.join("out");
    let (learner, addr) = learner(
        &[
            "learner",
            "--env",
            "mountain-car",
            "--levels",
            "2",
            "--episodes",
            "80",
            "--set",
            "test_episodes=5",
            "--listen",
            "127.0.0.1:0",
            "--out",
            out.to_str().unwrap(),
        ],
        &dir,
        "learner",
    );
    let url = format!("http://{addr}");
    let mut processes = Processes(vec![("learner".into(), learner)]);
    for (name, extra) in [
        (
            "evaluator",
            &["--role", "evaluator", "--eval-every", "20"][..],
        ),
        ("trainer-0", &["--role", "trainer"][..]),
        ("trainer-1", &["--role", "trainer"][..]),
    ] {
        let mut args = vec!["actor", "--learner", &url, "--id", name];
        args.extend_from_slice(extra);
        processes.0.push((name.into(), hac(&args, &dir, name)));
    }
    // Mid-run: once the first evaluation is on the curve (20 episodes trained).
    common::wait_for_lines(&out.join("curve.csv"), 2, &dir, DEADLINE);
    let (_, victim) = processes
        .0
        .iter_mut()
        .find(|(n, _)| n == "trainer-1")
        .unwrap();
    victim.kill().unwrap(); // SIGKILL
    let status = victim.wait().unwrap();
    assert!(!status.success());
    processes.0.retain(|(n, _)| n != "trainer-1");
    processes.0.push((
        "trainer-1-again".into(),
        hac(
            &[
                "actor",
                "--learner",
                &url,
                "--id",
                "trainer-1",
                "--role",
                "trainer",
            ],
            &dir,
            "trainer-1-again",
        ),
    ));

    processes.all_succeed(&dir, DEADLINE);
    let s = summary(&out);
    // Exactly once: every message that reached the learner was stored, a duplicate of a stored
    // one, or refused (the killed incarnation's stragglers, if any), and every transition counted
    // at ingest is in replay once.
    let rejected: u64 = s["rejected"]
        .as_object()
        .unwrap()
        .values()
        .map(|v| v.as_u64().unwrap())
        .sum();
    assert_eq!(
        count(&s, "messages"),
        count(&s, "batches") + count(&s, "episodes_ingested") + count(&s, "duplicates") + rejected,
        "{s}"
    );
    assert_eq!(
        count(&s, "transitions"),
        count(&s, "transitions_in_replay"),
        "{s}"
    );
    assert!(
        count(&s, "episodes") >= 80,
        "training went on to the budget: {s}"
    );
    let log = log(&dir, "learner");
    assert_eq!(
        log.matches("actor registered actor=trainer-1").count(),
        2,
        "{log}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn actors_reconnect_by_themselves_to_a_restarted_learner() {
    let dir = scratch("learner");
    let out = dir.join("out");
    // The same run both times (actors refuse a restarted learner with another config, by
    // design); only where the outputs go differs.
    let common = [
        "--env",
        "mountain-car",
        "--levels",
        "2",
        "--episodes",
        "60",
        "--set",
        "test_episodes=5",
    ];
    let first_out = dir.join("out-1");
    let mut args = vec![
        "learner",
        "--listen",
        "127.0.0.1:0",
        "--out",
        first_out.to_str().unwrap(),
    ];
    args.extend_from_slice(&common);
    let (first, addr) = learner(&args, &dir, "learner-1");
    let url = format!("http://{addr}");
    let mut processes = Processes(vec![("learner-1".into(), first)]);
    for name in ["trainer-0", "trainer-1"] {
        processes.0.push((
            name.into(),
            hac(&["actor", "--learner", &url, "--id", name], &dir, name),
        ));
    }
    // Let the actors register and stream for a while, then kill the learner outright.
    let started = Instant::now();
    while std::fs::read_to_string(dir.join("learner-1.log"))
        .unwrap_or_default()
        .matches("actor registered")
        .count()
        < 2
    {
        assert!(
            started.elapsed() < DEADLINE,
            "actors never registered\n{}",
            all_logs(&dir)
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    std::thread::sleep(Duration::from_secs(1));
    let (_, first) = processes
        .0
        .iter_mut()
        .find(|(n, _)| n == "learner-1")
        .unwrap();
    first.kill().unwrap();
    first.wait().unwrap();
    processes.0.retain(|(n, _)| n != "learner-1");
    // Down for a moment: the actors retry with backoff meanwhile.
    std::thread::sleep(Duration::from_millis(500));

    let mut args = vec!["learner", "--listen", &addr, "--out", out.to_str().unwrap()];
    args.extend_from_slice(&common);
    let (second, addr_again) = learner(&args, &dir, "learner-2");
    assert_eq!(addr_again, addr);
    processes.0.push(("learner-2".into(), second));

    processes.all_succeed(&dir, DEADLINE);
    let s = summary(&out);
    assert!(
        count(&s, "episodes_ingested") >= 60,
        "the restarted learner got a run's worth: {s}"
    );
    let log = std::fs::read_to_string(dir.join("learner-2.log")).unwrap();
    for name in ["trainer-0", "trainer-1"] {
        assert!(
            log.contains(&format!("actor registered actor={name}")),
            "{name} re-registered by itself\n{log}"
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
}
