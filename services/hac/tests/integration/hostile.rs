//! `hac bench hostile --inputs N` in a short form: a real learner process with an honest trainer
//! while two hostile clients send every kind of bad input over gRPC. Every input must get the
//! answer its kind is due, the learner must not crash or publish a non-finite weight, and every
//! ingest message must be accounted for exactly once. (The long forms, a million inputs and a
//! minute-long attack while pendulum is learned, are measurements: docs/RESULTS.md.)

use std::process::Command;

#[test]
fn hostile_inputs_over_grpc_get_their_due_answers_and_break_nothing() {
    let dir = std::env::temp_dir().join(format!("hac-hostile-test-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let output = Command::new(env!("CARGO_BIN_EXE_hac"))
        .args([
            "bench",
            "hostile",
            "--inputs",
            "1500",
            "--clients",
            "2",
            "--trainers",
            "1",
            "--throughput-seconds",
            "1",
            "--json",
            "--dir",
        ])
        .arg(&dir)
        .env_remove("RUST_LOG")
        .output()
        .expect("the hac binary runs");
    let stdout = String::from_utf8_lossy(&output.stdout);
    let stderr = String::from_utf8_lossy(&output.stderr);
    let learner_log = std::fs::read_to_string(dir.join("learner.log")).unwrap_or_default();
    assert!(
        output.status.success(),
        "bench hostile failed ({}):\n{stdout}\n{stderr}\n--- learner.log\n{learner_log}",
        output.status
    );
    let report: serde_json::Value = serde_json::from_str(&stdout).unwrap();
    assert_eq!(report["mode"], "fuzz");
    assert_eq!(report["hostile_inputs"], 1500, "{report}");
    assert_eq!(report["wrong_answers"], 0, "{report}");
    assert_eq!(report["learner_crashed"], false, "{report}");
    assert_eq!(report["weights_non_finite"], 0, "{report}");
    assert_eq!(report["exactly_once"], true, "{report}");
    assert!(report["weights_versions_checked"].as_u64().unwrap() >= 1);
    // Every kind was tried, and the refusals were counted by the learner under their reasons.
    let kinds = report["kinds"].as_array().unwrap();
    assert_eq!(kinds.len(), 26, "{report}");
    for reason in [
        "out_of_range",
        "not_finite",
        "level_out_of_range",
        "invalid_batch",
        "unknown_actor",
        "stale_incarnation",
        "sequence_gap",
        "malformed",
    ] {
        assert!(
            report["refused"][reason].as_u64().unwrap_or(0) > 0,
            "no {reason} refusal: {report}"
        );
    }
    assert!(report["duplicates"].as_u64().unwrap() > 0, "{report}");
    assert!(report["throughput_transitions_per_s"].as_f64().unwrap() > 0.0);
    let _ = std::fs::remove_dir_all(&dir);
}
