//! Keeping strangers out: a shared bearer [`Token`] checked on every RPC but health
//! ([`AuthLayer`]), and TLS for servers ([`ServerTls`]) and clients ([`ClientTls`]), both
//! rustls through tonic.
//!
//! The token travels as gRPC metadata `authorization: Bearer <token>`. The server compares
//! SHA-256 digests of the presented and the expected token with a constant-time fold, so the
//! time a check takes says nothing about how much of a guess was right. Health
//! (`grpc.health.v1.Health`) stays open so that Kubernetes probes and load balancers need no
//! secret; everything else (the learner service, status, reflection) is refused with
//! `UNAUTHENTICATED` and the [`REJECT_REASON_KEY`](crate::grpc::REJECT_REASON_KEY) metadata
//! `unauthenticated`.

use std::fmt;
use std::future::Future;
use std::path::{Path, PathBuf};
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};

use hac_proto::RejectReason;
use sha2::{Digest, Sha256};
use tonic::metadata::{AsciiMetadataValue, MetadataValue};
use tonic::service::Interceptor;
use tonic::transport::{Certificate, ClientTlsConfig, Endpoint, Identity, ServerTlsConfig};
use tonic::{Request, Status};

use crate::grpc::REJECT_REASON_KEY;
use crate::refusal_log::{RefusalLog, SUMMARY_INTERVAL};

/// Why a token or TLS setting could not be used.
#[derive(Debug, thiserror::Error)]
pub enum SecurityError {
    #[error("reading {what} `{}`: {source}", path.display())]
    Read {
        what: &'static str,
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("the token is empty")]
    EmptyToken,
    #[error("the token holds a character other than visible ASCII (33 to 126)")]
    TokenCharacters,
    #[error("invalid TLS {what}: {message}")]
    Tls { what: &'static str, message: String },
}

/// The shared secret of a deployment. Its `Debug` output does not show it.
#[derive(Clone)]
pub struct Token {
    /// `Bearer <token>`, ready to send.
    header: AsciiMetadataValue,
    digest: [u8; 32],
}

impl fmt::Debug for Token {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("Token(..)")
    }
}

impl Token {
    /// The metadata key the token travels under.
    pub const METADATA_KEY: &'static str = "authorization";

    /// A token of visible ASCII characters (what fits in a header without escaping).
    pub fn new(secret: &str) -> Result<Self, SecurityError> {
        if secret.is_empty() {
            return Err(SecurityError::EmptyToken);
        }
        if !secret.bytes().all(|b| (33..=126).contains(&b)) {
            return Err(SecurityError::TokenCharacters);
        }
        let header = MetadataValue::try_from(format!("Bearer {secret}"))
            .map_err(|_| SecurityError::TokenCharacters)?;
        Ok(Self {
            header,
            digest: Sha256::digest(secret.as_bytes()).into(),
        })
    }

    /// The token in a file (a Kubernetes or compose secret), without surrounding whitespace.
    pub fn from_file(path: &Path) -> Result<Self, SecurityError> {
        let text = std::fs::read_to_string(path).map_err(|source| SecurityError::Read {
            what: "the token file",
            path: path.to_path_buf(),
            source,
        })?;
        Self::new(text.trim())
    }

    /// The `authorization` value clients send.
    pub fn header_value(&self) -> &AsciiMetadataValue {
        &self.header
    }

    /// True if `header` (an `authorization` value) is `Bearer <this token>`. The scheme is
    /// matched case-insensitively; the token is compared in constant time.
    pub fn accepts(&self, header: Option<&[u8]>) -> bool {
        let Some(header) = header else {
            return false;
        };
        let Some(presented) = header
            .get(..7)
            .filter(|scheme| scheme.eq_ignore_ascii_case(b"bearer "))
            .map(|_| &header[7..])
        else {
            return false;
        };
        let digest: [u8; 32] = Sha256::digest(presented).into();
        digest
            .iter()
            .zip(&self.digest)
            .fold(0u8, |diff, (a, b)| diff | (a ^ b))
            == 0
    }
}

