//! `hac experiment`: a grid of environments x algorithms x level counts x seeds, run `--jobs` at
//! a time, summarised the way the paper shows results: one plot per environment with the mean
//! test success and a +- 1 standard deviation band per algorithm and level count (Figure 3:
//! level counts; Figure 4: HAC against HIRO), and a markdown table.
//!
//! Output directory layout:
//! - `<env>-<k>l-seed<s>/` (HAC) and `<env>-hiro-<k>l-seed<s>/` (HIRO): one run directory per
//!   run, exactly as `hac train` writes it;
//! - `<env>.svg`: the learning curves, mean +- 1 std over seeds, one curve per algorithm and
//!   level count;
//! - `summary.md`: per environment, algorithm and level count, episodes to 50% and 90% (the
//!   median seed's, a seed that never got there counting as the slowest, so "never" unless at
//!   least half did; and how many did), final success (mean +- std), wall time.
//!
//! With `--resume`, a run whose directory already holds a finished run of the configuration the
//! grid resolves for it is read back instead of trained again ([`inspect`] says what counts as
//! finished), and the summary covers it like the runs trained now; a run that did not finish is
//! trained again from the start. A finished run of another configuration is refused before any
//! run starts. A run that saved its state (`--keep-state`) goes on from it instead of starting
//! again: an interrupted one to its budget, a finished one to a larger episode budget (the only
//! key, with `stop_at`, that may then differ).

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use hac_agent::RoundReport;
use hac_core::hiro::Algo;
use hac_learner::{LearnerOptions, MAX_LEARNER_THREADS, available_threads};
use hac_serve::SavedRun;

use crate::config::{self, RunConfig};
use crate::plot;
use crate::run_dir::{self, RunDir, Summary};
use crate::state::{self, Embedded};
use crate::tabular_cmd;

/// What to run.
#[derive(Debug)]
pub struct Grid {
    pub envs: Vec<String>,
    pub algos: Vec<Algo>,
    pub levels: Vec<usize>,
    pub seeds: u64,
    pub episodes: Option<u64>,
    pub max_actions: Option<usize>,
    pub jobs: usize,
    /// Each run's learner threads; `None`: the cores available divided among the jobs.
    pub learner_threads: Option<usize>,
    pub out: PathBuf,
    pub config: Option<PathBuf>,
    pub set: Vec<String>,
    pub overwrite: bool,
    /// Read back the finished runs already in `out` (of the same configuration) instead of
    /// training them again; train the others, unfinished ones again from the start.
    pub resume: bool,
    /// Each neural run saves its whole state when it stops.
    pub keep_state: bool,
    /// Set by SIGINT/SIGTERM: running runs stop and save, queued runs do not start.
    pub interrupt: Arc<AtomicBool>,
}

/// One finished run.
#[derive(Debug)]
struct Finished {
    config: RunConfig,
    curve: Vec<RoundReport>,
    summary: Summary,
}

/// What `--resume` found in a run's directory.
#[derive(Debug)]
enum Found {
    /// No run: train it.
    Nothing,
    /// A finished run of the configuration the grid resolves: reuse it.
    Finished(Box<Finished>),
    /// A run that did not finish, and why it counts as unfinished: train it again.
    Unfinished(String),
    /// A run with a saved state to go on from (made ready for the grid's budget).
    Continue(Box<SavedRun>),
}

