//! Mean greedy success curves of 1-, 2- and 3-level tabular HAC on a four-rooms grid.
//!
//! `cargo run --release -p hac-tabular --example levels -- [size] [trials] [episodes]
//! [eval_every] [test_episodes] [learning_rate] [h1,h2,h3]` (defaults: 10 10 500 50 50 1.0, and
//! the environment's horizons).

use hac_core::Env;
use hac_tabular::{CurveSpec, FourRooms, TabularConfig, success_curve_with};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let arg = |i: usize, default: &str| args.get(i).cloned().unwrap_or(default.to_string());
    let size: usize = arg(0, "10").parse()?;
    let trials: usize = arg(1, "10").parse()?;
    let episodes: usize = arg(2, "500").parse()?;
    let eval_every: usize = arg(3, "50").parse()?;
    let test_episodes: usize = arg(4, "50").parse()?;
    let tabular = TabularConfig {
        learning_rate: arg(5, "1.0").parse()?,
        ..TabularConfig::default()
    };
    let horizons: Vec<Option<usize>> = match args.get(6) {
        Some(list) => list.split(',').map(|h| h.parse().ok()).collect(),
        None => vec![None; 3],
    };
    let env = FourRooms::new(size)?;
    for levels in 1..=3 {
        let mut config = env.default_config(levels);
        if let Some(Some(h)) = horizons.get(levels - 1) {
            config.horizon = *h;
        }
        let spec = CurveSpec {
            size,
            levels,
            trials,
            episodes,
            eval_every,
            test_episodes,
            seed: 0,
        };
        let started = std::time::Instant::now();
        let curve = success_curve_with(&spec, &config, &tabular)?;
        let points: Vec<String> = curve
            .episodes
            .iter()
            .zip(&curve.mean_success)
            .map(|(e, s)| format!("{e}:{s:.2}"))
            .collect();
        println!(
            "{size}x{size} levels={levels} H={} ({:.1}s) {}",
            config.horizon,
            started.elapsed().as_secs_f32(),
            points.join(" ")
        );
    }
    Ok(())
}
