//! The learner daemon's operations flags ([`OpsArgs`], flattened into [`LearnerArgs`]):
//! Prometheus metrics, the per-actor message rate limit, the bearer token and TLS.
//!
//! [`LearnerArgs`]: crate::LearnerArgs

use std::net::SocketAddr;
use std::sync::Arc;

use anyhow::{Context, Result};
use hac_learner::Learner;
use hac_run::security::{ServerTlsArgs, TokenArgs};
use hac_serve::metrics::learner_metrics;
use hac_transport::grpc::ServerSecurity;
use hac_transport::metrics::serve_metrics;
use tokio::net::TcpListener;
use tokio::sync::watch;

/// Metrics, limits and security of the learner daemon.
#[derive(Debug, Clone, Default, clap::Args)]
pub struct OpsArgs {
    /// Serve Prometheus metrics at http://ADDR/metrics (port 0 picks a free port; the address
    /// is printed on stdout as `metrics on <addr>` after the `listening on` line) [default: off].
    #[arg(long, env = "HAC_METRICS_LISTEN", value_name = "ADDR")]
    pub metrics_listen: Option<SocketAddr>,
    /// Most ingest messages (batches and episode summaries) per second taken from one actor;
    /// faster actors are held back (backpressure: nothing is refused, their sends block)
    /// [default: no limit].
    #[arg(long, env = "HAC_MAX_ACTOR_MESSAGES_PER_SECOND", value_name = "N",
          value_parser = positive_rate)]
    pub max_actor_messages_per_second: Option<f64>,
    #[command(flatten)]
    pub token: TokenArgs,
    #[command(flatten)]
    pub tls: ServerTlsArgs,
}

fn positive_rate(text: &str) -> Result<f64, String> {
    let rate: f64 = text
        .parse()
        .map_err(|e| format!("`{text}` is not a number: {e}"))?;
    if rate.is_finite() && rate > 0.0 {
        Ok(rate)
    } else {
        Err(format!(
            "`{text}`: must be a positive number of messages per second"
        ))
    }
}

impl OpsArgs {
    /// The token and TLS, read and checked (before any port is bound).
    pub fn security(&self) -> Result<ServerSecurity> {
        Ok(ServerSecurity {
            token: self.token.token()?,
            tls: self.tls.server_tls()?,
        })
    }

    /// Binds `--metrics-listen` if set, and returns its address with the server task, which
    /// runs until `stop` is set.
    pub async fn start_metrics(
        &self,
        learner: &Arc<Learner>,
        mut stop: watch::Receiver<bool>,
    ) -> Result<Option<(SocketAddr, tokio::task::JoinHandle<std::io::Result<()>>)>> {
        let Some(addr) = self.metrics_listen else {
            return Ok(None);
        };
        let listener = TcpListener::bind(addr)
            .await
            .with_context(|| format!("binding --metrics-listen {addr}"))?;
        let bound = listener.local_addr().context("reading the bound address")?;
        let learner = learner.clone();
        let server = tokio::spawn(serve_metrics(
            listener,
            Arc::new(move || learner_metrics(&learner)),
            async move {
                let _ = stop.wait_for(|&stop| stop).await;
            },
        ));
        Ok(Some((bound, server)))
    }
}