/// Runs the grid (see the module documentation) and writes its summary.
pub fn run(grid: Grid) -> Result<()> {
    if grid.resume && grid.overwrite {
        bail!(
            "`--resume` and `--overwrite` contradict each other: --resume keeps the finished runs \
             in --out, --overwrite trains every run again; pass one of them"
        );
    }
    if grid.levels.is_empty() {
        bail!("invalid value for `--levels`: give at least one level count, e.g. 1,2,3");
    }
    if grid.envs.is_empty() {
        bail!("invalid value for `--env`: give at least one environment, e.g. pendulum");
    }
    if grid.algos.is_empty() {
        bail!("invalid value for `--algo`: give at least one algorithm, e.g. hac,hiro");
    }
    if grid.algos.contains(&Algo::Hiro) && grid.levels != [2] {
        bail!(
            "invalid value for `--levels`: HIRO has exactly 2 levels; with `--algo` naming hiro, \
             pass `--levels 2`"
        );
    }
    if grid.seeds == 0 {
        bail!("invalid value for `--seeds`: must be at least 1");
    }
    if grid.jobs == 0 {
        bail!("invalid value for `--jobs`: must be at least 1");
    }
    let learner_threads = match grid.learner_threads {
        Some(n) if n == 0 || n > MAX_LEARNER_THREADS => bail!(
            "invalid value for `--learner-threads`: must be 1 to {MAX_LEARNER_THREADS}, got {n}"
        ),
        Some(n) => n,
        None => (available_threads() / grid.jobs).max(1),
    };
    // Resolve (and so validate) every run's configuration before starting any.
    let mut runs = Vec::new();
    for env in &grid.envs {
        for &algo in &grid.algos {
            for &levels in &grid.levels {
                for seed in 0..grid.seeds {
                    let config = config::resolve(
                        grid.config.as_deref(),
                        config::Overrides {
                            algo: Some(algo),
                            env: Some(env.clone()),
                            levels: Some(levels),
                            seed: Some(seed),
                            episodes: grid.episodes,
                            max_actions: grid.max_actions,
                            set: grid.set.clone(),
                            // `--set hiro.KEY` in a grid of HAC and HIRO is for the HIRO runs.
                            hiro_settings_for_hiro_only: grid.algos.len() > 1,
                            ..Default::default()
                        },
                    )?;
                    runs.push(config);
                }
            }
        }
    }
    // With --resume, look at every run's directory before starting any, so that a finished run
    // of another configuration stops the grid before anything is overwritten.
    let found: Vec<Found> = if grid.resume {
        runs.iter()
            .map(|c| inspect(&run_path(&grid.out, c), c))
            .collect::<Result<_>>()?
    } else {
        if !grid.overwrite {
            let taken = runs
                .iter()
                .map(|c| run_path(&grid.out, c))
                .find(|p| p.join("config.toml").exists());
            if let Some(taken) = taken {
                bail!(
                    "{} already holds a run; choose another --out, pass --resume to finish the \
                     grid it belongs to, or --overwrite to train every run again",
                    taken.display()
                );
            }
        }
        runs.iter().map(|_| Found::Nothing).collect()
    };
    std::fs::create_dir_all(&grid.out)
        .with_context(|| format!("creating {}", grid.out.display()))?;
    // The finished runs read back, each with its index in `runs`.
    let mut reused: Vec<(usize, Finished)> = Vec::new();
    // The runs to train, each with why it is trained again if it was there unfinished, or the
    // saved state it goes on from.
    let mut to_train: Vec<(usize, Option<String>, Option<SavedRun>)> = Vec::new();
    for (i, found) in found.into_iter().enumerate() {
        match found {
            Found::Nothing => to_train.push((i, None, None)),
            Found::Finished(f) => reused.push((i, *f)),
            Found::Unfinished(why) => to_train.push((i, Some(why), None)),
            Found::Continue(saved) => to_train.push((i, None, Some(*saved))),
        }
    }
    outln!(
        "experiment: {} x {} with levels {:?} x {} seeds = {} runs{}, {} at a time ({} learner \
         threads each); writing {}",
        grid.envs.join(","),
        grid.algos
            .iter()
            .map(|a| a.name())
            .collect::<Vec<_>>()
            .join(","),
        grid.levels,
        grid.seeds,
        runs.len(),
        if grid.resume {
            format!(
                " ({} finished already, {} to train)",
                reused.len(),
                to_train.len()
            )
        } else {
            String::new()
        },
        grid.jobs.min(to_train.len()).max(1),
        learner_threads,
        grid.out.display()
    );
    for (n, (_, f)) in reused.iter().enumerate() {
        outln!(
            "[{}/{}] {}: reused ({})",
            n + 1,
            runs.len(),
            run_label(&f.config),
            outcome(&f.summary)
        );
    }
    for (i, why, from) in &to_train {
        let path = run_path(&grid.out, &runs[*i]);
        if let Some(why) = why {
            outln!(
                "{}: unfinished ({why}); training it again from the start",
                path.display()
            );
        }
        if let Some(saved) = from {
            outln!(
                "{}: going on from its saved state at {} episodes to {}",
                path.display(),
                saved.trainer.episodes,
                runs[*i].episodes
            );
        }
    }

    let started = Instant::now();
    let next = AtomicUsize::new(0);
    let done = AtomicUsize::new(reused.len());
    // Each result with its run's index in `runs`; the reused runs' first.
    let results: Mutex<Vec<(usize, Result<Finished>)>> =
        Mutex::new(reused.into_iter().map(|(i, f)| (i, Ok(f))).collect());
    std::thread::scope(|scope| {
        for _ in 0..grid.jobs.min(to_train.len()) {
            scope.spawn(|| {
                while let Some((i, again, from)) =
                    to_train.get(next.fetch_add(1, Ordering::Relaxed))
                {
                    if grid.interrupt.load(Ordering::Relaxed) {
                        break;
                    }
                    let config = &runs[*i];
                    let start = Start {
                        from: from.as_ref(),
                        keep_state: grid.keep_state || from.is_some(),
                    };
                    let result =
                        run_one(config, &grid.out, learner_threads, start, &grid.interrupt);
                    let n = done.fetch_add(1, Ordering::Relaxed) + 1;
                    let again = if again.is_some() {
                        " (trained again: it was unfinished)"
                    } else {
                        ""
                    };
                    match &result {
                        Ok(f) => outln!(
                            "[{n}/{}] {}: {}{again}",
                            runs.len(),
                            run_label(&f.config),
                            outcome(&f.summary)
                        ),
                        Err(e) => {
                            outln!(
                                "[{n}/{}] {} failed{again}: {e:#}",
                                runs.len(),
                                config.run_name()
                            )
                        }
                    }
                    results
                        .lock()
                        .expect("no panics while holding the lock")
                        .push((*i, result));
                }
            });
        }
    });
    // A run that failed leaves the others' summary standing: it is left out of the means and
    // named below the tables, and the command fails once the summary is written.
    let mut finished: Vec<Finished> = Vec::new();
    let mut failed: Vec<String> = Vec::new();
    for (i, result) in results.into_inner().expect("workers finished") {
        match result {
            Ok(f) => finished.push(f),
            Err(e) => failed.push(format!("{}: {e:#}", runs[i].run_name())),
        }
    }
    failed.sort();
    if finished.is_empty() && !failed.is_empty() {
        bail!("every run failed:\n{}", failed.join("\n"));
    }

    // Name the algorithm wherever it is not HAC alone.
    let named = grid.algos != [Algo::Hac];
    let mut tables = String::new();
    let mut svgs = Vec::new();
    for env in &grid.envs {
        let groups = group(env, &grid.algos, &grid.levels, &finished);
        let svg = plot::success_chart(
            &format!(
                "{env}: mean test success +- 1 std over {} seeds",
                grid.seeds
            ),
            "training episodes",
            &groups
                .iter()
                .filter(|(_, _, runs)| !runs.is_empty())
                .map(|(algo, k, runs)| series(*algo, *k, named, runs))
                .collect::<Vec<_>>(),
        );
        let svg_path = grid.out.join(format!("{env}.svg"));
        std::fs::write(&svg_path, svg)
            .with_context(|| format!("writing {}", svg_path.display()))?;
        svgs.push(svg_path.display().to_string());
        tables.push_str(&summary_table(env, named, &groups));
        tables.push('\n');
    }
    if !failed.is_empty() {
        tables.push_str(&format!(
            "Failed runs, left out of the tables and plots above:\n\n{}\n",
            failed
                .iter()
                .map(|f| format!("- {f}\n"))
                .collect::<String>()
        ));
    }
    let md_path = grid.out.join("summary.md");
    std::fs::write(&md_path, &tables).with_context(|| format!("writing {}", md_path.display()))?;
    outln!("{tables}");
    outln!(
        "done in {:.1}s: {} and {}",
        started.elapsed().as_secs_f64(),
        svgs.join(", "),
        md_path.display()
    );
    if !failed.is_empty() {
        bail!(
            "{} of {} runs failed (the summary covers the others): {}",
            failed.len(),
            runs.len(),
            failed.join("; ")
        );
    }
    Ok(())
}

