//! `hac experiment --resume`: an interrupted grid is finished in the same `--out`, its finished
//! runs read back untouched and summarised with the runs trained now, its unfinished runs (killed:
//! no `summary.json`; stopped by Ctrl-C: a summary short of the budget) trained again; a finished
//! run of another configuration, and `--resume` with `--overwrite`, are refused before any run
//! starts.

use std::path::{Path, PathBuf};
use std::process::Output;
use std::time::SystemTime;

use crate::common;
use common::{curve_without_times, hac_output, text};

fn scratch(name: &str) -> PathBuf {
    common::fresh_path("hac-experiment-resume-test", name)
}

/// `hac experiment` over a grid small enough for a debug build: a neural run (pendulum) and a
/// tabular one (four-rooms), 1 level, two seeds each, two test rounds of 3 episodes per run,
/// episodes of at most 50 actions.
fn experiment(out: &Path, extra: &[&str]) -> Output {
    let mut args = vec![
        "experiment",
        "--env",
        "pendulum,four-rooms",
        "--levels",
        "1",
        "--seeds",
        "2",
        "--episodes",
        "4",
        "--max-actions",
        "50",
        "--set",
        "exploration_episodes=2",
        "--set",
        "test_episodes=3",
        "--jobs",
        "2",
        "--learner-threads",
        "1",
        "--out",
        out.to_str().unwrap(),
    ];
    args.extend_from_slice(extra);
    hac_output(&args)
}

/// A file's bytes and modification time.
fn snapshot(path: &Path) -> (Vec<u8>, SystemTime) {
    let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    (bytes, std::fs::metadata(path).unwrap().modified().unwrap())
}

fn summary_json(run: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(run.join("summary.json")).unwrap()).unwrap()
}

/// The mean wall time per run of the first table row after `## <env>` in `summary.md`.
fn wall_time(summary_md: &str, env: &str) -> f64 {
    let table = summary_md
        .split(&format!("## {env}\n"))
        .nth(1)
        .unwrap_or_else(|| panic!("no table for {env}: {summary_md}"));
    let row = table
        .lines()
        .find(|l| l.starts_with("| 1 |"))
        .unwrap_or_else(|| panic!("no row for 1 level: {table}"));
    let cells: Vec<&str> = row.split('|').map(str::trim).collect();
    cells[cells.len() - 2]
        .trim_end_matches(" s")
        .parse()
        .unwrap_or_else(|_| panic!("wall time in {row}"))
}

