//! Checkpoints and resume with real processes: a learner checkpointing every second is killed
//! with SIGKILL, its newest checkpoint is damaged, and a learner started with `--resume` skips it,
//! continues from the one before (weights version, counters, learning curve), gets its actors
//! back and finishes the run; the run's policy then exports from its checkpoints.

use crate::common;
use std::path::{Path, PathBuf};
use std::process::{Child, Command};
use std::time::{Duration, Instant};

use common::{Processes, all_logs, hac, learner};

const DEADLINE: Duration = Duration::from_secs(240);

fn scratch(name: &str) -> PathBuf {
    common::scratch("hac-resume-test", name)
}

impl Processes {
    fn take(&mut self, name: &str) -> Child {
        let i = self.0.iter().position(|(n, _)| n == name).unwrap();
        self.0.remove(i).1
    }
}

/// The complete checkpoints (named `ckpt-*`), oldest first.
fn checkpoints(out: &Path) -> Vec<PathBuf> {
    let mut found: Vec<PathBuf> = std::fs::read_dir(out.join("checkpoints"))
        .map(|entries| {
            entries
                .map(|e| e.unwrap().path())
                .filter(|p| {
                    p.file_name()
                        .unwrap()
                        .to_string_lossy()
                        .starts_with("ckpt-")
                })
                .collect()
        })
        .unwrap_or_default();
    found.sort();
    found
}

fn state(checkpoint: &Path) -> serde_json::Value {
    let text = std::fs::read_to_string(checkpoint.join("learner.json")).unwrap();
    serde_json::from_str(&text).unwrap()
}

fn u64_at(value: &serde_json::Value, pointer: &str) -> u64 {
    value
        .pointer(pointer)
        .and_then(serde_json::Value::as_u64)
        .unwrap_or_else(|| panic!("{pointer} in {value}"))
}

fn updates(state: &serde_json::Value) -> Vec<u64> {
    state["levels"]
        .as_array()
        .unwrap()
        .iter()
        .map(|l| l["updates"].as_u64().unwrap())
        .collect()
}

fn name(path: &Path) -> String {
    path.file_name().unwrap().to_string_lossy().into_owned()
}

