//! The `hac` binary as a user runs it: train writes a complete run directory, eval reads it
//! back, and bad configuration fails early with the offending key named; addresses are taken
//! in one form everywhere, and errors say each cause once.

use std::path::{Path, PathBuf};
use std::process::{Command, ExitStatus, Output};

use crate::common;
use common::{curve_without_times, hac_output, text};

fn scratch(name: &str) -> PathBuf {
    common::fresh_path("hac-cli-test", name)
}

#[test]
fn train_writes_a_run_directory_and_eval_reads_it() {
    let out = scratch("train");
    let out_s = out.to_str().unwrap();
    let o = hac_output(&[
        "train",
        "--env",
        "mountain-car",
        "--episodes",
        "20",
        "--seed",
        "3",
        "--set",
        "test_episodes=5",
        "--out",
        out_s,
    ]);
    assert!(o.status.success(), "train failed: {}", text(&o.stderr));
    let stdout = text(&o.stdout);
    assert_eq!(
        stdout.lines().filter(|l| l.starts_with("round ")).count(),
        2,
        "one progress line per test round:\n{stdout}"
    );
    assert!(
        stdout.contains("success")
            && stdout.contains("env steps/s")
            && stdout.contains("updates/s")
    );

    for file in [
        "config.toml",
        "curve.csv",
        "curve.svg",
        "summary.json",
        "weights/level0.safetensors",
        "weights/level1.safetensors",
    ] {
        assert!(out.join(file).is_file(), "missing {file}");
    }
    let csv = std::fs::read_to_string(out.join("curve.csv")).unwrap();
    let lines: Vec<&str> = csv.lines().collect();
    assert_eq!(lines.len(), 3, "header and two rounds:\n{csv}");
    assert!(lines[0].starts_with("round,episodes,env_steps,success_rate"));
    assert!(lines[2].starts_with("2,20,"));
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    assert_eq!(summary["episodes"], 20);

    // The saved config reproduces the run's settings.
    let config = std::fs::read_to_string(out.join("config.toml")).unwrap();
    assert!(
        config.contains("env = \"mountain-car\"")
            && config.contains("seed = 3")
            && config.contains("test_episodes = 5")
    );

    // A second run into the same directory is refused; --overwrite replaces it.
    let again = [
        "train",
        "--env",
        "mountain-car",
        "--episodes",
        "10",
        "--set",
        "test_episodes=2",
        "--out",
        out_s,
    ];
    let o = hac_output(&again);
    assert!(
        !o.status.success() && text(&o.stderr).contains("--overwrite"),
        "{}",
        text(&o.stderr)
    );
    assert!(
        std::fs::read_to_string(out.join("config.toml"))
            .unwrap()
            .contains("test_episodes = 5"),
        "the first run was kept"
    );
    let o = hac_output(&[&again[..], &["--overwrite", "--seed", "3"]].concat());
    assert!(o.status.success(), "{}", text(&o.stderr));

    let o = hac_output(&["eval", "--run", out_s, "--episodes", "4", "--json"]);
    assert!(o.status.success(), "eval failed: {}", text(&o.stderr));
    let result: serde_json::Value = serde_json::from_str(text(&o.stdout).trim()).unwrap();
    assert_eq!(result["episodes"], 4);
    let rate = result["success_rate"].as_f64().unwrap();
    assert!((0.0..=1.0).contains(&rate));
    let moved = result["moved_rate"].as_f64().unwrap();
    assert!((0.0..=1.0).contains(&moved), "{result}");

    // What each level did, summed over the episodes: every level's attempts call the level
    // below once each, and the top level is called once per episode.
    let levels: Vec<serde_json::Value> =
        serde_json::from_value(result["per_level"].clone()).unwrap();
    assert_eq!(levels.len(), 2, "{result}");
    assert_eq!(levels[1]["calls"], 4, "{result}");
    assert_eq!(levels[0]["calls"], levels[1]["attempts"], "{result}");
    assert_eq!(
        levels[1]["tested"], 0,
        "greedy episodes test nothing: {result}"
    );

    // The behaviour policy of training: subgoals are tested, and each penalty is a test.
    let o = hac_output(&[
        "eval",
        "--run",
        out_s,
        "--episodes",
        "4",
        "--behaviour",
        "--json",
    ]);
    assert!(o.status.success(), "eval failed: {}", text(&o.stderr));
    let result: serde_json::Value = serde_json::from_str(text(&o.stdout).trim()).unwrap();
    assert_eq!(result["mode"], "behaviour");
    let levels: Vec<serde_json::Value> =
        serde_json::from_value(result["per_level"].clone()).unwrap();
    let count = |l: usize, key: &str| levels[l][key].as_u64().unwrap();
    assert!(count(1, "tested") > 0, "{result}");
    assert!(count(1, "penalties") <= count(1, "tested"), "{result}");
    assert_eq!(
        count(0, "tested"),
        0,
        "level 0 proposes no subgoals: {result}"
    );

    // A reader that stops early (`| head -n 1`) ends the command quietly, not with a panic.
    let (first, status, stderr) = first_line_then_close(
        &[
            "eval",
            "--run",
            out_s,
            "--episodes",
            "5000",
            "--per-episode",
        ],
        "",
    );
    assert!(first.starts_with("{\"end_goal\":"), "{first}");
    assert!(status.success() && stderr.is_empty(), "{status}: {stderr}");

    // --per-episode: one line per episode with its end goal, final state and what each level
    // did, then the summary and a line per level.
    let o = hac_output(&["eval", "--run", out_s, "--episodes", "3", "--per-episode"]);
    assert!(o.status.success(), "eval failed: {}", text(&o.stderr));
    let stdout = text(&o.stdout);
    let lines: Vec<&str> = stdout.lines().collect();
    assert_eq!(lines.len(), 7, "{lines:?}");
    assert!(
        lines[4].contains("achieved end goal moved")
            && lines[5]
                .trim_start()
                .starts_with("level 1: 3 calls, goal reached in")
            && lines[6].trim_start().starts_with("level 0: "),
        "{lines:?}"
    );
    for (i, line) in lines[..3].iter().enumerate() {
        let e: serde_json::Value = serde_json::from_str(line).unwrap();
        assert_eq!(e["episode"], i);
        // Mountain car's end goal is fixed at [0.48, 0.04]; the state is [x, v].
        let goal: Vec<f64> = serde_json::from_value(e["end_goal"].clone()).unwrap();
        assert_eq!(goal.len(), 2, "{line}");
        assert!(
            (goal[0] - 0.48).abs() < 1e-6 && (goal[1] - 0.04).abs() < 1e-6,
            "{line}"
        );
        let state: Vec<f64> = serde_json::from_value(e["final_state"].clone()).unwrap();
        let reached = (state[0] - goal[0]).abs() <= 0.01 && (state[1] - goal[1]).abs() <= 0.02;
        assert_eq!(e["success"], reached, "{line}");
        // The achieved end goal at the first and last state (mountain car: the state itself),
        // and whether it moved beyond the end goal's thresholds.
        let start: Vec<f64> = serde_json::from_value(e["start_achieved"].clone()).unwrap();
        let last: Vec<f64> = serde_json::from_value(e["final_achieved"].clone()).unwrap();
        assert_eq!(last, state, "{line}");
        assert!(
            (-0.6..=-0.4).contains(&start[0]) && start[1] == 0.0,
            "{line}"
        );
        let moved = (last[0] - start[0]).abs() > 0.01 || (last[1] - start[1]).abs() > 0.02;
        assert_eq!(e["moved"], moved, "{line}");
        // Level 0's attempts are the episode's primitive actions; the top level reached its
        // goal exactly when the episode succeeded.
        let levels = &e["levels"];
        assert_eq!(levels[0]["attempts"], e["steps"], "{line}");
        assert_eq!(levels[0]["calls"], levels[1]["attempts"], "{line}");
        assert_eq!(levels[1]["calls"], 1, "{line}");
        assert_eq!(levels[1]["reached"], u64::from(reached), "{line}");
    }
    assert!(lines[3].contains("success"), "{}", lines[3]);

    // --subgoals: before each episode's line, one line per subgoal level 1 proposed, from the
    // state its attempt started in; as many as level 1's attempts in that episode.
    let o = hac_output(&["eval", "--run", out_s, "--episodes", "2", "--subgoals"]);
    assert!(o.status.success(), "eval failed: {}", text(&o.stderr));
    let stdout = text(&o.stdout);
    let lines: Vec<serde_json::Value> = stdout
        .lines()
        .take_while(|l| l.starts_with('{'))
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    let mut proposed = 0;
    let mut episodes = 0;
    for line in &lines {
        if line.get("subgoal").is_some() {
            assert_eq!(line["episode"], episodes, "{line}");
            assert_eq!(line["level"], 1, "{line}");
            assert_eq!(line["state"].as_array().unwrap().len(), 2, "{line}");
            let subgoal: Vec<f64> = serde_json::from_value(line["subgoal"].clone()).unwrap();
            // Mountain car's subgoal box: x in [-1.2, 0.6], v in [-0.07, 0.07] (in f32).
            let within = |v: f64, low: f64, high: f64| low - 1e-6 <= v && v <= high + 1e-6;
            assert!(
                subgoal.len() == 2
                    && within(subgoal[0], -1.2, 0.6)
                    && within(subgoal[1], -0.07, 0.07),
                "{line}"
            );
            proposed += 1;
        } else {
            assert_eq!(line["episode"], episodes, "{line}");
            assert_eq!(line["levels"][1]["attempts"], proposed, "{line}");
            episodes += 1;
            proposed = 0;
        }
    }
    assert_eq!(episodes, 2, "{stdout}");
    let o = hac_output(&["eval", "--run", out_s, "--subgoals", "--behaviour"]);
    assert!(!o.status.success(), "--subgoals with --behaviour accepted");
    let _ = std::fs::remove_dir_all(&out);
}