/// Adds `authorization: Bearer <token>` to every request of a client (nothing without a
/// token).
#[derive(Debug, Clone, Default)]
pub struct BearerToken(pub Option<Token>);

impl Interceptor for BearerToken {
    fn call(&mut self, mut request: Request<()>) -> Result<Request<()>, Status> {
        if let Some(token) = &self.0 {
            request
                .metadata_mut()
                .insert(Token::METADATA_KEY, token.header_value().clone());
        }
        Ok(request)
    }
}

/// The path prefix of the one service that needs no token.
const HEALTH_PREFIX: &str = "/grpc.health.v1.Health/";

/// A tower layer for a whole tonic server: with a token, every request whose path is not
/// health must carry it, else it is answered `UNAUTHENTICATED` without reaching a service, and
/// `on_refused` is called (the learner counts it as an `unauthenticated` rejection). Without a
/// token it lets everything through. Refusals are logged like other refused input
/// (`input refused`, reason `unauthenticated`), rate limited: the first with a missing and the
/// first with a wrong token in each interval in full, the rest in a summary line per interval
/// (the learner's `unauthenticated` count has them all).
#[derive(Clone)]
pub struct AuthLayer {
    token: Option<Token>,
    on_refused: Option<Arc<dyn Fn() + Send + Sync>>,
    refusals: Arc<RefusalLog>,
}

impl Default for AuthLayer {
    fn default() -> Self {
        Self::new(None)
    }
}

impl fmt::Debug for AuthLayer {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("AuthLayer")
            .field("token", &self.token)
            .finish_non_exhaustive()
    }
}

impl AuthLayer {
    pub fn new(token: Option<Token>) -> Self {
        Self {
            token,
            on_refused: None,
            refusals: Arc::new(RefusalLog::new(SUMMARY_INTERVAL)),
        }
    }

    /// Calls `f` for every request refused.
    pub fn on_refused(mut self, f: impl Fn() + Send + Sync + 'static) -> Self {
        self.on_refused = Some(Arc::new(f));
        self
    }
}

impl<S> tower::Layer<S> for AuthLayer {
    type Service = Auth<S>;

    fn layer(&self, inner: S) -> Auth<S> {
        Auth {
            inner,
            layer: self.clone(),
        }
    }
}

/// The service [`AuthLayer`] wraps around a server's routes.
#[derive(Clone, Debug)]
pub struct Auth<S> {
    inner: S,
    layer: AuthLayer,
}

type BoxFuture<T> = Pin<Box<dyn Future<Output = T> + Send>>;

impl<S, B> tower::Service<http::Request<B>> for Auth<S>
where
    S: tower::Service<http::Request<B>, Response = http::Response<tonic::body::Body>>,
    S::Future: Send + 'static,
    S::Error: Send + 'static,
{
    type Response = http::Response<tonic::body::Body>;
    type Error = S::Error;
    type Future = BoxFuture<Result<Self::Response, S::Error>>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), S::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, request: http::Request<B>) -> Self::Future {
        if let Some(token) = &self.layer.token {
            let open = request.uri().path().starts_with(HEALTH_PREFIX);
            let presented = request
                .headers()
                .get(Token::METADATA_KEY)
                .map(|v| v.as_bytes());
            if !open && !token.accepts(presented) {
                if let Some(f) = &self.layer.on_refused {
                    f();
                }
                // No actor id can be read before the token is checked: the token's state
                // stands in for it, so a missing and a wrong token are each logged once per
                // interval.
                let token = if presented.is_some() {
                    "(wrong token)"
                } else {
                    "(missing token)"
                };
                self.layer.refusals.refused(
                    "request",
                    RejectReason::Unauthenticated,
                    token,
                    &format_args!("{token} on {}", request.uri().path()),
                );
                let mut status = Status::unauthenticated(if presented.is_some() {
                    "wrong bearer token"
                } else {
                    "missing bearer token (metadata `authorization: Bearer <token>`)"
                });
                status.metadata_mut().insert(
                    REJECT_REASON_KEY,
                    MetadataValue::from_static(RejectReason::Unauthenticated.name()),
                );
                return Box::pin(std::future::ready(Ok(status.into_http())));
            }
        }
        Box::pin(self.inner.call(request))
    }
}

