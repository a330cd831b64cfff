//! A distributed run with the real `hac` binary: a learner service, three trainer actors and an
//! evaluator over loopback gRPC, to completion, learning mountain-car from nothing.

use std::io::{BufRead as _, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::time::{Duration, Instant};

const DEADLINE: Duration = Duration::from_secs(120);

fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!(
        "hac-distributed-test-{}-{name}",
        std::process::id()
    ));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// `hac <args>` with stderr to `<logs>/<name>.log`.
fn hac(args: &[&str], logs: &Path, name: &str) -> Child {
    let log = std::fs::File::create(logs.join(format!("{name}.log"))).unwrap();
    Command::new(env!("CARGO_BIN_EXE_hac"))
        .args(args)
        .env_remove("RUST_LOG")
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(log)
        .spawn()
        .expect("the hac binary runs")
}

/// Kills what still runs when a test fails, so that nothing outlives it.
struct Processes(Vec<(String, Child)>);

impl Processes {
    /// Waits for every process to exit, up to the deadline.
    fn wait_all(&mut self, logs: &Path) -> Vec<(String, ExitStatus)> {
        let started = Instant::now();
        let mut done = Vec::new();
        while done.len() < self.0.len() {
            for (name, child) in &mut self.0 {
                if done.iter().any(|(n, _)| n == name) {
                    continue;
                }
                if let Some(status) = child.try_wait().unwrap() {
                    done.push((name.clone(), status));
                }
            }
            if started.elapsed() > DEADLINE {
                panic!(
                    "still running after {DEADLINE:?} (finished: {done:?})\n{}",
                    all_logs(logs)
                );
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        done
    }
}

impl Drop for Processes {
    fn drop(&mut self) {
        for (_, child) in &mut self.0 {
            if child.try_wait().ok().flatten().is_none() {
                let _ = child.kill();
                let _ = child.wait();
            }
        }
    }
}

fn all_logs(logs: &Path) -> String {
    let mut text = String::new();
    for entry in std::fs::read_dir(logs).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_some_and(|e| e == "log") {
            let log = std::fs::read_to_string(&path).unwrap_or_default();
            let tail: Vec<&str> = log.lines().rev().take(30).collect();
            text += &format!("--- {}\n", path.display());
            for line in tail.into_iter().rev() {
                text += line;
                text.push('\n');
            }
        }
    }
    text
}

#[test]
fn a_learner_three_trainers_and_an_evaluator_learn_mountain_car() {
    let dir = scratch("run");
    let out = dir.join("out");
    let out_s = out.to_str().unwrap();
    let mut processes = Processes(Vec::new());
    let mut learner = hac(
        &[
            "learner",
            "--env",
            "mountain-car",
            "--levels",
            "2",
            "--episodes",
            "100",
            "--set",
            "test_episodes=20",
            "--listen",
            "127.0.0.1:0",
            "--out",
            out_s,
        ],
        &dir,
        "learner",
    );
    let mut first_line = String::new();
    BufReader::new(learner.stdout.take().unwrap())
        .read_line(&mut first_line)
        .unwrap();
    processes.0.push(("learner".into(), learner));
    let addr = first_line
        .trim()
        .strip_prefix("listening on ")
        .unwrap_or_else(|| {
            panic!(
                "expected `listening on <addr>`, got {first_line:?}\n{}",
                all_logs(&dir)
            )
        });
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

    let exits = processes.wait_all(&dir);
    for (name, status) in &exits {
        assert!(
            status.success(),
            "{name} exited with {status}\n{}",
            all_logs(&dir)
        );
    }

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
    let csv = std::fs::read_to_string(out.join("curve.csv")).unwrap();
    let rows: Vec<&str> = csv.lines().collect();
    assert!(rows[0].starts_with("round,episodes,env_steps,success_rate"));
    assert!(rows.len() >= 2, "at least one evaluation:\n{csv}");
    let last_episodes: u64 = rows
        .last()
        .unwrap()
        .split(',')
        .nth(1)
        .unwrap()
        .parse()
        .unwrap();
    assert!(
        last_episodes >= 100,
        "the last evaluation covers the budget:\n{csv}"
    );
    // Learned from nothing: untrained greedy agents never reach the flag (see the embedded
    // mountain-car test); the best evaluation must.
    let best = rows[1..]
        .iter()
        .map(|r| r.split(',').nth(3).unwrap().parse::<f32>().unwrap())
        .fold(0.0, f32::max);
    assert!(best >= 0.1, "best evaluation {best}:\n{csv}");
    let summary = std::fs::read_to_string(out.join("summary.json")).unwrap();
    assert!(summary.contains("\"episodes_ingested\""), "{summary}");
    let learner_log = std::fs::read_to_string(dir.join("learner.log")).unwrap();
    assert_eq!(
        learner_log.matches("actor registered").count(),
        4,
        "{learner_log}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}
