//! Durable acknowledgements end to end, with the real `hac` binary: a learner killed with
//! SIGKILL at varied moments while two trainers stream to it (over gRPC five times; over shared
//! memory, `--shm` and `--transport shm`, three times), and started again with `--resume` on the
//! same address each time. Nothing the learner acknowledged as durable is lost (every actor
//! keeps its incarnation through every restart: a learner missing a durable message could not
//! keep it), nothing is stored twice (the learner's stored transitions are exactly the
//! transitions the actors sent), and both actors are back and ingesting within 10 s each time.

use std::path::Path;
use std::process::{Child, Command};
use std::time::{Duration, Instant};

use crate::common;

use common::{Processes, USING_SHM, all_logs, count, hac, hac_command, summary};

/// Kills of the learner with gRPC trainers, and with shared-memory ones.
const GRPC_KILLS: usize = 5;
const SHM_KILLS: usize = 3;
/// Actors back and ingesting after a restart within this.
const RECOVERY: Duration = Duration::from_secs(10);
const ACTORS: [&str; 2] = ["trainer-0", "trainer-1"];

/// A learner of the run in `out`, resumed if it has a checkpoint or a log; serving shared memory
/// too with `shm`.
fn learner(out: &Path, listen: &str, logs: &Path, name: &str, shm: bool) -> (Child, String) {
    let mut args = vec![
        "learner",
        "--env",
        "mountain-car",
        "--levels",
        "2",
        "--episodes",
        "100000",
        "--listen",
        listen,
        "--out",
        out.to_str().unwrap(),
        "--resume",
        "--checkpoint-every",
        "1.5",
        "--durable-interval",
        "0.1",
    ];
    if shm {
        args.push("--shm");
    }
    common::learner(&args, logs, name)
}

/// The learner's status as JSON, `None` while it does not answer.
fn status(addr: &str) -> Option<serde_json::Value> {
    let output = hac_command(&["status", "--learner", addr, "--json"], &[])
        .output()
        .ok()?;
    if !output.status.success() {
        return None;
    }
    let value: serde_json::Value = serde_json::from_slice(&output.stdout).ok()?;
    Some(value["learner"].clone())
}

/// Each actor's stored-through sequence on the learner (0 for one not registered).
fn stored(status: &serde_json::Value) -> [u64; 2] {
    ACTORS.map(|name| {
        status["actors"]
            .as_array()
            .into_iter()
            .flatten()
            .find(|a| a["actor_id"] == name)
            .and_then(|a| a["stored_through"].as_u64())
            .unwrap_or(0)
    })
}

/// Waits until both actors have stored more than `above` on the learner at `addr`; how long
/// that took from `since`.
fn ingesting(addr: &str, above: [u64; 2], since: Instant, logs: &Path) -> Duration {
    let mut last = None;
    loop {
        if let Some(s) = status(addr) {
            let now = stored(&s);
            if now[0] > above[0] && now[1] > above[1] {
                return since.elapsed();
            }
            last = Some(s);
        }
        assert!(
            since.elapsed() < Duration::from_secs(60),
            "the actors never came back above {above:?}; the learner's last status: {last:?}\n{}",
            all_logs(logs)
        );
        std::thread::sleep(Duration::from_millis(50));
    }
}

fn signal(child: &Child, signal: &str) {
    let status = Command::new("kill")
        .args([signal, &child.id().to_string()])
        .status()
        .unwrap();
    assert!(status.success());
}

/// `key=<u64>` from a log line.
fn field(line: &str, key: &str) -> u64 {
    line.split(&format!(" {key}="))
        .nth(1)
        .and_then(|v| v.split_whitespace().next())
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("no {key} in {line}"))
}

#[test]
fn kill_9_of_the_learner_five_times_loses_nothing_durable_and_stores_nothing_twice() {
    kills_lose_nothing_durable_and_store_nothing_twice("kills", "grpc", GRPC_KILLS);
}

#[test]
fn kill_9_of_a_learner_serving_shared_memory_loses_nothing_durable_and_stores_nothing_twice() {
    kills_lose_nothing_durable_and_store_nothing_twice("shm-kills", "shm", SHM_KILLS);
}

