//! What defines a run and what it leaves behind, shared by `hac` and the daemons so that every
//! entry point resolves a run identically:
//!
//! - [`config`]: the layered run configuration (environment defaults, a TOML file, `HAC_*`
//!   variables, flags), validated with errors that name the key;
//! - [`registry`]: every built-in environment by name (continuous tasks and grid worlds);
//! - [`daemon`]: the daemons' `[learner]` and `[actor]` config tables, derived from their clap
//!   definitions (every flag is a key and a `HAC_*` variable);
//! - [`run_dir`]: the run directory (`config.toml`, `curve.csv`, `curve.svg`, weights,
//!   `summary.json`);
//! - [`checkpoints`]: checkpoint directories written atomically with a manifest, kept to the
//!   newest K, loaded newest-valid-first;
//! - [`plot`]: SVG learning curves;
//! - [`logging`]: the tracing setup every binary shares;
//! - [`output`]: the binaries' output on stdout ([`outln!`], [`out!`]), ending quietly when the
//!   reader closes the pipe;
//! - [`signals`]: the interrupt flag of long-running commands;
//! - [`security`]: the token and TLS flags of the daemons and `hac status`.

pub mod checkpoints;
pub mod config;
pub mod daemon;
pub mod logging;
pub mod output;
pub mod plot;
pub mod registry;
pub mod run_dir;
pub mod security;
pub mod signals;