fn run_path(out: &Path, config: &RunConfig) -> PathBuf {
    out.join(config.run_name())
}

/// A run as the progress lines name it: `cartpole hac 3 levels, seed 2`.
fn run_label(config: &RunConfig) -> String {
    format!(
        "{} {} {} level{}, seed {}",
        config.env,
        config.algo,
        config.levels,
        if config.levels == 1 { "" } else { "s" },
        config.seed
    )
}

/// A finished run's result as the progress lines give it: final success, when it reached 90%,
/// wall time.
fn outcome(summary: &Summary) -> String {
    format!(
        "final {:.1}%, 90% {}, {:.1}s",
        100.0 * summary.final_success,
        summary
            .episodes_to_90
            .map_or("never".into(), |e| format!("after {e} episodes")),
        summary.wall_time_s
    )
}

/// What the directory `dir` of the run `config` holds, for `--resume`. A run is finished when
/// `summary.json` (written last) and `curve.csv` read back, and the curve ends where the
/// schedule ends a run: at its episode budget, or at a round reaching its `stop_at`. A run
/// stopped by SIGINT/SIGTERM saved a summary too, but its curve stops short: unfinished. So is
/// a directory with `config.toml` and no readable summary or curve (the run was killed, or is
/// training). A finished run whose `config.toml` differs from `config`, or cannot be read, is
/// an error: reusing it would mix configurations, training it again would lose it.
fn inspect(dir: &Path, config: &RunConfig) -> Result<Found> {
    if !dir.join("config.toml").exists() {
        return Ok(Found::Nothing);
    }
    let found = inspect_run(dir, config);
    if matches!(found, Ok(Found::Finished(_))) {
        return found;
    }
    // Unfinished, or finished under another budget: a saved state goes on from where it stood.
    let saved = match state::load(dir) {
        Ok(saved) => saved,
        Err(e) => {
            tracing::warn!(run = %dir.display(), "its saved state does not read back: {e:#}");
            None
        }
    };
    if let Some(loaded) = saved {
        let mut saved = loaded.value;
        if saved.checkpoint.continue_as(config).is_ok() {
            return Ok(Found::Continue(Box::new(saved)));
        }
    }
    found
}

