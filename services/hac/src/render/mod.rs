//! `hac render`: one greedy (test-mode) episode of a trained run, drawn frame by frame: the state,
//! the end goal and every level's current subgoal, with a legend.
//!
//! - [`record`]: the policy wrapper that captures each level's goal as the episode runs;
//! - [`scenes`]: how each environment is drawn;
//! - [`raster`]: the indexed-colour canvas, shapes and bitmap font;
//! - this file: the command, the frame layout (header, picture, legend) and the encoders (an
//!   animated GIF, or numbered PNG files).

mod raster;
mod record;
mod scenes;

use std::borrow::Cow;
use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use hac_agent::Agent;
use hac_core::{Env, EpisodeOutcome, GaussianExploration, Hierarchy, Mode, NullSink, Policy, Rng};

use crate::config::{self, RunConfig};
use crate::{run_dir, tabular_cmd};
use raster::{BLACK, Canvas, DARK_GREY, END_GOAL, PAPER, subgoal_colour, text_width};
use record::{Frame, SubgoalRecorder};
use scenes::Scene;

#[derive(Debug, clap::Args)]
pub struct RenderArgs {
    /// A run directory written by `hac train` (or one run of `hac experiment`).
    #[arg(long)]
    run: PathBuf,
    /// Output: an animated GIF if the name ends in `.gif`, otherwise a directory (created if
    /// missing, refused if not empty) of numbered PNG frames `frame-00000.png`, ...
    #[arg(long)]
    out: PathBuf,
    /// Seed of the episode's initial state and end goal (and of the tabular agent's choice
    /// between equally valued actions).
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// End the episode after at most this many primitive actions [default: the environment's
    /// budget, max_actions]; the episode also ends when the end goal is reached.
    #[arg(long, value_name = "MAX")]
    episode_steps: Option<usize>,
}

pub fn run(args: &RenderArgs) -> Result<()> {
    let run = config::load_run(&args.run)?;
    let scene = scenes::scene_for(&run.env).with_context(|| {
        format!(
            "no renderer for environment `{}` (renderable: pendulum, ur5-reacher, mountain-car, \
             cartpole, pick-and-place, four-rooms, four-rooms-25)",
            run.env
        )
    })?;
    if args.episode_steps == Some(0) {
        bail!("invalid value for `--episode-steps`: must be at least 1");
    }
    if run.hiro().is_some() {
        bail!(
            "{} is a HIRO run: `hac render` draws HAC's absolute subgoals, and HIRO's are relative \
             goals it does not draw yet (`hac eval --per-episode` plays its greedy episodes)",
            args.run.display()
        );
    }
    let (mut env, mut policy) = load_policy(&args.run, &run, args.seed)?;
    let mut spec = env.spec().clone();
    if let Some(max) = args.episode_steps {
        spec.max_actions = spec.max_actions.min(max);
    }
    let max_actions = spec.max_actions;

    let mut rng = Rng::seed_from(args.seed);
    // Never consulted in test mode, where every level acts greedily.
    let mut exploration = GaussianExploration::new(&spec, &run.agent, rng.fork());
    let mut hierarchy = Hierarchy::new(&spec, &run.agent);
    let mut recorder = SubgoalRecorder::new(policy.as_mut(), run.levels);
    let outcome = hierarchy.run_episode(
        env.as_mut(),
        &mut recorder,
        &mut exploration,
        Mode::Test,
        &mut rng,
        &mut NullSink,
    );
    let frames = recorder.finish(env.state());

    let layout = Layout::new(scene, &run, args.seed, max_actions);
    let mut canvas = Canvas::new(layout.width as usize, layout.height as usize, PAPER);
    let mut output = Output::create(&args.out, &canvas)?;
    for (i, frame) in frames.iter().enumerate() {
        let last = i + 1 == frames.len();
        layout.draw(&mut canvas, frame, last.then_some(&outcome));
        // Hold the last frame so the end of the loop can be seen.
        let delay = if last {
            150
        } else {
            layout.scene.frame_delay()
        };
        output.write(&canvas, delay)?;
    }
    output.finish()?;
    outln!(
        "{}: {} with {} level{}, seed {}: {} ({} primitive actions); {} frames written to {}",
        args.run.display(),
        run.env,
        run.levels,
        if run.levels == 1 { "" } else { "s" },
        args.seed,
        if outcome.success {
            "end goal reached"
        } else {
            "end goal not reached"
        },
        outcome.steps,
        frames.len(),
        args.out.display()
    );
    Ok(())
}

