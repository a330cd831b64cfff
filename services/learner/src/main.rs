//! `hac-learner`: the learner daemon (the same as `hac learner`); see [`hac_learner_service`].

use clap::Parser;
use hac_learner_service::LearnerArgs;
use hac_run::logging::{LogFormat, init_tracing};

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
    let cli = Cli::parse();
    init_tracing(cli.log_format);
    if let Err(e) = hac_learner_service::run(cli.args) {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}