/// [`inspect`] of the run's files, its saved state aside.
fn inspect_run(dir: &Path, config: &RunConfig) -> Result<Found> {
    if !dir.join("summary.json").exists() {
        return Ok(Found::Unfinished(
            "no summary.json: it was stopped before the end".into(),
        ));
    }
    let summary = match run_dir::load_summary(dir) {
        Ok(summary) => summary,
        Err(e) => return Ok(Found::Unfinished(format!("{e:#}"))),
    };
    // The level count of the directory's own run: the summary records it.
    let curve = match run_dir::load_curve(dir, summary.levels) {
        Ok(curve) => curve,
        Err(e) => return Ok(Found::Unfinished(format!("{e:#}"))),
    };
    let last = curve.last();
    if summary.rounds != curve.len() || summary.episodes != last.map_or(0, |r| r.episodes) {
        return Ok(Found::Unfinished(format!(
            "its summary.json ({} rounds, {} episodes) does not match its curve.csv ({} rounds)",
            summary.rounds,
            summary.episodes,
            curve.len()
        )));
    }
    let recorded = config::load_run(dir).with_context(|| {
        format!(
            "{} holds a finished run whose configuration cannot be read; choose another --out \
             or pass --overwrite to train every run again",
            dir.display()
        )
    })?;
    // The summary's final success is the last round's, unrounded (curve.csv has 4 decimals).
    let reached_target = !curve.is_empty()
        && recorded
            .stop_at
            .is_some_and(|target| summary.final_success >= target);
    if summary.episodes < recorded.episodes && !reached_target {
        return Ok(Found::Unfinished(format!(
            "interrupted after {} of {} episodes",
            summary.episodes, recorded.episodes
        )));
    }
    if recorded != *config {
        bail!(
            "{} holds a finished run of another configuration: {}; choose another --out, or \
             pass --overwrite to train every run again",
            dir.display(),
            difference(&recorded, config)
        );
    }
    Ok(Found::Finished(Box::new(Finished {
        config: recorded,
        curve,
        summary,
    })))
}