/// The run's environment and its trained greedy policy.
fn load_policy(
    run_dir: &Path,
    run: &RunConfig,
    seed: u64,
) -> Result<(Box<dyn Env>, Box<dyn Policy>)> {
    if tabular_cmd::handles(&run.env) {
        let (env, agent) = tabular_cmd::load(run_dir, run, seed)?;
        return Ok((Box::new(env), Box::new(agent)));
    }
    let env = run.make_env()?;
    let agent = Agent::load(&run_dir::weights_dir(run_dir), env.spec(), run)
        .context("loading the run's weights")?;
    Ok((env, Box::new(agent)))
}

const MARGIN: i32 = 8;
const SCALE: i32 = 2;
/// Height of a text line: a glyph and two pixels of space, scaled.
const LINE: i32 = (raster::GLYPH_HEIGHT + 2) * SCALE;
const SWATCH: i32 = 10;

/// Where everything goes on a frame: two header lines, the scene's picture, then a legend line
/// for the state, the end goal and each level's subgoal.
struct Layout {
    scene: Box<dyn Scene>,
    title: String,
    levels: usize,
    max_actions: usize,
    width: i32,
    height: i32,
    picture: (i32, i32),
    legend_y: i32,
}

impl Layout {
    fn new(scene: Box<dyn Scene>, run: &RunConfig, seed: u64, max_actions: usize) -> Self {
        let (w, h) = scene.size();
        // Room for a legend line of about 40 characters.
        let legend_w = SWATCH + 6 + text_width(&"X".repeat(40), SCALE);
        let width = w.max(legend_w) + 2 * MARGIN;
        let picture = ((width - w) / 2, MARGIN + 2 * LINE + 4);
        let legend_y = picture.1 + h + MARGIN;
        let height = legend_y + (run.levels as i32 + 1) * LINE + MARGIN;
        let title = format!(
            "{}  {} LEVEL{}  SEED {seed}",
            run.env,
            run.levels,
            if run.levels == 1 { "" } else { "S" }
        );
        Self {
            scene,
            title,
            levels: run.levels,
            max_actions,
            width,
            height,
            picture,
            legend_y,
        }
    }

    /// Draws `frame`; `outcome` is given for the episode's last frame.
    fn draw(&self, canvas: &mut Canvas, frame: &Frame, outcome: Option<&EpisodeOutcome>) {
        canvas.clear(PAPER);
        canvas.text(MARGIN, MARGIN, &self.title, SCALE, DARK_GREY);
        let status = match outcome {
            Some(o) if o.success => "  END GOAL REACHED",
            Some(_) => "  END GOAL NOT REACHED",
            None => "",
        };
        let step = format!("STEP {}/{}{status}", frame.step, self.max_actions);
        canvas.text(MARGIN, MARGIN + LINE, &step, SCALE, DARK_GREY);
        let (w, h) = self.scene.size();
        canvas.fill_rect(self.picture.0, self.picture.1, w, h, raster::WHITE);
        self.scene.draw(canvas, self.picture, frame);

        let mut lines = vec![(
            BLACK,
            format!("STATE  {}", self.scene.describe_state(&frame.state)),
        )];
        if !frame.end_goal().is_empty() {
            lines.push((
                END_GOAL,
                format!("END GOAL  {}", self.scene.describe_goal(frame.end_goal())),
            ));
        }
        for level in (1..self.levels).rev() {
            if !frame.subgoal(level).is_empty() {
                lines.push((
                    subgoal_colour(level),
                    format!(
                        "L{level} SUBGOAL  {}",
                        self.scene.describe_goal(frame.subgoal(level))
                    ),
                ));
            }
        }
        for (i, (colour, text)) in lines.iter().enumerate() {
            let y = self.legend_y + i as i32 * LINE;
            canvas.fill_rect(MARGIN, y, SWATCH, SWATCH, *colour);
            canvas.text(MARGIN + SWATCH + 6, y, text, SCALE, BLACK);
        }
    }
}

