//! Prometheus metrics: the text exposition format ([`Exposition`]), a minimal HTTP/1 server for
//! `GET /metrics` ([`serve_metrics`]), and what an actor daemon exposes ([`actor_metrics`]; the
//! learner's are `hac_serve::metrics::learner_metrics`).
//!
//! Names follow the Prometheus conventions: a `hac_learner_` or `hac_actor_` prefix, base units
//! in the name (`_seconds`, `_bytes`; transitions, episodes and steps are counts), counters end in
//! `_total`, and every family has HELP and TYPE lines. Rates are left to PromQL (`rate(...)`), so
//! only totals and gauges are exposed. A scrape renders a fresh snapshot; nothing is kept between
//! scrapes.

use std::convert::Infallible;
use std::fmt::Write as _;
use std::future::Future;
use std::sync::Arc;
use std::time::Duration;

use http::{Method, Request, Response, StatusCode, header};
use http_body_util::Full;
use hyper::body::{Bytes, Incoming};
use hyper::server::conn::http1;
use hyper::service::service_fn;
use hyper_util::rt::{TokioIo, TokioTimer};
use tokio::net::TcpListener;

use crate::grpc::ActorNodeStatus;

/// The content type of the text exposition format.
pub const CONTENT_TYPE: &str = "text/plain; version=0.0.4; charset=utf-8";
/// The path metrics are served on.
pub const PATH: &str = "/metrics";
/// Longest wait for a request's headers before the connection is closed.
const HEADER_TIMEOUT: Duration = Duration::from_secs(10);

/// A metric family's type.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kind {
    Counter,
    Gauge,
}

/// A document in the Prometheus text exposition format, built family by family.
#[derive(Debug, Default)]
pub struct Exposition {
    text: String,
}

impl Exposition {
    pub fn new() -> Self {
        Self::default()
    }

    /// Starts the family `name` (HELP and TYPE lines); add its samples with
    /// [`sample`](Self::sample).
    pub fn family(&mut self, name: &str, kind: Kind, help: &str) -> &mut Self {
        let kind = match kind {
            Kind::Counter => "counter",
            Kind::Gauge => "gauge",
        };
        let help = help.replace('\\', "\\\\").replace('\n', "\\n");
        let _ = writeln!(self.text, "# HELP {name} {help}");
        let _ = writeln!(self.text, "# TYPE {name} {kind}");
        self
    }

    /// One sample of the current family.
    pub fn sample(&mut self, name: &str, labels: &[(&str, &str)], value: f64) -> &mut Self {
        self.text.push_str(name);
        if !labels.is_empty() {
            self.text.push('{');
            for (i, (label, value)) in labels.iter().enumerate() {
                if i > 0 {
                    self.text.push(',');
                }
                let value = value
                    .replace('\\', "\\\\")
                    .replace('"', "\\\"")
                    .replace('\n', "\\n");
                let _ = write!(self.text, "{label}=\"{value}\"");
            }
            self.text.push('}');
        }
        self.text.push(' ');
        if value.is_nan() {
            self.text.push_str("NaN");
        } else if value.is_infinite() {
            self.text
                .push_str(if value > 0.0 { "+Inf" } else { "-Inf" });
        } else {
            let _ = write!(self.text, "{value}");
        }
        self.text.push('\n');
        self
    }

    /// A family with a single unlabelled sample.
    pub fn single(&mut self, name: &str, kind: Kind, help: &str, value: f64) -> &mut Self {
        self.family(name, kind, help).sample(name, &[], value)
    }

    pub fn finish(self) -> String {
        self.text
    }
}

/// Serves `GET /metrics` (and `HEAD`) with whatever `render` returns, on `listener`, until
/// `shutdown` completes; then stops accepting (scrapes in progress finish on their own). Other
/// paths get 404, other methods 405.
pub async fn serve_metrics(
    listener: TcpListener,
    render: Arc<dyn Fn() -> String + Send + Sync>,
    shutdown: impl Future<Output = ()>,
) -> std::io::Result<()> {
    tokio::pin!(shutdown);
    loop {
        let (stream, peer) = tokio::select! {
            () = &mut shutdown => return Ok(()),
            accepted = listener.accept() => match accepted {
                Ok(accepted) => accepted,
                // Out of file descriptors and the like: the next accept may work.
                Err(e) => {
                    tracing::warn!(error = %e, "metrics: accepting a connection failed");
                    tokio::time::sleep(Duration::from_millis(100)).await;
                    continue;
                }
            },
        };
        let render = render.clone();
        tokio::spawn(async move {
            let service = service_fn(move |request| {
                let render = render.clone();
                async move { Ok::<_, Infallible>(respond(&request, render.as_ref())) }
            });
            let connection = http1::Builder::new()
                .timer(TokioTimer::new())
                .header_read_timeout(HEADER_TIMEOUT)
                .serve_connection(TokioIo::new(stream), service);
            if let Err(e) = connection.await {
                tracing::debug!(%peer, error = %e, "metrics connection ended");
            }
        });
    }
}

fn respond(
    request: &Request<Incoming>,
    render: &(dyn Fn() -> String + Send + Sync),
) -> Response<Full<Bytes>> {
    let reply = |status: StatusCode, body: String| {
        Response::builder()
            .status(status)
            .header(header::CONTENT_TYPE, CONTENT_TYPE)
            .body(Full::new(Bytes::from(body)))
            .expect("a valid response")
    };
    if request.uri().path() != PATH {
        return reply(
            StatusCode::NOT_FOUND,
            format!("not found: metrics are at {PATH}\n"),
        );
    }
    match *request.method() {
        Method::GET => reply(StatusCode::OK, render()),
        Method::HEAD => reply(StatusCode::OK, String::new()),
        _ => reply(StatusCode::METHOD_NOT_ALLOWED, "only GET and HEAD\n".into()),
    }
}