#[test]
fn bad_configuration_is_rejected_before_training_with_the_key_named() {
    let out = scratch("bad");
    let out_s = out.to_str().unwrap();
    let cases: &[(&[&str], &str)] = &[
        (&["--env", "acrobot"], "acrobot"),
        (&["--levels", "0"], "levels"),
        (&["--set", "gamma=1.5"], "gamma"),
        (&["--set", "horizn=5"], "horizn"),
        (&["--set", "hidden_layers=[64, 0]"], "hidden_layers"),
        (&["--set", "action_noise=[0.1, 0.2]"], "action_noise"),
        (
            &["--set", "actor_preactivation_l2=-0.1"],
            "actor_preactivation_l2",
        ),
        (&["--stop-at", "2"], "stop_at"),
        (&["--set", "batch_size"], "KEY=VALUE"),
    ];
    for (args, key) in cases {
        let mut all = vec!["train", "--episodes", "1", "--out", out_s];
        all.extend_from_slice(args);
        let o = hac_output(&all);
        assert!(!o.status.success(), "{args:?} was accepted");
        let err = text(&o.stderr);
        assert!(
            err.contains(key),
            "{args:?}: error does not name `{key}`: {err}"
        );
        assert!(
            !Path::new(&out).join("config.toml").exists(),
            "{args:?}: wrote a run before validating"
        );
    }

    let file = out.with_extension("toml");
    std::fs::write(&file, "env = \"pendulum\"\nepisodez = 3\n").unwrap();
    let o = hac_output(&["train", "--config", file.to_str().unwrap(), "--out", out_s]);
    assert!(!o.status.success());
    assert!(text(&o.stderr).contains("episodez"), "{}", text(&o.stderr));
    let _ = std::fs::remove_file(&file);

    let o = hac_output(&["eval", "--run", out_s]);
    assert!(!o.status.success());
    assert!(
        text(&o.stderr).contains("config.toml"),
        "{}",
        text(&o.stderr)
    );
}

