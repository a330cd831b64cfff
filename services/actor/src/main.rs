//! `hac-actor`: the actor daemon (the same as `hac actor`); see [`hac_actor_service`].

use clap::Parser;
use hac_actor_service::ActorArgs;
use hac_run::daemon::{self, Mount, Section};
use hac_run::logging::{LogFormat, error_chain, init_tracing};

#[derive(Debug, Parser)]
#[command(
    name = "hac-actor",
    version,
    about = "A HAC actor: rolls out episodes and streams them to a learner service over gRPC"
)]
struct Cli {
    /// Log format on stderr (filter with RUST_LOG, default `info`).
    #[arg(long, value_enum, default_value_t = LogFormat::Plain, env = "HAC_LOG_FORMAT")]
    log_format: LogFormat,
    #[command(flatten)]
    args: ActorArgs,
}

fn main() {
    let actor = hac_actor_service::config_section();
    // This binary does not link the learner: its table is checked by key names.
    let learner = Section::of_keys("learner", daemon::keys::LEARNER);
    let mount = Mount {
        path: &[],
        section: &actor,
    };
    let result = daemon::parse::<Cli>(&[mount], &[&learner]).and_then(|(mut cli, resolved)| {
        cli.args.config.resolved = resolved;
        init_tracing(cli.log_format);
        hac_actor_service::run(cli.args)
    });
    if let Err(e) = result {
        eprintln!("error: {}", error_chain(&e));
        std::process::exit(1);
    }
}
