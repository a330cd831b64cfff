//! deploy/local-cluster.sh in its short form, with the `hac` binary Cargo built for the tests:
//! a learner and 1, then 2, trainer processes (plus an evaluator) configured by deploy/hac.toml,
//! each run to its small budget, then one run scaled 1 -> 2 -> 1 trainers while it trains. The
//! script must finish cleanly and print a table whose figures come from real run directories.

use std::path::Path;
use std::process::Command;

#[test]
fn the_local_cluster_script_runs_its_short_form() {
    let repo = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let out = std::env::temp_dir().join(format!("hac-cluster-test-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
    let output = Command::new("bash")
        .arg(repo.join("deploy/local-cluster.sh"))
        .args(["--short", "--timeout", "300", "--out"])
        .arg(&out)
        .env("HAC_BIN", env!("CARGO_BIN_EXE_hac"))
        .env_remove("RUST_LOG")
        .output()
        .expect("bash runs");
    let stdout = String::from_utf8_lossy(&output.stdout);
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(
        output.status.success(),
        "local-cluster.sh --short failed ({}):\n{stdout}\n{stderr}",
        output.status
    );

    // | trainers | episodes | env steps/s | transitions/s | updates/s | t90 | e90 | wall |
    let rows: Vec<Vec<&str>> = stdout
        .lines()
        .filter(|l| l.starts_with("| ") && !l.starts_with("| ---"))
        .map(|l| l.trim_matches('|').split('|').map(str::trim).collect())
        .collect();
    let runs: Vec<&Vec<&str>> = rows.iter().filter(|r| r.len() == 8).collect();
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
    let phases: Vec<&Vec<&str>> = rows.iter().filter(|r| r.len() == 5).collect();
    assert_eq!(phases.len(), 4, "a header and three phases:\n{stdout}");
    let trainers: Vec<&str> = phases[1..].iter().map(|r| r[1]).collect();
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