/// A server's certificate chain and private key (PEM).
#[derive(Clone)]
pub struct ServerTls {
    cert_pem: Vec<u8>,
    key_pem: Vec<u8>,
}

impl fmt::Debug for ServerTls {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("ServerTls(..)")
    }
}

impl ServerTls {
    /// Checks that the PEM texts hold a certificate chain and a key rustls accepts.
    pub fn new(cert_pem: Vec<u8>, key_pem: Vec<u8>) -> Result<Self, SecurityError> {
        let tls = Self { cert_pem, key_pem };
        tonic::transport::Server::builder()
            .tls_config(tls.config())
            .map_err(|e| SecurityError::Tls {
                what: "certificate or key",
                message: error_chain(&e),
            })?;
        Ok(tls)
    }

    pub fn from_files(cert: &Path, key: &Path) -> Result<Self, SecurityError> {
        Self::new(
            read(cert, "the TLS certificate")?,
            read(key, "the TLS key")?,
        )
    }

    pub(crate) fn config(&self) -> ServerTlsConfig {
        ServerTlsConfig::new().identity(Identity::from_pem(&self.cert_pem, &self.key_pem))
    }
}

/// How a client checks the server: the CA certificate(s) to trust (PEM) and, optionally, the
/// name to expect in the server's certificate instead of the URL's host.
#[derive(Clone, Debug)]
pub struct ClientTls {
    ca_pem: Vec<u8>,
    domain: Option<String>,
}

impl ClientTls {
    /// Checks that `ca_pem` holds at least one PEM certificate (the TLS library would skip
    /// anything else silently, and every handshake would fail later).
    pub fn new(ca_pem: Vec<u8>, domain: Option<String>) -> Result<Self, SecurityError> {
        let marker = b"-----BEGIN CERTIFICATE-----";
        if !ca_pem.windows(marker.len()).any(|w| w == marker) {
            return Err(SecurityError::Tls {
                what: "CA certificate",
                message: "no PEM certificate (-----BEGIN CERTIFICATE-----) in it".into(),
            });
        }
        Ok(Self { ca_pem, domain })
    }

    pub fn from_file(ca: &Path, domain: Option<String>) -> Result<Self, SecurityError> {
        Self::new(read(ca, "the TLS CA certificate")?, domain)
    }

    fn config(&self) -> ClientTlsConfig {
        let config = ClientTlsConfig::new().ca_certificate(Certificate::from_pem(&self.ca_pem));
        match &self.domain {
            Some(domain) => config.domain_name(domain.clone()),
            None => config,
        }
    }
}

/// Why [`endpoint`] refused a URL.
#[derive(Debug, thiserror::Error)]
pub enum EndpointError {
    #[error("invalid url `{url}`: {message}")]
    InvalidUrl { url: String, message: String },
    #[error("`{0}` is https: give the CA to trust with --tls-ca")]
    HttpsWithoutCa(String),
    #[error("`{0}` is plain http but TLS is configured (--tls-ca): use https://")]
    TlsOverHttp(String),
}

/// A tonic endpoint for `url` (`http://host:port`, `https://host:port`, or a bare `host:port`,
/// which means https with `tls` and http without), with `tls` applied.
pub fn endpoint(url: &str, tls: Option<&ClientTls>) -> Result<Endpoint, EndpointError> {
    let url = if url.contains("://") {
        url.to_string()
    } else if tls.is_some() {
        format!("https://{url}")
    } else {
        format!("http://{url}")
    };
    let invalid = |message: String| EndpointError::InvalidUrl {
        url: url.clone(),
        message,
    };
    let endpoint = Endpoint::from_shared(url.clone()).map_err(|e| invalid(e.to_string()))?;
    let https = endpoint.uri().scheme_str() == Some("https");
    match (tls, https) {
        (Some(tls), true) => endpoint
            .tls_config(tls.config())
            .map_err(|e| invalid(error_chain(&e))),
        (None, false) => Ok(endpoint),
        (None, true) => Err(EndpointError::HttpsWithoutCa(url)),
        (Some(_), false) => Err(EndpointError::TlsOverHttp(url)),
    }
}