/// Where frames go.
enum Output {
    Gif {
        path: PathBuf,
        encoder: gif::Encoder<BufWriter<File>>,
        width: u16,
        height: u16,
    },
    Png {
        dir: PathBuf,
        next: usize,
    },
}

impl Output {
    /// Opens `path` for frames the size of `canvas`: a GIF file when it ends in `.gif`, else a
    /// directory of PNG files.
    fn create(path: &Path, canvas: &Canvas) -> Result<Self> {
        let is_gif = path
            .extension()
            .is_some_and(|e| e.eq_ignore_ascii_case("gif"));
        if !is_gif {
            if path.is_file() {
                bail!(
                    "{} is a file: give a name ending in .gif for an animated GIF, or a directory for PNG frames",
                    path.display()
                );
            }
            std::fs::create_dir_all(path)
                .with_context(|| format!("creating output directory {}", path.display()))?;
            let not_empty = std::fs::read_dir(path)
                .with_context(|| format!("reading output directory {}", path.display()))?
                .next()
                .is_some();
            if not_empty {
                bail!(
                    "output directory {} is not empty; choose a new or empty one",
                    path.display()
                );
            }
            return Ok(Output::Png {
                dir: path.to_path_buf(),
                next: 0,
            });
        }
        let (width, height) = (to_u16(canvas.width())?, to_u16(canvas.height())?);
        let file = File::create(path).with_context(|| format!("creating {}", path.display()))?;
        let gif_error = |e| anyhow::Error::new(e).context(format!("writing {}", path.display()));
        let mut encoder = gif::Encoder::new(
            BufWriter::new(file),
            width,
            height,
            &raster::palette_bytes(),
        )
        .map_err(gif_error)?;
        encoder
            .set_repeat(gif::Repeat::Infinite)
            .map_err(gif_error)?;
        Ok(Output::Gif {
            path: path.to_path_buf(),
            encoder,
            width,
            height,
        })
    }

    /// Adds one frame shown for `delay` hundredths of a second (GIF only).
    fn write(&mut self, canvas: &Canvas, delay: u16) -> Result<()> {
        match self {
            Output::Gif {
                path,
                encoder,
                width,
                height,
            } => {
                let frame = gif::Frame {
                    width: *width,
                    height: *height,
                    delay,
                    buffer: Cow::Borrowed(canvas.pixels()),
                    ..gif::Frame::default()
                };
                encoder
                    .write_frame(&frame)
                    .with_context(|| format!("writing {}", path.display()))
            }
            Output::Png { dir, next } => {
                let path = dir.join(format!("frame-{next:05}.png"));
                *next += 1;
                write_png(&path, canvas).with_context(|| format!("writing {}", path.display()))
            }
        }
    }

    /// Completes the file (the GIF trailer); PNG frames are complete as written.
    fn finish(self) -> Result<()> {
        if let Output::Gif { path, encoder, .. } = self {
            let mut writer = encoder
                .into_inner()
                .with_context(|| format!("writing {}", path.display()))?;
            std::io::Write::flush(&mut writer)
                .with_context(|| format!("writing {}", path.display()))?;
        }
        Ok(())
    }
}

fn to_u16(n: usize) -> Result<u16> {
    u16::try_from(n)
        .with_context(|| format!("a frame {n} pixels wide or high is too large for a GIF"))
}

fn write_png(path: &Path, canvas: &Canvas) -> Result<()> {
    let file = File::create(path)?;
    let mut encoder = png::Encoder::new(
        BufWriter::new(file),
        canvas.width() as u32,
        canvas.height() as u32,
    );
    encoder.set_color(png::ColorType::Indexed);
    encoder.set_depth(png::BitDepth::Eight);
    encoder.set_palette(raster::palette_bytes());
    let mut writer = encoder.write_header()?;
    writer.write_image_data(canvas.pixels())?;
    writer.finish()?;
    Ok(())
}
