//! deploy/local-cluster.sh in its short form, with the `hac` binary Cargo built for the tests:
//! a learner and 1, then 2, trainer processes (plus an evaluator) configured by deploy/hac.toml,
//! each run to its small budget, then one run scaled 1 -> 2 -> 1 trainers while it trains. The
//! script must finish cleanly and print a table whose figures come from real run directories.

use std::path::Path;
use std::process::Command;

/// Runs deploy/local-cluster.sh with `args` into the fresh directory `out` (and `--timeout 300`),
/// with the `hac` binary Cargo built; fails unless it exits 0. Returns its stdout and the cells
/// of its markdown table rows (headers included, separators left out).
fn run_script(out: &Path, args: &[&str]) -> (String, Vec<Vec<String>>) {
    let repo = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let _ = std::fs::remove_dir_all(out);
    let output = Command::new("bash")
        .arg(repo.join("deploy/local-cluster.sh"))
        .args(args)
        .args(["--timeout", "300", "--out"])
        .arg(out)
        .env("HAC_BIN", env!("CARGO_BIN_EXE_hac"))
        .env_remove("RUST_LOG")
        .output()
        .expect("bash runs");
    let stdout = String::from_utf8_lossy(&output.stdout).into_owned();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(
        output.status.success(),
        "local-cluster.sh {args:?} failed ({}):\n{stdout}\n{stderr}",
        output.status
    );
    let rows = stdout
        .lines()
        .filter(|l| l.starts_with("| ") && !l.starts_with("| ---"))
        .map(|l| {
            l.trim_matches('|')
                .split('|')
                .map(|c| c.trim().to_string())
                .collect()
        })
        .collect();
    (stdout, rows)
}

#[test]
fn the_local_cluster_script_runs_its_short_form() {
    let out = std::env::temp_dir().join(format!("hac-cluster-test-{}", std::process::id()));
    let (stdout, rows) = run_script(&out, &["--short"]);

    // | trainers | episodes | env steps/s | transitions/s | updates/s | t90 | e90 | wall |
    let runs: Vec<&Vec<String>> = rows.iter().filter(|r| r.len() == 8).collect();
    assert_eq!(runs.len(), 3, "a header and two runs:\n{stdout}");
    for (row, trainers) in runs[1..].iter().zip(["1", "2"]) {
        assert_eq!(row[0], trainers, "{stdout}");
        let number = |i: usize| -> f64 {
            row[i]
                .parse()
                .unwrap_or_else(|_| panic!("column {i} of {row:?} is not a number:\n{stdout}"))
        };
        assert!(
            number(1) >= 20.0,
            "the budget of 20 episodes was trained: {row:?}"
        );
        for column in [2, 3, 4, 7] {
            assert!(number(column) > 0.0, "column {column} of {row:?}");
        }
        // Every transition stored comes from an env step at some level: more of them than steps.
        assert!(
            number(3) >= number(2),
            "transitions/s >= env steps/s: {row:?}"
        );
    }
    let phases: Vec<&Vec<String>> = rows.iter().filter(|r| r.len() == 5).collect();
    assert_eq!(phases.len(), 4, "a header and three phases:\n{stdout}");
    let trainers: Vec<&str> = phases[1..].iter().map(|r| r[1].as_str()).collect();
    assert_eq!(trainers, ["1", "2", "1"], "{stdout}");
    // The scaled run: an evaluator and two distinct trainers registered.
    let log = std::fs::read_to_string(out.join("scaling/learner.log")).unwrap();
    assert!(
        log.matches("actor registered").count() >= 3,
        "registrations in the scaled run:\n{log}"
    );
    for n in [1, 2] {
        let summary = out.join(format!("actors-{n}/run/summary.json"));
        assert!(summary.is_file(), "{} is missing", summary.display());
    }
    let _ = std::fs::remove_dir_all(&out);
}

/// The grid form: every updates-per-episode value x trainer count x seed is a run of its own,
/// with the seed and the learner's ratio applied (read back from each run's config.toml), one
/// row per run and one summary row per ratio and trainer count.
#[test]
fn the_local_cluster_script_runs_a_grid_of_seeds_and_update_ratios() {
    let out = std::env::temp_dir().join(format!("hac-cluster-grid-test-{}", std::process::id()));
    let (stdout, rows) = run_script(
        &out,
        &[
            "--short",
            "--actors",
            "1",
            "--seeds",
            "3 4",
            "--updates",
            "10 5",
            "--scale",
            "",
        ],
    );
    // | updates per episode | seed | trainers | episodes | ... | wall time |
    let runs: Vec<&Vec<String>> = rows.iter().filter(|r| r.len() == 10).collect();
    let cells: Vec<(&str, &str, &str)> = runs[1..]
        .iter()
        .map(|r| (r[0].as_str(), r[1].as_str(), r[2].as_str()))
        .collect();
    assert_eq!(
        cells,
        [
            ("10", "3", "1"),
            ("10", "4", "1"),
            ("5", "3", "1"),
            ("5", "4", "1")
        ],
        "one run per ratio and seed, in that order:\n{stdout}"
    );
    for row in &runs[1..] {
        let episodes: f64 = row[3].parse().expect("episodes");
        assert!(
            episodes >= 20.0,
            "the budget of 20 episodes was trained: {row:?}"
        );
    }
    for (u, seed) in [(10, 3), (10, 4), (5, 3), (5, 4)] {
        let config = out.join(format!("actors-1-upe{u}-seed{seed}/run/config.toml"));
        let config = std::fs::read_to_string(&config)
            .unwrap_or_else(|e| panic!("{}: {e}", config.display()));
        assert!(config.contains(&format!("\nseed = {seed}\n")), "{config}");
        assert!(
            config.contains(&format!("\nupdates_per_episode = {u}\n")),
            "{config}"
        );
    }
    // | updates per episode | trainers | e90 | t90 | reached | wall sum |: 20 episodes never
    // reach 90%, so every median is "never".
    let summary: Vec<&Vec<String>> = rows.iter().filter(|r| r.len() == 6).collect();
    let cells: Vec<(&str, &str, &str, &str, &str)> = summary[1..]
        .iter()
        .map(|r| {
            (
                r[0].as_str(),
                r[1].as_str(),
                r[2].as_str(),
                r[3].as_str(),
                r[4].as_str(),
            )
        })
        .collect();
    assert_eq!(
        cells,
        [
            ("10", "1", "never", "never", "0 of 2"),
            ("5", "1", "never", "never", "0 of 2")
        ],
        "{stdout}"
    );
    let _ = std::fs::remove_dir_all(&out);
}
