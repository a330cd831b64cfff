//! Structured logs on stderr for `hac` and the daemons, one setup for all of them, and the one
//! way they print a fatal error ([`error_chain`]).

use std::io::IsTerminal as _;

/// Log format on stderr.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum LogFormat {
    /// Human-readable lines (coloured only when stderr is a terminal).
    Plain,
    /// One JSON object per event.
    Json,
}

/// Installs the global tracing subscriber: `format` on stderr, filtered by `RUST_LOG` (default
/// `info`).
pub fn init_tracing(format: LogFormat) {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_ansi(std::io::stderr().is_terminal())
        .with_writer(std::io::stderr);
    match format {
        LogFormat::Plain => builder.init(),
        LogFormat::Json => builder.json().init(),
    }
}

/// `e` and its causes as `a: b: c`, each said once: tonic's and hyper's errors often repeat
/// their source's message as their own (`tcp connect error: tcp connect error: ...`), so a cause
/// whose message ends the text so far adds nothing and is left out.
pub fn error_chain(e: &anyhow::Error) -> String {
    let mut text = String::new();
    for cause in e.chain() {
        let message = cause.to_string();
        if text.is_empty() {
            text = message;
        } else if text != message && !text.ends_with(&format!(": {message}")) {
            text.push_str(": ");
            text.push_str(&message);
        }
    }
    text
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_chain_says_each_cause_once() {
        let e = anyhow::anyhow!("connection refused")
            .context("tcp connect error")
            .context("tcp connect error")
            .context("transport error")
            .context("connecting to 127.0.0.1:1");
        assert_eq!(
            error_chain(&e),
            "connecting to 127.0.0.1:1: transport error: tcp connect error: connection refused"
        );
        // A message that already quotes its cause.
        let e = anyhow::anyhow!("refused").context("status: refused");
        assert_eq!(error_chain(&e), "status: refused");
    }
}
