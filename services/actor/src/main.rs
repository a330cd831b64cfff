//! `hac-actor`: the actor daemon (the same as `hac actor`); see [`hac_actor_service`].

use clap::Parser;
use hac_actor_service::ActorArgs;

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

#[derive(Debug, Clone, Copy, clap::ValueEnum)]
enum LogFormat {
    Plain,
    Json,
}

fn main() {
    let cli = Cli::parse();
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
    let logs = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr);
    match cli.log_format {
        LogFormat::Plain => logs.init(),
        LogFormat::Json => logs.json().init(),
    }
    if let Err(e) = hac_actor_service::run(cli.args) {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}