#[test]
fn print_config_shows_the_resolved_configuration() {
    let o = hac_output(&[
        "train",
        "--env",
        "pendulum",
        "--levels",
        "3",
        "--set",
        "gamma=0.9",
        "--print-config",
    ]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    let config = text(&o.stdout);
    assert!(config.contains("horizon = 10"), "{config}");
    assert!(config.contains("gamma = 0.9"), "{config}");
}

/// `hac <args>` with stdin, stdout and stderr piped.
fn spawn_piped(args: &[&str]) -> std::process::Child {
    Command::new(env!("CARGO_BIN_EXE_hac"))
        .args(args)
        .stdin(std::process::Stdio::piped())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("the hac binary runs")
}

fn hac_with_stdin(args: &[&str], stdin: &str) -> Output {
    use std::io::Write;
    let mut child = spawn_piped(args);
    let written = child.stdin.take().unwrap().write_all(stdin.as_bytes());
    let output = child.wait_with_output().unwrap();
    // A command that refuses its input may exit before reading all of it.
    if let Err(e) = written {
        assert!(
            e.kind() == std::io::ErrorKind::BrokenPipe && !output.status.success(),
            "writing stdin: {e}"
        );
    }
    output
}

/// Runs `hac <args>` with `stdin` fed from a thread, reads the first line of its output and then
/// closes the pipe, as `| head -n 1` does; returns that line, the exit status and stderr.
fn first_line_then_close(args: &[&str], stdin: &str) -> (String, ExitStatus, String) {
    use std::io::{BufRead, BufReader, Read, Write};
    let mut child = spawn_piped(args);
    let mut input = child.stdin.take().unwrap();
    let stdin = stdin.to_owned();
    // The child stops reading once its output is gone: the write may fail.
    let feeder = std::thread::spawn(move || drop(input.write_all(stdin.as_bytes())));
    let mut first = String::new();
    BufReader::new(child.stdout.take().unwrap())
        .read_line(&mut first)
        .unwrap();
    let mut stderr = String::new();
    child
        .stderr
        .take()
        .unwrap()
        .read_to_string(&mut stderr)
        .unwrap();
    let status = child.wait().unwrap();
    feeder.join().unwrap();
    (first, status, stderr)
}

#[test]
fn env_list_and_describe() {
    let o = hac_output(&["env", "list"]);
    assert!(o.status.success());
    let list = text(&o.stdout);
    assert!(
        [
            "pendulum",
            "mountain-car",
            "cartpole",
            "four-rooms",
            "four-rooms-25"
        ]
        .iter()
        .all(|name| list.contains(name)),
        "{list}"
    );
    let o = hac_output(&["env", "describe", "pendulum", "--json"]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    let d: serde_json::Value = serde_json::from_str(&text(&o.stdout)).unwrap();
    assert_eq!(d["spec"]["state_dim"], 3);
    assert_eq!(d["defaults"][1]["horizon"], 32);
    let o = hac_output(&["env", "describe", "four-rooms-25", "--json"]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    let d: serde_json::Value = serde_json::from_str(&text(&o.stdout)).unwrap();
    assert_eq!(
        d["spec"]["max_actions"], 144,
        "3 x the 25x25 grid's diameter of 48"
    );
    assert_eq!(d["tabular"]["initial_q"], "pessimistic");
    assert_eq!(d["tabular"]["all_goals"], false);
    assert_eq!(d["tabular"]["all_segments"], true);
    // Another budget: H of every level count follows it (12 / 6 for 144; 22 / 8 for 480).
    assert_eq!(d["defaults"][1]["horizon"], 12);
    let o = hac_output(&[
        "env",
        "describe",
        "four-rooms-25",
        "--json",
        "--max-actions",
        "480",
    ]);
    let d: serde_json::Value = serde_json::from_str(&text(&o.stdout)).unwrap();
    assert_eq!(d["spec"]["max_actions"], 480);
    assert_eq!(d["defaults"][1]["horizon"], 22);
    assert_eq!(d["defaults"][2]["horizon"], 8);
    let o = hac_output(&["env", "describe", "pendulum", "--max-actions", "0"]);
    assert!(
        !o.status.success() && text(&o.stderr).contains("--max-actions"),
        "{}",
        text(&o.stderr)
    );
    let o = hac_output(&["env", "describe", "four-rooms"]);
    assert!(text(&o.stdout).contains("tabular Q-learning"));
    // The UR5's joint angles are compared along the circle, its joint speeds are not.
    let o = hac_output(&["env", "describe", "ur5-reacher", "--json"]);
    let d: serde_json::Value = serde_json::from_str(&text(&o.stdout)).unwrap();
    assert_eq!(
        d["spec"]["end_goal_angles"],
        serde_json::json!([true, true, true])
    );
    assert_eq!(
        d["spec"]["subgoal_angles"],
        serde_json::json!([true, true, true, false, false, false])
    );
    let o = hac_output(&["env", "describe", "ur5-reacher"]);
    assert!(
        text(&o.stdout).contains("end goal [0, 1, 2]  subgoal [0, 1, 2]"),
        "{}",
        text(&o.stdout)
    );
    // The cart-pole's pole angle is its one circular dimension.
    let o = hac_output(&["env", "describe", "cartpole", "--json"]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    let d: serde_json::Value = serde_json::from_str(&text(&o.stdout)).unwrap();
    assert_eq!(d["spec"]["state_dim"], 5);
    assert_eq!(d["spec"]["end_goal_dim"], 3);
    assert_eq!(
        d["spec"]["subgoal_angles"],
        serde_json::json!([false, true, false, false])
    );
    let horizons: Vec<_> = (0..3)
        .map(|k| d["defaults"][k]["horizon"].clone())
        .collect();
    assert_eq!(horizons, [1000, 32, 10]);
    let o = hac_output(&["env", "describe", "cartpole"]);
    assert!(
        text(&o.stdout).contains("end goal [1]  subgoal [1]"),
        "{}",
        text(&o.stdout)
    );
    let o = hac_output(&["env", "describe", "nope"]);
    assert!(!o.status.success() && text(&o.stderr).contains("unknown environment"));
}

#[test]
fn env_rollout_steps_from_a_set_state_and_rejects_bad_lines() {
    // Mountain car at x = 0.44, v = 0.05 with full throttle: the documented update gives
    // v = 0.05 + 0.0015 - 0.0025 cos(1.32) and x = 0.44 + v, past the flag at 0.45.
    let o = hac_with_stdin(
        &[
            "env",
            "rollout",
            "--env",
            "mountain-car",
            "--state",
            "[0.44, 0.05]",
        ],
        "[1]\n[5]\n",
    );
    assert!(o.status.success(), "{}", text(&o.stderr));
    let lines: Vec<serde_json::Value> = text(&o.stdout)
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(lines.len(), 3);
    assert!(text(&o.stdout).starts_with("{\"step\":0,\"state\":"));
    let v = 0.05 + 0.0015 - 0.0025 * (3.0f64 * 0.44).cos();
    let state = lines[1]["state"].as_array().unwrap();
    assert!((state[1].as_f64().unwrap() - v).abs() < 1e-6);
    assert!((state[0].as_f64().unwrap() - (0.44 + v)).abs() < 1e-6);
    assert_eq!(lines[1]["terminated"], true);

    for (input, needle) in [
        ("[1, 2]\n", "1 values, got 2"),
        ("[\"x\"]\n", "JSON array"),
        ("1\n", "JSON array"),
    ] {
        let o = hac_with_stdin(&["env", "rollout", "--env", "mountain-car"], input);
        assert!(!o.status.success(), "{input:?} accepted");
        assert!(
            text(&o.stderr).contains(needle),
            "{input:?}: {}",
            text(&o.stderr)
        );
        assert!(text(&o.stderr).contains("line 1"), "{}", text(&o.stderr));
    }
    // A line that never ends is refused once it passes 1 MiB, not buffered without bound.
    let endless = "0".repeat(3 << 20);
    let o = hac_with_stdin(&["env", "rollout", "--env", "mountain-car"], &endless);
    assert!(
        !o.status.success() && text(&o.stderr).contains("line 1: longer than 1048576 bytes"),
        "{}",
        text(&o.stderr)
    );
    // Thousands of actions, read while the output is read: a reader that stops after the first
    // line ends the rollout quietly.
    let (first, status, stderr) = first_line_then_close(
        &["env", "rollout", "--env", "cartpole"],
        &"[0.5]\n".repeat(200_000),
    );
    assert!(first.starts_with("{\"step\":0,"), "{first}");
    assert!(status.success() && stderr.is_empty(), "{status}: {stderr}");
    // The cart-pole hanging at rest over x = 0.5, pushed right: the cart moves right, the pole
    // lags behind it (q past pi, wrapped to negative: sin q < 0).
    let o = hac_with_stdin(
        &[
            "env",
            "rollout",
            "--env",
            "cartpole",
            "--state",
            "[0.5, 3.141592653589793, 0, 0]",
        ],
        "[1]\n",
    );
    assert!(o.status.success(), "{}", text(&o.stderr));
    let lines: Vec<serde_json::Value> = text(&o.stdout)
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    let state: Vec<f64> = serde_json::from_value(lines[1]["state"].clone()).unwrap();
    assert_eq!(state.len(), 5, "{state:?}");
    assert!(state[0] > 0.5 && state[3] > 0.0, "{state:?}");
    assert!(state[1] < -0.99 && state[2] < 0.0, "{state:?}");
    let o = hac_with_stdin(
        &["env", "rollout", "--env", "cartpole", "--state", "[0, 0]"],
        "",
    );
    assert!(
        !o.status.success() && text(&o.stderr).contains("cartpole physical state needs 4 values"),
        "{}",
        text(&o.stderr)
    );
    let o = hac_with_stdin(
        &[
            "env",
            "rollout",
            "--env",
            "pendulum",
            "--state",
            "[1, 2, 3]",
        ],
        "",
    );
    assert!(
        !o.status.success() && text(&o.stderr).contains("needs 2 values, got 3"),
        "{}",
        text(&o.stderr)
    );
}

#[test]
fn an_experiment_summarises_the_runs_that_finished_when_one_fails() {
    // A file where seed 1's run directory would go: that run fails at its start, the other
    // runs to its end, and the summary covers it and names the failed one.
    let out = scratch("experiment-failed-run");
    std::fs::create_dir_all(&out).unwrap();
    std::fs::write(out.join("mountain-car-1l-seed1"), "not a directory").unwrap();
    let o = hac_output(&[
        "experiment",
        "--env",
        "mountain-car",
        "--levels",
        "1",
        "--seeds",
        "2",
        "--episodes",
        "10",
        "--set",
        "test_episodes=3",
        "--jobs",
        "1",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(!o.status.success(), "a failed run fails the command");
    assert!(
        text(&o.stderr).contains("1 of 2 runs failed")
            && text(&o.stderr).contains("mountain-car-1l-seed1"),
        "{}",
        text(&o.stderr)
    );
    assert!(out.join("mountain-car-1l-seed0/curve.csv").is_file());
    let summary = std::fs::read_to_string(out.join("summary.md")).unwrap();
    assert!(
        summary.contains("| 1 | 1 |"),
        "one seed in the means: {summary}"
    );
    assert!(
        summary.contains("Failed runs") && summary.contains("- mountain-car-1l-seed1: "),
        "{summary}"
    );
    let svg = std::fs::read_to_string(out.join("mountain-car.svg")).unwrap();
    assert_eq!(svg.matches("<polyline").count(), 1, "{svg}");
}

#[test]
fn experiment_runs_the_grid_and_summarises_it() {
    let out = scratch("experiment");
    let out_s = out.to_str().unwrap();
    let o = hac_output(&[
        "experiment",
        "--env",
        "mountain-car",
        "--levels",
        "1,2",
        "--seeds",
        "2",
        "--episodes",
        "10",
        "--set",
        "test_episodes=3",
        "--jobs",
        "2",
        "--out",
        out_s,
    ]);
    assert!(o.status.success(), "experiment failed: {}", text(&o.stderr));
    for run in [
        "mountain-car-1l-seed0",
        "mountain-car-1l-seed1",
        "mountain-car-2l-seed0",
        "mountain-car-2l-seed1",
    ] {
        assert!(out.join(run).join("curve.csv").is_file(), "missing {run}");
    }
    let svg = std::fs::read_to_string(out.join("mountain-car.svg")).unwrap();
    assert_eq!(
        svg.matches("<polyline").count(),
        2,
        "one curve per level count"
    );
    assert_eq!(
        svg.matches("fill-opacity").count(),
        2,
        "one std band per level count"
    );
    let summary = std::fs::read_to_string(out.join("summary.md")).unwrap();
    assert!(
        summary.contains("| 1 | 2 |") && summary.contains("| 2 | 2 |"),
        "{summary}"
    );
    assert_eq!(
        text(&o.stdout)
            .lines()
            .filter(|l| l.starts_with('['))
            .count(),
        4,
        "a line per finished run"
    );

    // Re-running into the same directory is refused before anything runs.
    let o = hac_output(&[
        "experiment",
        "--env",
        "mountain-car",
        "--levels",
        "2",
        "--seeds",
        "1",
        "--out",
        out_s,
    ]);
    assert!(
        !o.status.success() && text(&o.stderr).contains("--overwrite"),
        "{}",
        text(&o.stderr)
    );

    let o = hac_output(&[
        "experiment",
        "--env",
        "mountain-car",
        "--levels",
        "2",
        "--seeds",
        "0",
        "--out",
        out_s,
    ]);
    assert!(
        !o.status.success() && text(&o.stderr).contains("--seeds"),
        "{}",
        text(&o.stderr)
    );
    let _ = std::fs::remove_dir_all(&out);
}

/// `hac train --keep-state` saves a run's whole state, and `hac train --resume` trains it on
/// to a larger budget: the curve and weights of the run trained to that budget at once. Other
/// changes, a run without a state and a budget already trained are refused with the reason.
#[test]
fn a_kept_run_trains_on_with_resume_to_the_longer_run() {
    let (whole, kept) = (scratch("train-on-whole"), scratch("train-on-kept"));
    let train = |out: &Path, episodes: &str, keep: bool| {
        let mut args = vec![
            "train",
            "--env",
            "mountain-car",
            "--seed",
            "4",
            "--episodes",
            episodes,
        ];
        args.extend([
            "--set",
            "exploration_episodes=5",
            "--set",
            "test_episodes=5",
        ]);
        args.extend(["--out", out.to_str().unwrap()]);
        if keep {
            args.push("--keep-state");
        }
        let o = hac_output(&args);
        assert!(o.status.success(), "train failed: {}", text(&o.stderr));
        text(&o.stdout)
    };
    train(&whole, "15", false);
    assert!(!whole.join("checkpoints").exists(), "no state unless asked");
    let stdout = train(&kept, "10", true);
    assert!(stdout.contains("state saved in"), "{stdout}");
    let kept_s = kept.to_str().unwrap();

    let o = hac_output(&["train", "--resume", "--out", kept_s, "--episodes", "15"]);
    assert!(o.status.success(), "resume failed: {}", text(&o.stderr));
    let stdout = text(&o.stdout);
    assert!(
        stdout.contains("from 10 episodes (2 test rounds"),
        "{stdout}"
    );
    assert_eq!(
        stdout.lines().filter(|l| l.starts_with("round ")).count(),
        1
    );
    assert_eq!(curve_without_times(&kept), curve_without_times(&whole));
    for level in ["level0", "level1"] {
        let file = format!("weights/{level}.safetensors");
        let bytes = |run: &Path| std::fs::read(run.join(&file)).unwrap();
        assert!(bytes(&kept) == bytes(&whole), "{file} differs");
    }
    let summary = |run: &Path| -> serde_json::Value {
        serde_json::from_str(&std::fs::read_to_string(run.join("summary.json")).unwrap()).unwrap()
    };
    assert_eq!(summary(&kept)["episodes"], 15);

    for (args, says) in [
        (
            vec!["--episodes", "15"],
            "trained 15 episodes already; ask for more than that",
        ),
        (
            vec!["--episodes", "20", "--seed", "5"],
            "only --episodes and --stop-at may change (drop --seed",
        ),
        (
            vec!["--episodes", "20", "--set", "gamma=0.9"],
            "(drop --set",
        ),
    ] {
        let mut all = vec!["train", "--resume", "--out", kept_s];
        all.extend(args);
        let o = hac_output(&all);
        assert!(!o.status.success());
        assert!(
            text(&o.stderr).contains(says),
            "{all:?}: {}",
            text(&o.stderr)
        );
    }
    let grid_world = scratch("train-on-four-rooms");
    let o = hac_output(&[
        "train",
        "--env",
        "four-rooms",
        "--keep-state",
        "--out",
        grid_world.to_str().unwrap(),
    ]);
    assert!(!o.status.success());
    assert!(
        text(&o.stderr).contains("--keep-state is for neural runs: `four-rooms` is a grid world"),
        "{}",
        text(&o.stderr)
    );
    assert!(
        !grid_world.exists(),
        "refused before the run directory is made"
    );
    let o = hac_output(&[
        "train",
        "--resume",
        "--out",
        whole.to_str().unwrap(),
        "--episodes",
        "20",
    ]);
    assert!(!o.status.success());
    assert!(
        text(&o.stderr)
            .contains("holds no saved state to continue from: train it with --keep-state"),
        "{}",
        text(&o.stderr)
    );
    let _ = std::fs::remove_dir_all(&whole);
    let _ = std::fs::remove_dir_all(&kept);
}

#[test]
fn sigint_stops_training_between_episodes_and_saves_the_run() {
    interrupt_saves_the_run("mountain-car");
}

#[test]
fn sigint_stops_tabular_training_and_saves_the_run() {
    interrupt_saves_the_run("four-rooms");
}

fn interrupt_saves_the_run(env: &str) {
    use std::io::{BufRead, BufReader};
    let out = scratch(&format!("sigint-{env}"));
    let mut child = Command::new(env!("CARGO_BIN_EXE_hac"))
        .args([
            "train",
            "--env",
            env,
            "--episodes",
            "1000000",
            "--set",
            "exploration_episodes=2",
        ])
        .args(["--set", "test_episodes=1", "--out", out.to_str().unwrap()])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("the hac binary runs");
    let mut stdout = BufReader::new(child.stdout.take().unwrap());
    let mut line = String::new();
    // Wait for the first progress line: training is under way.
    while !line.starts_with("round ") {
        line.clear();
        assert!(
            stdout.read_line(&mut line).unwrap() > 0,
            "training ended before a round"
        );
    }
    let kill = Command::new("kill")
        .args(["-INT", &child.id().to_string()])
        .status()
        .unwrap();
    assert!(kill.success());
    let mut rest = String::new();
    std::io::Read::read_to_string(&mut stdout, &mut rest).unwrap();
    let status = child.wait().unwrap();
    assert!(status.success(), "exit {status:?}; stdout: {rest}");
    assert!(rest.contains("interrupted after"), "{rest}");
    assert!(out.join("weights/level0.safetensors").is_file() && out.join("summary.json").is_file());
    let _ = std::fs::remove_dir_all(&out);
}

#[test]
fn four_rooms_trains_with_the_tabular_learner_and_eval_reads_it_back() {
    let out = scratch("four-rooms");
    let out_s = out.to_str().unwrap();
    let o = hac_output(&[
        "train",
        "--env",
        "four-rooms",
        "--levels",
        "3",
        "--episodes",
        "250",
        "--seed",
        "2",
        "--out",
        out_s,
    ]);
    assert!(o.status.success(), "train failed: {}", text(&o.stderr));
    let stdout = text(&o.stdout);
    assert!(stdout.contains("tabular Q-learning"), "{stdout}");
    assert_eq!(
        stdout.lines().filter(|l| l.starts_with("round ")).count(),
        5,
        "a round every 50 episodes:\n{stdout}"
    );
    for file in [
        "config.toml",
        "curve.csv",
        "curve.svg",
        "summary.json",
        "weights/level0.safetensors",
        "weights/level1.safetensors",
        "weights/level2.safetensors",
    ] {
        assert!(out.join(file).is_file(), "missing {file}");
    }
    let config = std::fs::read_to_string(out.join("config.toml")).unwrap();
    assert!(
        config.contains("env = \"four-rooms\"")
            && config.contains("horizon = 4")
            && config.contains("[tabular]"),
        "{config}"
    );
    let csv = std::fs::read_to_string(out.join("curve.csv")).unwrap();
    let last: Vec<&str> = csv.lines().last().unwrap().split(',').collect();
    assert_eq!(&last[..2], ["5", "250"], "{csv}");
    let level_updates: Vec<u64> = [7, 12, 17]
        .iter()
        .map(|&i| last[i].parse().unwrap())
        .collect();
    assert!(level_updates.iter().all(|&u| u > 0), "{csv}");
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    assert_eq!(summary["episodes"], 250);

    let o = hac_output(&["eval", "--run", out_s, "--episodes", "100", "--json"]);
    assert!(o.status.success(), "eval failed: {}", text(&o.stderr));
    let result: serde_json::Value = serde_json::from_str(text(&o.stdout).trim()).unwrap();
    assert_eq!(result["env"], "four-rooms");
    // A random walk reaches another room's cell in about 5% of episodes; 250 episodes of
    // training get well above that.
    let rate = result["success_rate"].as_f64().unwrap();
    assert!(rate > 0.3, "greedy success from the saved tables: {rate}");
    // The same seed gives the same episodes.
    let again = hac_output(&["eval", "--run", out_s, "--episodes", "100", "--json"]);
    assert_eq!(text(&again.stdout), text(&o.stdout));

    let o = hac_output(&[
        "train",
        "--env",
        "four-rooms",
        "--set",
        "tabular.learning_rate=0",
        "--out",
        &format!("{out_s}-bad"),
    ]);
    assert!(
        !o.status.success() && text(&o.stderr).contains("learning_rate"),
        "{}",
        text(&o.stderr)
    );
    let _ = std::fs::remove_dir_all(&out);
}

#[test]
fn experiment_runs_four_rooms_seeds() {
    let out = scratch("four-rooms-experiment");
    let o = hac_output(&[
        "experiment",
        "--env",
        "four-rooms",
        "--levels",
        "1,2",
        "--seeds",
        "3",
        "--episodes",
        "100",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "experiment failed: {}", text(&o.stderr));
    for run in ["four-rooms-1l-seed2", "four-rooms-2l-seed0"] {
        assert!(out.join(run).join("weights/level0.safetensors").is_file());
    }
    let summary = std::fs::read_to_string(out.join("summary.md")).unwrap();
    assert!(
        summary.contains("| 1 | 3 |") && summary.contains("| 2 | 3 |"),
        "{summary}"
    );
    let _ = std::fs::remove_dir_all(&out);
}

#[test]
fn a_run_budget_caps_training_and_evaluation_episodes() {
    // Four-rooms 10 x 10 with 5 actions per episode instead of 54: a training episode never
    // takes more, evaluation of the saved run neither, and the default H follows (3^2 >= 5).
    let out = scratch("four-rooms-budget");
    let out_s = out.to_str().unwrap();
    let o = hac_output(&[
        "train",
        "--env",
        "four-rooms",
        "--levels",
        "2",
        "--episodes",
        "100",
        "--max-actions",
        "5",
        "--out",
        out_s,
    ]);
    assert!(o.status.success(), "train failed: {}", text(&o.stderr));
    let config = std::fs::read_to_string(out.join("config.toml")).unwrap();
    assert!(
        config.contains("max_actions = 5") && config.contains("horizon = 3"),
        "{config}"
    );
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    let steps = summary["env_steps"].as_u64().unwrap();
    assert!(steps <= 100 * 5, "{steps} training steps in 100 episodes");

    let o = hac_output(&["eval", "--run", out_s, "--episodes", "30", "--per-episode"]);
    assert!(o.status.success(), "eval failed: {}", text(&o.stderr));
    let steps: Vec<u64> = text(&o.stdout)
        .lines()
        .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok())
        .filter_map(|v| v["steps"].as_u64())
        .collect();
    assert_eq!(steps.len(), 30, "{}", text(&o.stdout));
    // Start and goal lie in different rooms, more than 5 moves apart for most draws.
    assert!(
        steps.iter().all(|&s| s <= 5) && steps.contains(&5),
        "{steps:?}"
    );

    let o = hac_output(&[
        "experiment",
        "--env",
        "four-rooms",
        "--levels",
        "1",
        "--seeds",
        "1",
        "--episodes",
        "50",
        "--max-actions",
        "7",
        "--out",
        &format!("{out_s}-experiment"),
    ]);
    assert!(o.status.success(), "experiment failed: {}", text(&o.stderr));
    let experiment = PathBuf::from(format!("{out_s}-experiment"));
    let config =
        std::fs::read_to_string(experiment.join("four-rooms-1l-seed0/config.toml")).unwrap();
    assert!(
        config.contains("max_actions = 7") && config.contains("horizon = 7"),
        "{config}"
    );

    let o = hac_output(&[
        "train",
        "--env",
        "four-rooms",
        "--max-actions",
        "0",
        "--print-config",
    ]);
    assert!(
        !o.status.success() && text(&o.stderr).contains("max_actions"),
        "{}",
        text(&o.stderr)
    );
    let _ = std::fs::remove_dir_all(&out);
    let _ = std::fs::remove_dir_all(&experiment);
}

/// Checks the GIF signature and counts the frames with a decoder.
fn gif_frames(path: &Path) -> usize {
    let bytes = std::fs::read(path).unwrap();
    assert_eq!(&bytes[..6], b"GIF89a", "{}", path.display());
    let mut options = gif::DecodeOptions::new();
    options.set_color_output(gif::ColorOutput::Indexed);
    let mut decoder = options.read_info(bytes.as_slice()).unwrap();
    let mut frames = 0;
    while decoder.read_next_frame().unwrap().is_some() {
        frames += 1;
    }
    frames
}

#[test]
fn render_draws_a_pendulum_episode_as_a_gif() {
    let out = scratch("render-pendulum");
    let run = out.join("run");
    let o = hac_output(&[
        "train",
        "--env",
        "pendulum",
        "--levels",
        "2",
        "--episodes",
        "1",
        "--set",
        "exploration_episodes=1",
        "--set",
        "test_episodes=1",
        "--out",
        run.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "train failed: {}", text(&o.stderr));
    let gif = out.join("episode.gif");
    let o = hac_output(&[
        "render",
        "--run",
        run.to_str().unwrap(),
        "--out",
        gif.to_str().unwrap(),
        "--episode-steps",
        "30",
    ]);
    assert!(o.status.success(), "render failed: {}", text(&o.stderr));
    // The untrained agent uses the whole 30-action budget: a frame per action plus the last.
    assert_eq!(gif_frames(&gif), 31);
    assert!(text(&o.stdout).contains("31 frames"), "{}", text(&o.stdout));

    // Errors name the problem: no run, an unwritable output, an output file that is no GIF.
    let o = hac_output(&[
        "render",
        "--run",
        out.join("nope").to_str().unwrap(),
        "--out",
        "x.gif",
    ]);
    assert!(
        !o.status.success() && text(&o.stderr).contains("is this a run directory"),
        "{}",
        text(&o.stderr)
    );
    let blocked = out.join("episode.gif").join("x.gif");
    let o = hac_output(&[
        "render",
        "--run",
        run.to_str().unwrap(),
        "--out",
        blocked.to_str().unwrap(),
    ]);
    assert!(
        !o.status.success() && text(&o.stderr).contains(blocked.to_str().unwrap()),
        "{}",
        text(&o.stderr)
    );
    let o = hac_output(&[
        "render",
        "--run",
        run.to_str().unwrap(),
        "--out",
        out.join("run/summary.json").to_str().unwrap(),
    ]);
    assert!(
        !o.status.success() && text(&o.stderr).contains("is a file"),
        "{}",
        text(&o.stderr)
    );
    let _ = std::fs::remove_dir_all(&out);
}

#[test]
fn render_draws_a_cartpole_episode() {
    let out = scratch("render-cartpole");
    let run = out.join("run");
    let o = hac_output(&[
        "train",
        "--env",
        "cartpole",
        "--levels",
        "2",
        "--episodes",
        "1",
        "--set",
        "exploration_episodes=1",
        "--set",
        "test_episodes=1",
        "--max-actions",
        "64",
        "--out",
        run.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "train failed: {}", text(&o.stderr));
    let gif = out.join("episode.gif");
    let o = hac_output(&[
        "render",
        "--run",
        run.to_str().unwrap(),
        "--out",
        gif.to_str().unwrap(),
        "--episode-steps",
        "10",
    ]);
    assert!(o.status.success(), "render failed: {}", text(&o.stderr));
    assert_eq!(gif_frames(&gif), 11);
    let _ = std::fs::remove_dir_all(&out);
}

#[test]
fn render_draws_four_rooms_as_a_gif_or_png_frames() {
    let out = scratch("render-four-rooms");
    let run = out.join("run");
    let o = hac_output(&[
        "train",
        "--env",
        "four-rooms",
        "--levels",
        "3",
        "--episodes",
        "100",
        "--out",
        run.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "train failed: {}", text(&o.stderr));
    let run_s = run.to_str().unwrap();
    let gif = out.join("episode.gif");
    let o = hac_output(&[
        "render",
        "--run",
        run_s,
        "--out",
        gif.to_str().unwrap(),
        "--seed",
        "4",
    ]);
    assert!(o.status.success(), "render failed: {}", text(&o.stderr));
    let frames = gif_frames(&gif);
    assert!(frames > 1, "{frames} frames");

    let pngs = out.join("frames");
    let o = hac_output(&[
        "render",
        "--run",
        run_s,
        "--out",
        pngs.to_str().unwrap(),
        "--seed",
        "4",
    ]);
    assert!(o.status.success(), "render failed: {}", text(&o.stderr));
    let mut names: Vec<String> = std::fs::read_dir(&pngs)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    assert_eq!(names.len(), frames, "the same episode either way");
    assert_eq!(names[0], "frame-00000.png");
    let first = std::fs::read(pngs.join(&names[0])).unwrap();
    assert_eq!(&first[..8], b"\x89PNG\r\n\x1a\n");

    // A directory already holding files is not written into.
    let o = hac_output(&["render", "--run", run_s, "--out", pngs.to_str().unwrap()]);
    assert!(
        !o.status.success() && text(&o.stderr).contains("not empty"),
        "{}",
        text(&o.stderr)
    );
    let _ = std::fs::remove_dir_all(&out);
}

#[test]
fn health_reports_an_unreachable_server_and_a_bad_url() {
    // Port 1 on loopback: nothing listens there.
    let o = hac_output(&["health", "http://127.0.0.1:1", "--timeout", "2"]);
    assert_eq!(o.status.code(), Some(1), "{}", text(&o.stderr));
    assert!(
        text(&o.stderr).contains("connecting to http://127.0.0.1:1"),
        "{}",
        text(&o.stderr)
    );
    let o = hac_output(&["health", "not a url"]);
    assert_eq!(o.status.code(), Some(1));
    assert!(
        text(&o.stderr).contains("invalid server URL `not a url`"),
        "{}",
        text(&o.stderr)
    );
}

#[test]
fn bench_connections_holds_actors_against_a_learner_process() {
    let o = hac_output(&[
        "bench",
        "connections",
        "--actors",
        "8",
        "--seconds",
        "3",
        "--sample-every",
        "1",
        "--json",
    ]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    let report: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(report["actors_connected"], 8, "{report}");
    assert!(report["batches_acked"].as_u64().unwrap() > 0, "{report}");
    let samples = report["samples"].as_array().unwrap();
    assert!(samples.len() >= 3, "{report}");
    // The learner's own memory: a real process, larger than nothing, at least its last sample.
    let peak = report["peak_rss_kib"].as_u64().unwrap();
    assert!(peak >= samples.last().unwrap()["rss_kib"].as_u64().unwrap() && peak > 1024);
}

#[test]
fn bench_update_reports_each_thread_count_against_the_sgemm_peak() {
    let o = hac_output(&[
        "bench",
        "update",
        "--batch",
        "256",
        "--threads",
        "1,2",
        "--seconds",
        "0.3",
        "--json",
    ]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    let report: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    // Pendulum's level 0 of 2 with its default hidden layers (3 x 64): 85,120 multiply-adds per
    // sample (counted by hand in hac-nn's tests), 2 FLOP each.
    assert_eq!(
        report["hidden"],
        serde_json::json!([64, 64, 64]),
        "{report}"
    );
    let dims = [&report["state"], &report["goal"], &report["action"]];
    assert_eq!(dims, [3, 2, 1], "{report}");
    assert_eq!(report["flops_per_update"], 2 * 85_120 * 256, "{report}");
    assert_eq!(report["chunks"], 1, "{report}");
    let rows = report["rows"].as_array().unwrap();
    assert_eq!(rows.len(), 2, "{report}");
    assert!(
        report["sgemm_peak_gflops"].as_f64().unwrap() > 0.1,
        "{report}"
    );
    assert!(
        ["avx512", "avx2", "baseline"].contains(&report["simd"].as_str().unwrap()),
        "{report}"
    );
    for (row, threads) in rows.iter().zip([1, 2]) {
        assert_eq!(row["threads"], threads, "{report}");
        assert!(row["updates"].as_u64().unwrap() > 0, "{report}");
        let ms = row["ms_per_update"].as_f64().unwrap();
        let gflops = row["gflops"].as_f64().unwrap();
        let flops = report["flops_per_update"].as_f64().unwrap();
        assert!(
            (gflops - flops / ms / 1e6).abs() < 1e-6 * gflops,
            "{report}"
        );
        // The serial part, the wait and the optimiser steps are parts of the update. With one
        // chunk (batch 256) a second thread only keeps its copy of the networks in step; one
        // thread waits for nobody.
        let serial = row["serial_us"].as_f64().unwrap();
        assert!(serial > 0.0 && serial < ms * 1e3, "{report}");
        let waiting = row["waiting_us"].as_f64().unwrap();
        assert!((0.0..ms * 1e3).contains(&waiting), "{report}");
        let steps = row["steps_us"].as_f64().unwrap();
        assert!(steps > 0.0 && steps < ms * 1e3, "{report}");
    }
    assert_eq!(rows[0]["waiting_us"], 0.0, "{report}");
    assert_eq!(rows[0]["speedup"], 1.0, "{report}");
    // Two sgemm copies at once against one alone: a measured rate, whatever the machine's load.
    assert_eq!(rows[0]["sgemm_scaling"], 1.0, "{report}");
    let scaling = rows[1]["sgemm_scaling"].as_f64().unwrap();
    assert!(scaling.is_finite() && scaling > 0.1, "{report}");
    // The cache line's round trip: none on one thread; on two, measured before and after the
    // row where there are two cores (a spinning pair on one core would take a time slice).
    assert!(rows[0]["round_trip_ns"].is_null(), "{report}");
    if report["cores"].as_u64().unwrap() > 1 {
        let trips = rows[1]["round_trip_ns"].as_array().unwrap();
        assert_eq!(trips.len(), 2, "{report}");
        for trip in trips {
            let ns = trip.as_f64().unwrap();
            assert!(ns > 1.0 && ns < 1e6, "{report}");
        }
    }

    let o = hac_output(&["bench", "update", "--level", "2"]);
    assert!(!o.status.success());
    assert!(
        text(&o.stderr).contains("--level 2 is not a level of a 2-level hierarchy"),
        "{}",
        text(&o.stderr)
    );
}

#[test]
fn an_address_may_be_host_port_and_an_error_says_each_cause_once() {
    // Port 1 on loopback: nothing listens there.
    let o = hac_output(&["health", "127.0.0.1:1", "--timeout", "2"]);
    assert_eq!(o.status.code(), Some(1), "{}", text(&o.stderr));
    let stderr = text(&o.stderr);
    assert!(stderr.contains("connecting to 127.0.0.1:1: "), "{stderr}");
    let causes: Vec<&str> = stderr.trim().split(": ").collect();
    assert!(
        causes.windows(2).all(|pair| pair[0] != pair[1]),
        "a cause repeated: {stderr}"
    );
}

#[test]
fn status_refuses_a_learner_given_as_an_actor() {
    let dir = scratch("kinds");
    std::fs::create_dir_all(&dir).unwrap();
    let out = dir.join("out");
    let (mut learner, addr) = common::learner(
        &[
            "learner",
            "--env",
            "mountain-car",
            "--levels",
            "2",
            "--episodes",
            "100000",
            "--listen",
            "127.0.0.1:0",
            "--out",
            out.to_str().unwrap(),
        ],
        &dir,
        "learner",
    );
    // Both forms of the address, in every command that takes one.
    for url in [addr.clone(), format!("http://{addr}")] {
        let o = hac_output(&["health", &url]);
        assert!(o.status.success(), "{url}: {}", text(&o.stderr));
        assert!(text(&o.stdout).contains("SERVING"), "{}", text(&o.stdout));
        let o = hac_output(&["status", "--learner", &url, "--json"]);
        assert!(o.status.success(), "{url}: {}", text(&o.stderr));
    }
    let o = hac_output(&["status", "--actor", &addr]);
    assert_eq!(o.status.code(), Some(1), "{}", text(&o.stdout));
    assert!(
        text(&o.stderr).contains(&format!("{addr} answers as a learner, not an actor")),
        "{}",
        text(&o.stderr)
    );
    assert!(o.stdout.is_empty(), "no table: {}", text(&o.stdout));
    let _ = learner.kill();
    let _ = learner.wait();
    let _ = std::fs::remove_dir_all(&dir);
}