fn read(path: &Path, what: &'static str) -> Result<Vec<u8>, SecurityError> {
    std::fs::read(path).map_err(|source| SecurityError::Read {
        what,
        path: path.to_path_buf(),
        source,
    })
}

/// An error with its sources, `a: b: c` (tonic's transport errors hide the cause otherwise).
fn error_chain(e: &dyn std::error::Error) -> String {
    let mut text = e.to_string();
    let mut source = e.source();
    while let Some(cause) = source {
        text.push_str(": ");
        text.push_str(&cause.to_string());
        source = cause.source();
    }
    text
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_token_accepts_exactly_its_bearer_header() {
        let token = Token::new("s3cret-token").unwrap();
        assert_eq!(
            token.header_value().to_str().unwrap(),
            "Bearer s3cret-token"
        );
        assert!(token.accepts(Some(b"Bearer s3cret-token")));
        assert!(token.accepts(Some(b"bearer s3cret-token")));
        for wrong in [
            &b""[..],
            b"Bearer",
            b"Bearer ",
            b"Bearer s3cret-toke",
            b"Bearer s3cret-token2",
            b"Basic s3cret-token",
            b"s3cret-token",
        ] {
            assert!(
                !token.accepts(Some(wrong)),
                "{:?}",
                String::from_utf8_lossy(wrong)
            );
        }
        assert!(!token.accepts(None));
        assert_eq!(format!("{token:?}"), "Token(..)");
    }

    #[test]
    fn tokens_must_be_visible_ascii_and_files_are_trimmed() {
        assert!(matches!(Token::new(""), Err(SecurityError::EmptyToken)));
        for bad in ["with space", "tab\t", "caf\u{e9}", "new\nline"] {
            assert!(
                matches!(Token::new(bad), Err(SecurityError::TokenCharacters)),
                "{bad:?}"
            );
        }
        let dir = std::env::temp_dir().join(format!("hac-token-test-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("token");
        std::fs::write(&path, "abc123\n").unwrap();
        assert!(
            Token::from_file(&path)
                .unwrap()
                .accepts(Some(b"Bearer abc123"))
        );
        let missing = Token::from_file(&dir.join("missing")).unwrap_err();
        assert!(missing.to_string().contains("the token file"), "{missing}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn endpoints_match_the_scheme_to_the_tls_setting() {
        assert!(matches!(
            ClientTls::new(b"not a certificate".to_vec(), None),
            Err(SecurityError::Tls { .. })
        ));
        assert_eq!(
            endpoint("127.0.0.1:1", None).unwrap().uri().scheme_str(),
            Some("http")
        );
        // A bare address with TLS means https.
        let ca = rcgen::generate_simple_self_signed(vec!["localhost".to_string()])
            .unwrap()
            .cert
            .pem();
        let tls = ClientTls::new(ca.into_bytes(), Some("localhost".into())).unwrap();
        let e = endpoint("127.0.0.1:1", Some(&tls)).unwrap();
        assert_eq!(e.uri().scheme_str(), Some("https"));
        assert!(matches!(
            endpoint("https://127.0.0.1:1", None),
            Err(EndpointError::HttpsWithoutCa(_))
        ));
        assert!(matches!(
            endpoint("http://127.0.0.1:1", Some(&tls)),
            Err(EndpointError::TlsOverHttp(_))
        ));
        assert!(matches!(
            endpoint("http://bad url", None),
            Err(EndpointError::InvalidUrl { .. })
        ));
    }

    #[test]
    fn server_tls_refuses_what_is_not_a_certificate_and_key() {
        let e = ServerTls::new(b"garbage".to_vec(), b"garbage".to_vec()).unwrap_err();
        assert!(matches!(e, SecurityError::Tls { .. }), "{e}");
    }
}