#[test]
fn resume_reuses_finished_runs_and_trains_unfinished_ones_again() {
    let out = scratch("grid");
    let o = experiment(&out, &[]);
    assert!(o.status.success(), "experiment failed: {}", text(&o.stderr));

    // The finished runs: pendulum seed 0 (its recorded wall time made recognisable, so that the
    // summary shows where its figures come from) and four-rooms seed 0.
    let kept_pendulum = out.join("pendulum-1l-seed0");
    let kept_rooms = out.join("four-rooms-1l-seed0");
    let mut summary = summary_json(&kept_pendulum);
    summary["wall_time_s"] = serde_json::json!(1000.0);
    std::fs::write(
        kept_pendulum.join("summary.json"),
        serde_json::to_string_pretty(&summary).unwrap(),
    )
    .unwrap();
    let files = ["config.toml", "curve.csv", "summary.json"];
    let before: Vec<_> = [&kept_pendulum, &kept_rooms]
        .iter()
        .flat_map(|run| files.iter().map(move |f| run.join(f)))
        .map(|path| (snapshot(&path), path))
        .collect();

    // Pendulum seed 1 was killed: no summary. Four-rooms seed 1 was stopped by Ctrl-C after its
    // first round: a summary (written at the interrupt) and a curve short of the 4 episodes.
    let killed = out.join("pendulum-1l-seed1");
    std::fs::remove_file(killed.join("summary.json")).unwrap();
    let stopped = out.join("four-rooms-1l-seed1");
    let csv = std::fs::read_to_string(stopped.join("curve.csv")).unwrap();
    let rows: Vec<&str> = csv.lines().collect();
    assert_eq!(
        rows.len(),
        3,
        "two rounds before the interrupt is faked:\n{csv}"
    );
    std::fs::write(
        stopped.join("curve.csv"),
        format!("{}\n{}\n", rows[0], rows[1]),
    )
    .unwrap();
    let mut summary = summary_json(&stopped);
    summary["rounds"] = serde_json::json!(1);
    summary["episodes"] = serde_json::json!(2);
    std::fs::write(
        stopped.join("summary.json"),
        serde_json::to_string_pretty(&summary).unwrap(),
    )
    .unwrap();
    std::fs::remove_file(out.join("summary.md")).unwrap();

    let o = experiment(&out, &["--resume"]);
    let stdout = text(&o.stdout);
    assert!(
        o.status.success(),
        "resume failed: {}\n{stdout}",
        text(&o.stderr)
    );
    assert!(
        stdout.contains("(2 finished already, 2 to train)"),
        "{stdout}"
    );
    for reused in [
        "pendulum hac 1 level, seed 0: reused (final ",
        "four-rooms hac 1 level, seed 0: reused (final ",
    ] {
        assert_eq!(stdout.matches(reused).count(), 1, "{reused}:\n{stdout}");
    }
    assert!(
        stdout.contains(", 1000.0s)"),
        "recorded wall time:\n{stdout}"
    );
    for again in [
        "pendulum-1l-seed1: unfinished (no summary.json",
        "four-rooms-1l-seed1: unfinished (interrupted after 2 of 4 episodes)",
        "pendulum hac 1 level, seed 1: final ",
        "four-rooms hac 1 level, seed 1: final ",
    ] {
        assert_eq!(stdout.matches(again).count(), 1, "{again}:\n{stdout}");
    }
    assert_eq!(
        stdout.matches("(trained again: it was unfinished)").count(),
        2,
        "{stdout}"
    );
    assert_eq!(
        stdout.lines().filter(|l| l.starts_with('[')).count(),
        4,
        "a line per run:\n{stdout}"
    );

    // The finished runs were not touched; the unfinished ones were trained to the end again.
    for ((bytes, modified), path) in &before {
        let (now, when) = snapshot(path);
        assert!(
            now == *bytes && when == *modified,
            "{} changed",
            path.display()
        );
    }
    for run in [&killed, &stopped] {
        let summary = summary_json(run);
        assert_eq!(
            (&summary["episodes"], &summary["rounds"]),
            (&serde_json::json!(4), &serde_json::json!(2)),
            "{}: {summary}",
            run.display()
        );
        assert_eq!(
            std::fs::read_to_string(run.join("curve.csv"))
                .unwrap()
                .lines()
                .count(),
            3,
            "{}",
            run.display()
        );
    }

    // The summary covers both seeds of each environment, the reused with its recorded figures.
    let summary_md = std::fs::read_to_string(out.join("summary.md")).unwrap();
    assert_eq!(summary_md.matches("| 1 | 2 |").count(), 2, "{summary_md}");
    let pendulum_wall = wall_time(&summary_md, "pendulum");
    assert!(
        (500.0..600.0).contains(&pendulum_wall),
        "mean of 1000 s (reused) and a few seconds: {pendulum_wall}\n{summary_md}"
    );
    assert!(wall_time(&summary_md, "four-rooms") < 100.0, "{summary_md}");
    for env in ["pendulum", "four-rooms"] {
        let svg = std::fs::read_to_string(out.join(format!("{env}.svg"))).unwrap();
        assert_eq!(svg.matches("<polyline").count(), 1, "{env}: {svg}");
    }

    // Everything finished now: a second resume trains nothing.
    let o = experiment(&out, &["--resume"]);
    let stdout = text(&o.stdout);
    assert!(o.status.success(), "{}", text(&o.stderr));
    assert!(
        stdout.contains("(4 finished already, 0 to train)")
            && stdout.matches(": reused (").count() == 4,
        "{stdout}"
    );
    assert_eq!(
        std::fs::read_to_string(out.join("summary.md")).unwrap(),
        summary_md,
        "the same runs give the same summary"
    );
    let _ = std::fs::remove_dir_all(&out);
}

