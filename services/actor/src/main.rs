//! `hac-actor`: the actor daemon (the same as `hac actor`); see [`hac_actor_service`].

use clap::Parser;
use hac_actor_service::ActorArgs;
use hac_run::logging::{LogFormat, init_tracing};

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
    let cli = Cli::parse();
    init_tracing(cli.log_format);
    if let Err(e) = hac_actor_service::run(cli.args) {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}