/// Two trainers sending over `transport` (`grpc` or `shm`) to a learner killed `kills` times;
/// see the module docs.
fn kills_lose_nothing_durable_and_store_nothing_twice(test: &str, transport: &str, kills: usize) {
    let shm = transport == "shm";
    let dir = common::scratch("hac-durable-test", test);
    let out = dir.join("out");
    let (child, addr) = learner(&out, "127.0.0.1:0", &dir, "learner-0", shm);
    // Killed on drop, like the actors, if the test fails half way.
    let mut serving = Processes(vec![("learner".into(), child)]);
    let url = format!("http://{addr}");
    let mut actors = Processes(Vec::new());
    for name in ACTORS {
        let args = [
            "actor",
            "--learner",
            &url,
            "--id",
            name,
            "--transport",
            transport,
            "--flush-timeout",
            "30",
        ];
        actors.0.push((name.into(), hac(&args, &dir, name)));
    }
    ingesting(&addr, [0, 0], Instant::now(), &dir);

    // Varied moments, from a fixed seed: 0.5 to 2.5 s of streaming before each kill.
    let mut seed: u64 = 20;
    let mut recoveries = Vec::new();
    for kill in 1..=kills {
        seed = seed
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        let pause = Duration::from_millis(500 + (seed >> 33) % 2000);
        std::thread::sleep(pause);
        let first = &mut serving.0[0].1;
        first.kill().unwrap(); // SIGKILL
        first.wait().unwrap();
        let killed = Instant::now();
        let (again, addr_again) = learner(&out, &addr, &dir, &format!("learner-{kill}"), shm);
        assert_eq!(addr_again, addr);
        serving.0[0].1 = again;
        // What the restarted learner holds once it answers, then the actors ingesting beyond it.
        let recovered = loop {
            if let Some(s) = status(&addr) {
                break stored(&s);
            }
            std::thread::sleep(Duration::from_millis(20));
        };
        let back = ingesting(&addr, recovered, killed, &dir);
        eprintln!(
            "kill {kill} after {pause:?}: recovered stored-through {recovered:?}, ingesting again after {back:?}"
        );
        assert!(
            back < RECOVERY,
            "kill {kill}: the actors took {back:?}\n{}",
            all_logs(&dir)
        );
        recoveries.push(back);
        let log = std::fs::read_to_string(dir.join(format!("learner-{kill}.log"))).unwrap();
        assert!(
            log.contains("write-ahead log replayed") || log.contains("resuming the run"),
            "kill {kill}: {log}"
        );
    }

    // The end: the actors stop (SIGTERM: their episode, then everything flushed until durable),
    // then the learner (SIGTERM: drained, saved).
    for (_, actor) in &actors.0 {
        signal(actor, "-TERM");
    }
    actors.all_succeed(&dir, Duration::from_secs(60));
    signal(&serving.0[0].1, "-TERM");
    serving.all_succeed(&dir, Duration::from_secs(60));

    let (mut sent, mut durable) = (0, 0);
    for name in ACTORS {
        let log = std::fs::read_to_string(dir.join(format!("{name}.log"))).unwrap();
        let line = log
            .lines()
            .find(|l| l.contains("actor stopped"))
            .unwrap_or_else(|| panic!("{name} did not stop cleanly\n{log}"));
        if shm {
            assert!(
                log.contains(USING_SHM) && !log.contains("using gRPC"),
                "{name} sent over shared memory throughout\n{log}"
            );
        }
        sent += field(line, "sent_transitions");
        durable += field(line, "durable_transitions");
        assert_eq!(field(line, "undurable"), 0, "{line}");
        // The resumed learners knew the actor's incarnation (from checkpoint and log): it was
        // never renumbered, which a learner lacking a durable message would have forced.
        assert!(
            !log.lines().any(
                |l| l.contains("registered again with the learner") && l.contains("kept=false")
            ),
            "{name} was renumbered: a restarted learner lacked something durable\n{log}"
        );
        let first = std::fs::read_to_string(dir.join("learner-0.log")).unwrap();
        let registered = first
            .lines()
            .find(|l| l.contains(&format!("actor registered actor={name} ")))
            .unwrap_or_else(|| panic!("{name} registered\n{first}"));
        assert_eq!(
            field(line, "incarnation"),
            field(registered, "incarnation"),
            "{name} kept its first incarnation through every restart\n{log}"
        );
        for kill in 1..=kills {
            let restarted =
                std::fs::read_to_string(dir.join(format!("learner-{kill}.log"))).unwrap();
            assert!(
                !restarted.contains(&format!("actor registered actor={name} ")),
                "learner-{kill} gave {name} a fresh incarnation\n{restarted}"
            );
        }
    }
    let s = summary(&out);
    eprintln!(
        "sent {sent}, durable {durable}, stored {}, duplicates {}, recoveries {recoveries:?}",
        count(&s, "transitions"),
        count(&s, "duplicates")
    );
    assert_eq!(durable, sent, "everything sent became durable");
    assert_eq!(
        count(&s, "transitions"),
        sent,
        "every transition sent stored exactly once: {s}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}
