//! `hac-learner`: the learner daemon (the same as `hac learner`); see [`hac_learner_service`].

use clap::Parser;
use hac_learner_service::LearnerArgs;
use hac_run::daemon::{self, Mount, Section};
use hac_run::logging::{LogFormat, error_chain, init_tracing};

#[derive(Debug, Parser)]
#[command(
    name = "hac-learner",
    version,
    about = "The HAC learner service: trains every level on what actors stream to it over gRPC"
)]
struct Cli {
    /// Log format on stderr (filter with RUST_LOG, default `info`).
    #[arg(long, value_enum, default_value_t = LogFormat::Plain, env = "HAC_LOG_FORMAT")]
    log_format: LogFormat,
    #[command(flatten)]
    args: LearnerArgs,
}

fn main() {
    let learner = hac_learner_service::config_section();
    // This binary does not link the actor: its table is checked by key names.
    let actor = Section::of_keys("actor", daemon::keys::ACTOR);
    let mount = Mount {
        path: &[],
        section: &learner,
    };
    let result = daemon::parse::<Cli>(&[mount], &[&actor]).and_then(|(mut cli, resolved)| {
        cli.args.config.resolved = resolved;
        init_tracing(cli.log_format);
        hac_learner_service::run(cli.args)
    });
    if let Err(e) = result {
        eprintln!("error: {}", error_chain(&e));
        std::process::exit(1);
    }
}
