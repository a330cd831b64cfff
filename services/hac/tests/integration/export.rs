//! `hac export`: the exported policy file is self-contained. Loaded with nothing but the
//! safetensors format and the layout in docs/CHECKPOINTS.md (a plain forward pass written here),
//! it gives the trained run's actions.

use crate::common;
use common::hac_output;
use std::collections::HashMap;
use std::path::{Path, PathBuf};

use hac_agent::{Agent, RunConfig};
use hac_core::Rng;
use safetensors::SafeTensors;

fn scratch(name: &str) -> PathBuf {
    common::fresh_path("hac-export-test", name)
}

/// One level of the exported policy, read by the documented layout alone.
struct Level {
    /// `(weight [out][in], bias [out])` per layer.
    layers: Vec<(Vec<Vec<f32>>, Vec<f32>)>,
    scale: Vec<f32>,
    offset: Vec<f32>,
}

fn floats(file: &SafeTensors<'_>, name: &str) -> (Vec<usize>, Vec<f32>) {
    let t = file
        .tensor(name)
        .unwrap_or_else(|_| panic!("tensor {name}"));
    assert_eq!(t.dtype(), safetensors::Dtype::F32, "{name}");
    let values = t
        .data()
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect();
    (t.shape().to_vec(), values)
}

fn read_level(file: &SafeTensors<'_>, level: usize) -> Level {
    let mut layers = Vec::new();
    while file
        .tensor(&format!("level{level}.layers.{}.weight", layers.len()))
        .is_ok()
    {
        let l = layers.len();
        let (shape, w) = floats(file, &format!("level{level}.layers.{l}.weight"));
        let (_, b) = floats(file, &format!("level{level}.layers.{l}.bias"));
        let rows = w.chunks_exact(shape[1]).map(<[f32]>::to_vec).collect();
        layers.push((rows, b));
    }
    Level {
        layers,
        scale: floats(file, &format!("level{level}.output_scale")).1,
        offset: floats(file, &format!("level{level}.output_offset")).1,
    }
}

/// `tanh(W_L relu(... relu(W_1 x + b_1) ...) + b_L) * scale + offset`, `x = [state, goal]`.
fn act(level: &Level, state: &[f32], goal: &[f32]) -> Vec<f32> {
    let mut h: Vec<f32> = state.iter().chain(goal).copied().collect();
    for (i, (w, b)) in level.layers.iter().enumerate() {
        let z: Vec<f32> = w
            .iter()
            .zip(b)
            .map(|(row, bias)| row.iter().zip(&h).map(|(a, x)| a * x).sum::<f32>() + bias)
            .collect();
        let last = i + 1 == level.layers.len();
        h = if last {
            z
        } else {
            z.into_iter().map(|v| v.max(0.0)).collect()
        };
    }
    h.iter()
        .zip(&level.scale)
        .zip(&level.offset)
        .map(|((y, s), c)| y.tanh() * s + c)
        .collect()
}

fn train(out: &Path, algo: &str) {
    let mut args = vec![
        "train",
        "--algo",
        algo,
        "--env",
        "pendulum",
        "--levels",
        "2",
        "--episodes",
        "10",
        "--set",
        "test_episodes=2",
        "--set",
        "exploration_episodes=10",
        "--out",
        out.to_str().unwrap(),
    ];
    if algo == "hiro" {
        // A few updates are enough to export.
        args.extend(["--set", "hiro.updates_per_step=0.01"]);
    }
    let o = hac_output(&args);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
}

#[test]
fn an_exported_policy_reproduces_the_runs_actions_without_this_project() {
    exported_policy_reproduces("hac");
}

/// HIRO's high level outputs relative goals: its bounds are the relative-goal box, and the file
/// says it is HIRO's, with its c.
#[test]
fn an_exported_hiro_policy_reproduces_the_runs_actions_and_names_its_goals() {
    exported_policy_reproduces("hiro");
}