#[test]
fn resume_refuses_a_finished_run_of_another_configuration_and_overwrite() {
    let out = scratch("refusals");
    let out_s = out.to_str().unwrap();
    // One four-rooms seed, then two: the second seed's run would be new, so that a refusal after
    // starting would leave its directory behind.
    let grid = |seeds: &str, episodes: &str, extra: &[&str]| {
        let mut args = vec![
            "experiment",
            "--env",
            "four-rooms",
            "--levels",
            "1",
            "--seeds",
            seeds,
            "--episodes",
            episodes,
            "--set",
            "exploration_episodes=2",
            "--out",
            out_s,
        ];
        args.extend_from_slice(extra);
        hac_output(&args)
    };
    let o = grid("1", "4", &[]);
    assert!(o.status.success(), "experiment failed: {}", text(&o.stderr));
    let run = out.join("four-rooms-1l-seed0");
    let curve = snapshot(&run.join("curve.csv"));

    // Other episodes; another agent key.
    for (episodes, extra, key) in [
        ("6", &[][..], "`episodes` is 4 there and 6 in this grid"),
        (
            "4",
            &["--set", "test_episodes=7"][..],
            "`agent.test_episodes` is ",
        ),
    ] {
        let mut args = extra.to_vec();
        args.push("--resume");
        let o = grid("2", episodes, &args);
        let stderr = text(&o.stderr);
        assert!(!o.status.success(), "{extra:?} was resumed: {stderr}");
        assert!(
            stderr.contains(&format!(
                "{} holds a finished run of another configuration",
                run.display()
            )) && stderr.contains(key)
                && stderr.contains("--overwrite"),
            "{extra:?}: {stderr}"
        );
        assert!(
            !out.join("four-rooms-1l-seed1").exists(),
            "{extra:?}: a run started before the refusal"
        );
    }
    assert!(
        snapshot(&run.join("curve.csv")) == curve,
        "the run was touched"
    );

    let o = grid("1", "4", &["--resume", "--overwrite"]);
    let stderr = text(&o.stderr);
    assert!(
        !o.status.success() && stderr.contains("`--resume` and `--overwrite` contradict"),
        "{stderr}"
    );
    assert!(
        snapshot(&run.join("curve.csv")) == curve,
        "the run was touched"
    );
    let _ = std::fs::remove_dir_all(&out);
}

/// A grid run with `--keep-state` trains on with `--resume` and a larger `--episodes`: every run
/// goes on from its saved state and ends as the run the larger budget gives from the start.
#[test]
fn resume_trains_a_kept_grid_on_to_a_larger_budget() {
    let (kept, whole) = (scratch("kept"), scratch("whole"));
    let grid = |out: &Path, episodes: &str, extra: &[&str]| {
        let mut args = vec![
            "experiment",
            "--env",
            "pendulum",
            "--levels",
            "1",
            "--seeds",
            "2",
        ];
        args.extend(["--episodes", episodes, "--max-actions", "50"]);
        args.extend([
            "--set",
            "exploration_episodes=2",
            "--set",
            "test_episodes=3",
        ]);
        args.extend([
            "--jobs",
            "2",
            "--learner-threads",
            "1",
            "--out",
            out.to_str().unwrap(),
        ]);
        args.extend_from_slice(extra);
        let o = hac_output(&args);
        assert!(o.status.success(), "experiment failed: {}", text(&o.stderr));
        text(&o.stdout)
    };
    grid(&whole, "6", &[]);
    grid(&kept, "4", &["--keep-state"]);
    let stdout = grid(&kept, "6", &["--resume"]);
    for seed in 0..2 {
        let run = format!("pendulum-1l-seed{seed}");
        assert!(
            stdout.contains(&format!(
                "{run}: going on from its saved state at 4 episodes to 6"
            )),
            "{stdout}"
        );
        let (a, b) = (kept.join(&run), whole.join(&run));
        assert_eq!(curve_without_times(&a), curve_without_times(&b));
        let weights = |r: &Path| std::fs::read(r.join("weights/level0.safetensors")).unwrap();
        assert!(weights(&a) == weights(&b), "{run}: the weights differ");
        assert_eq!(summary_json(&a)["episodes"], 6);
    }
    assert!(
        stdout.contains("(0 finished already, 2 to train)"),
        "{stdout}"
    );
    // Resumed again at the same budget, both runs are finished: read back.
    let stdout = grid(&kept, "6", &["--resume"]);
    assert!(
        stdout.contains("(2 finished already, 0 to train)"),
        "{stdout}"
    );
    let _ = std::fs::remove_dir_all(&kept);
    let _ = std::fs::remove_dir_all(&whole);
}