/// The first key where the configuration `recorded` in a run directory differs from the one the
/// grid resolves (`resolved`), with both values.
fn difference(recorded: &RunConfig, resolved: &RunConfig) -> String {
    let as_table = |c: &RunConfig| toml::Value::try_from(c).ok();
    match (as_table(recorded), as_table(resolved)) {
        (Some(a), Some(b)) => match first_difference(&a, &b, "") {
            Some((key, there, here)) => {
                format!("`{key}` is {there} there and {here} in this grid")
            }
            None => "its config.toml differs from this grid's".into(),
        },
        _ => "its config.toml differs from this grid's".into(),
    }
}

/// The first differing key of `a` and `b` under `prefix` (tables key by key, sorted; other
/// values as a whole), with its value in each (`absent` where one has none).
fn first_difference(
    a: &toml::Value,
    b: &toml::Value,
    prefix: &str,
) -> Option<(String, String, String)> {
    match (a, b) {
        (toml::Value::Table(a), toml::Value::Table(b)) => {
            let mut keys: Vec<&String> = a.keys().chain(b.keys()).collect();
            keys.sort();
            keys.dedup();
            keys.into_iter().find_map(|key| {
                let path = if prefix.is_empty() {
                    key.clone()
                } else {
                    format!("{prefix}.{key}")
                };
                match (a.get(key), b.get(key)) {
                    (Some(x), Some(y)) => first_difference(x, y, &path),
                    (x, y) => {
                        let shown = |v: Option<&toml::Value>| {
                            v.map_or("absent".to_string(), ToString::to_string)
                        };
                        Some((path, shown(x), shown(y)))
                    }
                }
            })
        }
        _ if a == b => None,
        _ => Some((prefix.to_string(), a.to_string(), b.to_string())),
    }
}

/// Where a run of the grid starts, and whether it saves its state when it stops.
struct Start<'a> {
    from: Option<&'a SavedRun>,
    keep_state: bool,
}

fn run_one(
    config: &RunConfig,
    out: &Path,
    learner_threads: usize,
    start: Start<'_>,
    interrupt: &AtomicBool,
) -> Result<Finished> {
    let path = run_path(out, config);
    // Existing runs were refused (unless --overwrite) before any run started.
    let mut dir = match start.from {
        Some(saved) => RunDir::resume(&path, config, saved.checkpoint.curve())?,
        None => RunDir::create(&path, config, true)?,
    };
    if tabular_cmd::handles(&config.env) {
        let (trained, summary) = tabular_cmd::train_into(config, &mut dir, interrupt, |_| {})?;
        return Ok(Finished {
            config: config.clone(),
            curve: trained.curve,
            summary,
        });
    }
    let mut options = LearnerOptions::for_run(config);
    options.learner_threads = learner_threads;
    let embedded = Embedded {
        run: config,
        options,
        from: start.from,
        keep_state: start.keep_state,
        interrupt,
        progress: false,
    };
    let (curve, summary) = embedded.train(&mut dir, &path)?;
    Ok(Finished {
        config: config.clone(),
        curve,
        summary,
    })
}

/// The runs of `env`, grouped by algorithm and level count in the order given, each group by
/// seed.
type Group<'a> = (Algo, usize, Vec<&'a Finished>);

fn group<'a>(env: &str, algos: &[Algo], levels: &[usize], runs: &'a [Finished]) -> Vec<Group<'a>> {
    let mut groups = Vec::new();
    for &algo in algos {
        for &k in levels {
            let mut group: Vec<&Finished> = runs
                .iter()
                .filter(|r| r.config.env == env && r.config.algo == algo && r.config.levels == k)
                .collect();
            group.sort_by_key(|r| r.config.seed);
            groups.push((algo, k, group));
        }
    }
    groups
}