fn exported_policy_reproduces(algo: &str) {
    let dir = scratch(&format!("pendulum-{algo}"));
    let run = dir.join("run");
    train(&run, algo);
    let file = dir.join("policy.safetensors");
    let o = hac_output(&[
        "export",
        "--run",
        run.to_str().unwrap(),
        "--out",
        file.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(String::from_utf8_lossy(&o.stdout).contains("from weights/"));

    let bytes = std::fs::read(&file).unwrap();
    let st = SafeTensors::deserialize(&bytes).unwrap();
    let (_, header) = SafeTensors::read_metadata(&bytes).unwrap();
    let meta: HashMap<String, String> = header.metadata().clone().unwrap();
    assert_eq!(meta["format"], "hac/policy");
    assert_eq!(meta["env"], "pendulum");
    assert_eq!(meta["algo"], algo);
    let levels: usize = meta["levels"].parse().unwrap();
    assert_eq!(levels, 2);
    let spec = hac_envs::make("pendulum").unwrap().spec().clone();
    if algo == "hiro" {
        assert_eq!(meta["hiro.c"], "10");
        assert!(!meta.contains_key("horizon"));
        let r = hac_core::hiro::goal_radius(&spec);
        let high: Vec<f32> = meta["level1.action_high"]
            .split(',')
            .map(|v| v.parse().unwrap())
            .collect();
        assert_eq!(high, r);
    } else {
        assert!(meta.contains_key("horizon") && !meta.contains_key("hiro.c"));
    }

    // The run's own networks, through the project's code.
    let config = RunConfig::load_run(&run).unwrap();
    let env = hac_envs::make("pendulum").unwrap();
    let agent = Agent::load(&run.join("weights"), env.spec(), &config).unwrap();
    let mut rng = Rng::seed_from(11);
    for level in 0..levels {
        let exported = read_level(&st, level);
        let state_dim: usize = meta[&format!("level{level}.state_dim")].parse().unwrap();
        let goal_dim: usize = meta[&format!("level{level}.goal_dim")].parse().unwrap();
        let action_dim: usize = meta[&format!("level{level}.action_dim")].parse().unwrap();
        let low: Vec<f32> = meta[&format!("level{level}.action_low")]
            .split(',')
            .map(|v| v.parse().unwrap())
            .collect();
        let high: Vec<f32> = meta[&format!("level{level}.action_high")]
            .split(',')
            .map(|v| v.parse().unwrap())
            .collect();
        let mut actor = agent.levels()[level].actor().clone();
        for _ in 0..5 {
            let state: Vec<f32> = (0..state_dim).map(|_| rng.uniform(-2.0, 2.0)).collect();
            let goal: Vec<f32> = (0..goal_dim).map(|_| rng.uniform(-2.0, 2.0)).collect();
            let mut expected = vec![0.0; action_dim];
            actor.act(&state, &goal, &mut expected);
            let got = act(&exported, &state, &goal);
            assert_eq!(got.len(), action_dim);
            for d in 0..action_dim {
                assert!(
                    (got[d] - expected[d]).abs() <= 1e-4 * (1.0 + expected[d].abs()),
                    "level {level} dim {d}: {got:?} vs {expected:?}"
                );
                assert!(low[d] - 1e-5 <= got[d] && got[d] <= high[d] + 1e-5);
            }
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn export_refuses_grid_worlds_and_names_the_q_tables() {
    let dir = scratch("four-rooms");
    let run = dir.join("run");
    let o = hac_output(&[
        "train",
        "--env",
        "four-rooms",
        "--episodes",
        "5",
        "--set",
        "test_episodes=2",
        "--out",
        run.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let o = hac_output(&[
        "export",
        "--run",
        run.to_str().unwrap(),
        "--out",
        dir.join("p.safetensors").to_str().unwrap(),
    ]);
    assert!(!o.status.success());
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(
        stderr.contains("tabular") && stderr.contains("Q tables"),
        "{stderr}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn the_best_round_is_kept_evaluated_and_exported() {
    let dir = scratch("best");
    let run = dir.join("run");
    let run_s = run.to_str().unwrap();
    let o = hac_output(&[
        "train",
        "--env",
        "pendulum",
        "--levels",
        "2",
        "--episodes",
        "30",
        "--set",
        "test_episodes=5",
        "--set",
        "exploration_episodes=10",
        "--out",
        run_s,
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));

    // weights/best/ names the first round with the highest success on the curve.
    let csv = std::fs::read_to_string(run.join("curve.csv")).unwrap();
    let rates: Vec<f32> = csv
        .lines()
        .skip(1)
        .map(|row| row.split(',').nth(3).unwrap().parse().unwrap())
        .collect();
    assert_eq!(rates.len(), 3, "{csv}");
    let top = rates.iter().copied().fold(f32::MIN, f32::max);
    let first_top = rates.iter().position(|&r| r == top).unwrap() + 1;
    let record: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run.join("weights/best/best.json")).unwrap())
            .unwrap();
    assert_eq!(record["round"], first_top, "{record} vs {csv}");
    assert_eq!(record["levels"], 2);
    assert!((record["success_rate"].as_f64().unwrap() as f32 - top).abs() < 1e-6);

    let o = hac_output(&[
        "eval",
        "--run",
        run_s,
        "--best",
        "--episodes",
        "4",
        "--json",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let result: serde_json::Value =
        serde_json::from_str(String::from_utf8_lossy(&o.stdout).trim()).unwrap();
    assert_eq!(result["weights"], "weights/best/");
    assert_eq!(result["episodes"], 4);

    // The exported file holds the best round's actors: the same actions.
    let file = dir.join("best.safetensors");
    let o = hac_output(&[
        "export",
        "--run",
        run_s,
        "--best",
        "--out",
        file.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let bytes = std::fs::read(&file).unwrap();
    let st = SafeTensors::deserialize(&bytes).unwrap();
    let (_, header) = SafeTensors::read_metadata(&bytes).unwrap();
    let meta: HashMap<String, String> = header.metadata().clone().unwrap();
    assert!(meta["source"].starts_with("weights/best/"), "{meta:?}");
    assert_eq!(
        meta["weights_version"],
        record["weights_version"].to_string()
    );
    assert!(!meta.contains_key("level0.updates"), "{meta:?}");
    for level in 0..2 {
        let best =
            std::fs::read(run.join(format!("weights/best/level{level}.safetensors"))).unwrap();
        let mut best = hac_nn::ActorNet::from_safetensors(&best).unwrap();
        let exported = read_level(&st, level);
        let dims = best.dims();
        let mut rng = Rng::seed_from(5);
        for _ in 0..5 {
            let state: Vec<f32> = (0..dims.state).map(|_| rng.uniform(-2.0, 2.0)).collect();
            let goal: Vec<f32> = (0..dims.goal).map(|_| rng.uniform(-2.0, 2.0)).collect();
            let mut expected = vec![0.0; dims.action];
            best.act(&state, &goal, &mut expected);
            let got = act(&exported, &state, &goal);
            for (g, e) in got.iter().zip(&expected) {
                assert!(
                    (g - e).abs() <= 1e-4 * (1.0 + e.abs()),
                    "level {level}: {got:?} vs {expected:?}"
                );
            }
        }
    }

    // Without weights/best/ both say what is missing.
    std::fs::remove_dir_all(run.join("weights/best")).unwrap();
    for args in [
        vec!["eval", "--run", run_s, "--best"],
        vec![
            "export",
            "--run",
            run_s,
            "--best",
            "--out",
            file.to_str().unwrap(),
        ],
    ] {
        let o = hac_output(&args);
        assert!(!o.status.success(), "{args:?}");
        let stderr = String::from_utf8_lossy(&o.stderr);
        assert!(stderr.contains("no best weights"), "{args:?}: {stderr}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}