/// An actor daemon's metrics from its status.
pub fn actor_metrics(s: &ActorNodeStatus) -> String {
    use Kind::{Counter, Gauge};
    let mut m = Exposition::new();
    m.family("hac_actor_info", Gauge, "This actor's identity (always 1).")
        .sample(
            "hac_actor_info",
            &[
                ("actor", &s.actor_id),
                ("role", s.role),
                ("transport", s.transport),
                ("learner", &s.learner),
            ],
            1.0,
        );
    m.single(
        "hac_actor_ready",
        Gauge,
        "1 while registered with the learner and acting, else 0.",
        f64::from(u8::from(s.state == "running")),
    );
    m.single(
        "hac_actor_uptime_seconds",
        Gauge,
        "Seconds since the actor started.",
        s.uptime.as_secs_f64(),
    );
    m.single(
        "hac_actor_incarnation",
        Gauge,
        "The current registration's incarnation (0 before the first).",
        s.incarnation as f64,
    );
    for (name, help, value) in [
        (
            "hac_actor_episodes_total",
            "Training episodes played and sent.",
            s.episodes,
        ),
        (
            "hac_actor_episode_successes_total",
            "Training episodes that reached their goal.",
            s.successes,
        ),
        (
            "hac_actor_env_steps_total",
            "Primitive environment steps of training episodes.",
            s.env_steps,
        ),
        (
            "hac_actor_evaluations_total",
            "Greedy test rounds reported.",
            s.evaluations,
        ),
        (
            "hac_actor_reconnects_total",
            "Reconnects to the learner after a failed call or stream.",
            s.reconnects,
        ),
    ] {
        m.single(name, Counter, help, value as f64);
    }
    for (name, help, value) in [
        (
            "hac_actor_weights_version",
            "The weights version the actor acts with.",
            s.weights_version,
        ),
        (
            "hac_actor_learner_weights_version",
            "The newest weights version the learner announced.",
            s.learner_weights_version,
        ),
        (
            "hac_actor_unacked_messages",
            "Messages sent and not yet acknowledged by the learner.",
            s.unacked,
        ),
        (
            "hac_actor_undurable_messages",
            "Messages acknowledged and not yet durable (kept to be resent to a restarted learner).",
            s.undurable,
        ),
    ] {
        m.single(name, Gauge, help, value as f64);
    }
    m.finish()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_exposition_format_escapes_and_types() {
        let mut m = Exposition::new();
        m.family("x_total", Kind::Counter, "Things\\done\nhere.")
            .sample("x_total", &[("a", "q\"u\\o\nte"), ("b", "2")], 3.0)
            .sample("x_total", &[], 0.5);
        m.single("y", Kind::Gauge, "Y.", f64::NAN);
        m.single("z", Kind::Gauge, "Z.", f64::NEG_INFINITY);
        assert_eq!(
            m.finish(),
            "# HELP x_total Things\\\\done\\nhere.\n# TYPE x_total counter\n\
             x_total{a=\"q\\\"u\\\\o\\nte\",b=\"2\"} 3\nx_total 0.5\n\
             # HELP y Y.\n# TYPE y gauge\ny NaN\n# HELP z Z.\n# TYPE z gauge\nz -Inf\n"
        );
    }

    #[test]
    fn actor_metrics_follow_the_naming_conventions() {
        let text = actor_metrics(&ActorNodeStatus {
            actor_id: "a-0".into(),
            role: "trainer",
            state: "running",
            transport: "grpc",
            episodes: 12,
            unacked: 3,
            ..ActorNodeStatus::default()
        });
        assert!(text.contains("\nhac_actor_episodes_total 12\n"), "{text}");
        assert!(text.contains("\nhac_actor_unacked_messages 3\n"), "{text}");
        assert!(text.contains("\nhac_actor_ready 1\n"), "{text}");
        check_conventions(&text);
    }

    /// Every sample belongs to the family announced just before it, with HELP and TYPE;
    /// counters end in `_total`.
    pub(crate) fn check_conventions(text: &str) {
        let mut family: Option<(&str, &str)> = None;
        let mut help = None;
        for line in text.lines() {
            if let Some(rest) = line.strip_prefix("# HELP ") {
                help = rest.split(' ').next();
            } else if let Some(rest) = line.strip_prefix("# TYPE ") {
                let mut parts = rest.split(' ');
                let (name, kind) = (parts.next().unwrap(), parts.next().unwrap());
                assert_eq!(help, Some(name), "HELP before TYPE for {name}");
                assert_eq!(
                    name.ends_with("_total"),
                    kind == "counter",
                    "{name} is a {kind}"
                );
                assert!(name.starts_with("hac_"), "{name}");
                family = Some((name, kind));
            } else {
                let (name, _) = family.expect("a sample after a TYPE line");
                let sample = line.split(['{', ' ']).next().unwrap();
                assert_eq!(sample, name, "{line}");
                let value = line.rsplit(' ').next().unwrap();
                assert!(value.parse::<f64>().is_ok() || value == "NaN", "{line}");
            }
        }
    }
}