#[test]
fn a_learner_killed_with_sigkill_resumes_from_its_last_valid_checkpoint() {
    let dir = scratch("run");
    let out = dir.join("out");
    let out_s = out.to_str().unwrap();
    let learner_args = |listen: &str, resume: bool| {
        let mut args = vec![
            "learner",
            "--env",
            "mountain-car",
            "--levels",
            "2",
            // Far beyond the two evaluated checkpoints the kill waits for (about 2 s): with 80
            // the run once finished by itself, in 4 s, before the kill.
            "--episodes",
            "200",
            "--set",
            "test_episodes=5",
            "--checkpoint-every",
            "1",
            "--keep-checkpoints",
            "4",
            "--listen",
            listen,
            "--out",
            out_s,
        ]
        .into_iter()
        .map(str::to_string)
        .collect::<Vec<_>>();
        if resume {
            args.push("--resume".into());
        }
        args
    };
    let first_args = learner_args("127.0.0.1:0", false);
    let first_args: Vec<&str> = first_args.iter().map(String::as_str).collect();
    let (first, addr) = learner(&first_args, &dir, "learner-1");
    let url = format!("http://{addr}");
    let mut processes = Processes(vec![("learner-1".into(), first)]);
    for (name, extra) in [
        (
            "evaluator",
            &["--role", "evaluator", "--eval-every", "10"][..],
        ),
        ("trainer-0", &["--role", "trainer"][..]),
    ] {
        let mut args = vec!["actor", "--learner", &url, "--id", name];
        args.extend_from_slice(extra);
        processes.0.push((name.into(), hac(&args, &dir, name)));
    }

    // Two checkpoints that hold an evaluation, then SIGKILL: no shutdown, no final checkpoint.
    let started = Instant::now();
    // (Read defensively: the learner prunes old checkpoints meanwhile.)
    let evaluated = |c: &PathBuf| {
        c.join("MANIFEST").exists()
            && std::fs::read_to_string(c.join("learner.json"))
                .ok()
                .and_then(|text| serde_json::from_str::<serde_json::Value>(&text).ok())
                .is_some_and(|s| s["curve"].as_array().is_some_and(|a| !a.is_empty()))
    };
    while checkpoints(&out).iter().filter(|c| evaluated(c)).count() < 2 {
        assert!(
            started.elapsed() < DEADLINE,
            "no two checkpoints with an evaluation\n{}",
            all_logs(&dir)
        );
        std::thread::sleep(Duration::from_millis(100));
    }
    let mut first = processes.take("learner-1");
    first.kill().unwrap(); // SIGKILL
    assert!(!first.wait().unwrap().success());
    let csv_before = std::fs::read_to_string(out.join("curve.csv")).unwrap();

    // Damage the newest checkpoint: cut a weights file in half.
    let all = checkpoints(&out);
    let (previous, newest) = (&all[all.len() - 2], &all[all.len() - 1]);
    let victim = newest.join("level1.safetensors");
    let full = std::fs::read(&victim).unwrap();
    std::fs::write(&victim, &full[..full.len() / 2]).unwrap();
    let saved = state(previous);
    let saved_version = u64_at(&saved, "/weights_version");
    let saved_episodes = u64_at(&saved, "/counters/episodes");
    let saved_updates = updates(&saved);
    let saved_rounds = saved["curve"].as_array().unwrap().len();
    assert!(saved_rounds >= 1 && saved_episodes >= 10, "{saved}");

    // Another run's config is refused, naming what differs, before anything is bound.
    let mut other = learner_args(&addr, true);
    other.extend(["--seed".to_string(), "5".to_string()]);
    let o = Command::new(env!("CARGO_BIN_EXE_hac"))
        .args(&other)
        .env_remove("RUST_LOG")
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "{stderr}");
    assert!(
        stderr.contains("`seed` is 0 in the checkpoint, 5 now"),
        "{stderr}"
    );
    assert!(!String::from_utf8_lossy(&o.stdout).contains("listening on"));

    // The same run, resumed on the same address: the actors find it by themselves.
    let second_args = learner_args(&addr, true);
    let second_args: Vec<&str> = second_args.iter().map(String::as_str).collect();
    let (second, addr_again) = learner(&second_args, &dir, "learner-2");
    assert_eq!(addr_again, addr);
    processes.0.push(("learner-2".into(), second));
    processes.all_succeed(&dir, DEADLINE);

    let log = std::fs::read_to_string(dir.join("learner-2.log")).unwrap();
    let skipped = format!(
        "checkpoint {} is corrupt: level1.safetensors is {} bytes, MANIFEST says {}; using {}",
        name(newest),
        full.len() / 2,
        full.len(),
        name(previous)
    );
    assert!(log.contains(&skipped), "expected {skipped:?} in\n{log}");
    assert!(
        log.contains("resuming the run")
            && log.contains(&format!("checkpoint={}", name(previous)))
            && log.contains(&format!("weights_version={saved_version}")),
        "{log}"
    );
    // The log after the older checkpoint's cut is still there (it is kept from the oldest kept
    // checkpoint on), so the resumed learner knows the trainer under its incarnation and the
    // trainer's stream simply goes on; the evaluator (never in the registry a log restores)
    // registers again.
    assert!(
        !log.contains("does not continue the checkpoint"),
        "the log continues the older checkpoint\n{log}"
    );
    assert!(
        log.contains("write-ahead log replayed")
            || log.contains("actor registered actor=trainer-0"),
        "trainer-0 came back by itself\n{log}"
    );
    assert!(
        log.contains("actor registered actor=evaluator"),
        "the evaluator came back by itself\n{log}"
    );

    // Counters and versions continued from the checkpoint, and training went on to the budget.
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    assert!(
        u64_at(&summary, "/weights_version") > saved_version,
        "{summary}"
    );
    assert!(u64_at(&summary, "/episodes_ingested") >= 200, "{summary}");
    let last = checkpoints(&out).pop().unwrap();
    let last = state(&last);
    assert!(u64_at(&last, "/weights_version") > saved_version, "{last}");
    assert!(
        u64_at(&last, "/counters/episodes") > saved_episodes,
        "{last}"
    );
    for (now, then) in updates(&last).iter().zip(&saved_updates) {
        assert!(now > then, "updates continue: {now} after {then}");
    }
    assert!(last["completed"].is_string(), "the run completed: {last}");

    // The curve continues the checkpoint's: its rows first (rows recorded after the checkpoint
    // went with the killed learner), then new ones, every round once.
    let csv = std::fs::read_to_string(out.join("curve.csv")).unwrap();
    let rows: Vec<&str> = csv.lines().collect();
    let before: Vec<&str> = csv_before.lines().collect();
    // (The killed learner wrote rows a moment after they reached its curve.)
    let kept = saved_rounds.min(before.len() - 1);
    assert!(kept >= 1, "{csv_before}");
    assert_eq!(rows[..=kept], before[..=kept], "{csv}");
    assert!(
        rows.len() > saved_rounds + 1,
        "new evaluations after resuming:\n{csv}"
    );
    let column = |row: &str, i: usize| row.split(',').nth(i).unwrap().parse::<f64>().unwrap();
    for (i, row) in rows[1..].iter().enumerate() {
        assert_eq!(
            column(row, 0),
            (i + 1) as f64,
            "round numbers run on:\n{csv}"
        );
    }
    for pair in rows[1..].windows(2) {
        assert!(
            column(pair[1], 1) >= column(pair[0], 1),
            "episodes never go back:\n{csv}"
        );
        assert!(
            column(pair[1], 4) >= column(pair[0], 4),
            "elapsed time goes on:\n{csv}"
        );
    }

    // A complete run has nothing to resume.
    let o = Command::new(env!("CARGO_BIN_EXE_hac"))
        .args(&second_args)
        .env_remove("RUST_LOG")
        .output()
        .unwrap();
    assert!(o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("nothing to resume"));

    // The trained policy exports from the newest checkpoint.
    let policy = dir.join("policy.safetensors");
    let o = Command::new(env!("CARGO_BIN_EXE_hac"))
        .args(["export", "--run", out_s, "--out", policy.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(String::from_utf8_lossy(&o.stdout).contains("from checkpoint ckpt-"));
    let bytes = std::fs::read(&policy).unwrap();
    let (_, header) = safetensors::SafeTensors::read_metadata(&bytes).unwrap();
    let meta = header.metadata().clone().unwrap();
    assert_eq!(meta["env"], "mountain-car");
    assert_eq!(meta["levels"], "2");
    assert_eq!(
        meta["weights_version"],
        u64_at(&last, "/weights_version").to_string()
    );
    let _ = std::fs::remove_dir_all(&dir);
}
