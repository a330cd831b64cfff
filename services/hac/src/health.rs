//! `hac health`: one standard gRPC health check (`grpc.health.v1.Health/Check`), for container
//! health checks (the Compose file runs it inside the image) and for people. Exits 0 when the
//! service is SERVING; otherwise prints what was answered and exits 1. The health service needs
//! no token.

use std::time::Duration;

use anyhow::{Context, Result, bail};
use hac_transport::security::endpoint;
use tonic_health::pb::health_check_response::ServingStatus;
use tonic_health::pb::{HealthCheckRequest, health_client::HealthClient};

/// `hac health` flags.
#[derive(Debug, clap::Args)]
pub struct HealthArgs {
    /// The server, as `host:port` or `http://host:port` (a learner's --listen or an actor's
    /// --status-listen).
    pub url: String,
    /// The service asked about: "" is the whole server; a learner also answers for
    /// `hac.v1.Learner`, an actor for `hac.v1.Status`.
    #[arg(long, default_value = "")]
    pub service: String,
    /// Seconds to wait for the connection and the answer.
    #[arg(long, value_name = "SECS", default_value = "5", value_parser = seconds)]
    pub timeout: Duration,
}

/// A flag value in seconds (fractions allowed).
fn seconds(text: &str) -> Result<Duration, String> {
    let secs: f64 = text
        .parse()
        .map_err(|e| format!("`{text}` is not a number of seconds: {e}"))?;
    Duration::try_from_secs_f64(secs).map_err(|e| format!("`{text}` seconds: {e}"))
}

/// Runs the check; `Ok` only when the service is SERVING.
pub fn run(args: &HealthArgs) -> Result<()> {
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("starting the async runtime")?;
    let status = runtime.block_on(check(args))?;
    let shown = if args.service.is_empty() {
        "the server"
    } else {
        args.service.as_str()
    };
    match status {
        ServingStatus::Serving => {
            outln!("{shown} at {}: SERVING", args.url);
            Ok(())
        }
        other => bail!("{shown} at {}: {}", args.url, other.as_str_name()),
    }
}

async fn check(args: &HealthArgs) -> Result<ServingStatus> {
    // The one address parser of every command (`hac status`, the actor's --learner).
    let endpoint = endpoint(&args.url, None)
        .with_context(|| format!("invalid server URL `{}`", args.url))?
        .connect_timeout(args.timeout)
        .timeout(args.timeout);
    let channel = endpoint
        .connect()
        .await
        .with_context(|| format!("connecting to {}", args.url))?;
    let response = HealthClient::new(channel)
        .check(HealthCheckRequest {
            service: args.service.clone(),
        })
        .await
        .map_err(|status| match status.code() {
            tonic::Code::NotFound => {
                anyhow::anyhow!("{} does not know the service `{}`", args.url, args.service)
            }
            code => anyhow::anyhow!(
                "health check at {}: {code:?}: {}",
                args.url,
                status.message()
            ),
        })?;
    Ok(ServingStatus::try_from(response.into_inner().status).unwrap_or(ServingStatus::Unknown))
}