/// A group's name in plots and tables: the level count, after the algorithm when `named`.
fn label(algo: Algo, levels: usize, named: bool) -> String {
    let k = format!("{levels} level{}", if levels == 1 { "" } else { "s" });
    if named {
        format!("{} {k}", algo.name().to_uppercase())
    } else {
        k
    }
}

/// Mean and population standard deviation.
fn mean_std(values: &[f64]) -> (f64, f64) {
    let n = values.len().max(1) as f64;
    let mean = values.iter().sum::<f64>() / n;
    let var = values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n;
    (mean, var.sqrt())
}

/// The mean curve with its +- 1 std band, over the rounds every run of the group reached.
fn series(algo: Algo, levels: usize, named: bool, runs: &[&Finished]) -> plot::Series {
    let rounds = runs.iter().map(|r| r.curve.len()).min().unwrap_or(0);
    let mut points = Vec::with_capacity(rounds);
    let mut band = Vec::with_capacity(rounds);
    for i in 0..rounds {
        let values: Vec<f64> = runs
            .iter()
            .map(|r| r.curve[i].success_rate as f64)
            .collect();
        let (mean, std) = mean_std(&values);
        points.push((runs[0].curve[i].episodes as f64, mean));
        band.push(((mean - std).max(0.0), (mean + std).min(1.0)));
    }
    plot::Series {
        label: label(algo, levels, named),
        points,
        band: Some(band),
    }
}

fn summary_table(env: &str, named: bool, groups: &[Group<'_>]) -> String {
    let first = if named { "algorithm, levels" } else { "levels" };
    let mut s = format!(
        "## {env}\n\n| {first} | seeds | episodes to 50% (median seed; seeds that got there) | episodes to 90% (median seed; seeds that got there) | final success (mean +- std) | wall time per run (mean) |\n| --- | --- | --- | --- | --- | --- |\n"
    );
    for (algo, k, runs) in groups {
        let name = if named {
            label(*algo, *k, true)
        } else {
            k.to_string()
        };
        let to = |f: fn(&Summary) -> Option<u64>| {
            let mut hits: Vec<u64> = runs.iter().filter_map(|r| f(&r.summary)).collect();
            hits.sort_unstable();
            match median_seed(&hits, runs.len()) {
                Some(episodes) => format!("{episodes} ({} of {})", hits.len(), runs.len()),
                None => format!("never ({} of {})", hits.len(), runs.len()),
            }
        };
        let finals: Vec<f64> = runs
            .iter()
            .map(|r| r.summary.final_success as f64)
            .collect();
        let (mean, std) = mean_std(&finals);
        let (wall, _) = mean_std(
            &runs
                .iter()
                .map(|r| r.summary.wall_time_s)
                .collect::<Vec<_>>(),
        );
        s.push_str(&format!(
            "| {name} | {} | {} | {} | {:.1}% +- {:.1} | {wall:.1} s |\n",
            runs.len(),
            to(|s| s.episodes_to_50),
            to(|s| s.episodes_to_90),
            100.0 * mean,
            100.0 * std
        ));
    }
    s
}

/// The median seed's count among `seeds` runs, of which those in `reached` (sorted) got there: a
/// seed that never did counts as slower than every other, so fewer than half reaching gives
/// `None`. The lower middle for an even count, so it is a value that occurred.
fn median_seed(reached: &[u64], seeds: usize) -> Option<u64> {
    reached.get(seeds.max(1).div_ceil(2) - 1).copied()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mean_std_and_median_seed() {
        assert_eq!(mean_std(&[1.0, 3.0]), (2.0, 1.0));
        assert_eq!(median_seed(&[100, 200, 300], 3), Some(200));
        assert_eq!(median_seed(&[100, 200], 2), Some(100));
        // Seeds that never got there are the slowest: 3 of 5 is enough, 2 of 5 is not.
        assert_eq!(median_seed(&[100, 200, 300], 5), Some(300));
        assert_eq!(median_seed(&[100, 200], 5), None);
        assert_eq!(median_seed(&[], 4), None);
        // An even count takes the lower middle: the 5th fastest of 10.
        assert_eq!(median_seed(&[1, 2, 3, 4, 5], 10), Some(5));
        assert_eq!(median_seed(&[1, 2, 3, 4], 10), None);
    }
}
