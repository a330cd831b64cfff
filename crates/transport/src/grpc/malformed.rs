//! [`RefuseUndecodable`]: one answer to bytes that do not decode, whatever the RPC.
//!
//! tonic decodes a unary or server-streaming request before the handler runs, and answers bytes
//! it cannot decode (not protobuf, a broken frame, no message at all) with `INTERNAL` on its
//! own, uncounted. Ingest streams decode in the handler, which refuses such bytes as
//! `INVALID_ARGUMENT`/`malformed`. This wrapper around a whole service gives every other RPC the
//! same refusal: an `INTERNAL` status in a response's headers (a refusal before any message was
//! sent) is replaced by the `malformed` one and reported. The hac handlers answer no `INTERNAL`
//! of their own before their first message, so the status is tonic's decoding failure.

use std::convert::Infallible;
use std::fmt;
use std::future::Future;
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};

use hac_proto::RejectReason;
use tonic::body::Body;
use tonic::server::NamedService;
use tonic::{Code, Status};

use super::refusal_status;

/// Told about each refusal (its message): the learner counts and logs it.
pub type OnMalformed = Arc<dyn Fn(&str) + Send + Sync>;

/// A tonic service whose decoding failures are `INVALID_ARGUMENT`/`malformed` refusals; see the
/// module docs.
#[derive(Clone)]
pub struct RefuseUndecodable<S> {
    inner: S,
    on_malformed: Option<OnMalformed>,
}

impl<S> RefuseUndecodable<S> {
    /// Wraps `inner`; `on_malformed` (if any) is told about each refusal.
    pub fn new(inner: S, on_malformed: Option<OnMalformed>) -> Self {
        Self {
            inner,
            on_malformed,
        }
    }
}

impl<S: fmt::Debug> fmt::Debug for RefuseUndecodable<S> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("RefuseUndecodable")
            .field("inner", &self.inner)
            .finish_non_exhaustive()
    }
}

impl<S: NamedService> NamedService for RefuseUndecodable<S> {
    const NAME: &'static str = S::NAME;
}

impl<S> tower::Service<http::Request<Body>> for RefuseUndecodable<S>
where
    S: tower::Service<http::Request<Body>, Response = http::Response<Body>, Error = Infallible>,
    S::Future: Send + 'static,
{
    type Response = http::Response<Body>;
    type Error = Infallible;
    type Future = Pin<Box<dyn Future<Output = Result<http::Response<Body>, Infallible>> + Send>>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), Infallible>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, request: http::Request<Body>) -> Self::Future {
        let response = self.inner.call(request);
        let on_malformed = self.on_malformed.clone();
        Box::pin(async move {
            let response = response.await?;
            let Some(status) = Status::from_header_map(response.headers())
                .filter(|status| status.code() == Code::Internal)
            else {
                return Ok(response);
            };
            let message = format!("malformed request: {}", status.message());
            if let Some(report) = &on_malformed {
                report(&message);
            }
            Ok(malformed(message).into_http())
        })
    }
}

/// The refusal of bytes that do not decode as the expected message, on every RPC:
/// `INVALID_ARGUMENT`/`malformed`.
fn malformed(message: String) -> Status {
    refusal_status(RejectReason::Malformed, Code::InvalidArgument, message)
}
