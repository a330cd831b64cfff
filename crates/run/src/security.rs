//! The security flags shared by `hac learner`, `hac actor` and `hac status` (flattened into
//! each command's arguments): where the bearer token comes from ([`TokenArgs`]), a server's
//! certificate ([`ServerTlsArgs`]) and what a client trusts ([`ClientTlsArgs`]).

use std::path::PathBuf;

use anyhow::{Context, Result};
use hac_transport::security::{ClientTls, ServerTls, Token};

/// The environment variable that may hold the token itself (a file is preferred: values in the
/// environment show in `/proc/<pid>/environ` and in `docker inspect`).
pub const TOKEN_ENV: &str = "HAC_TOKEN";

/// Where the shared bearer token comes from.
#[derive(Debug, Clone, Default, clap::Args)]
pub struct TokenArgs {
    /// File holding the bearer token (surrounding whitespace ignored); with a token, servers
    /// refuse every RPC but health without it, and clients send it. The token may also be given
    /// itself in HAC_TOKEN (the file wins if both are set) [default: no token].
    #[arg(long, env = "HAC_TOKEN_FILE", value_name = "PATH")]
    pub token_file: Option<PathBuf>,
}

impl TokenArgs {
    /// The token from `--token-file`, else from `HAC_TOKEN`, else none.
    pub fn token(&self) -> Result<Option<Token>> {
        self.token_with(std::env::var(TOKEN_ENV).ok())
    }

    fn token_with(&self, from_env: Option<String>) -> Result<Option<Token>> {
        if let Some(path) = &self.token_file {
            return Token::from_file(path)
                .map(Some)
                .context("invalid value for --token-file");
        }
        from_env
            .map(|secret| Token::new(&secret).with_context(|| format!("invalid {TOKEN_ENV}")))
            .transpose()
    }
}

/// A server's TLS certificate and key (both or neither).
#[derive(Debug, Clone, Default, clap::Args)]
pub struct ServerTlsArgs {
    /// PEM certificate chain this server presents; serves TLS only (with --tls-key).
    #[arg(long, env = "HAC_TLS_CERT", value_name = "PATH", requires = "tls_key")]
    pub tls_cert: Option<PathBuf>,
    /// PEM private key of --tls-cert.
    #[arg(long, env = "HAC_TLS_KEY", value_name = "PATH", requires = "tls_cert")]
    pub tls_key: Option<PathBuf>,
}

impl ServerTlsArgs {
    /// The certificate and key, read and checked; none without the flags.
    pub fn server_tls(&self) -> Result<Option<ServerTls>> {
        match (&self.tls_cert, &self.tls_key) {
            (Some(cert), Some(key)) => ServerTls::from_files(cert, key)
                .map(Some)
                .context("invalid value for --tls-cert/--tls-key"),
            (None, None) => Ok(None),
            _ => anyhow::bail!("--tls-cert and --tls-key go together"),
        }
    }
}

/// What a client trusts when it connects over TLS.
#[derive(Debug, Clone, Default, clap::Args)]
pub struct ClientTlsArgs {
    /// PEM CA certificate(s) the server's certificate must chain to; connects over TLS
    /// (https://) only [default: plain http].
    #[arg(long, env = "HAC_TLS_CA", value_name = "PATH")]
    pub tls_ca: Option<PathBuf>,
    /// Name to expect in the server's certificate [default: the host of the server's URL].
    #[arg(long, env = "HAC_TLS_DOMAIN", value_name = "NAME", requires = "tls_ca")]
    pub tls_domain: Option<String>,
}

impl ClientTlsArgs {
    /// The CA and domain; none without --tls-ca.
    pub fn client_tls(&self) -> Result<Option<ClientTls>> {
        self.tls_ca
            .as_ref()
            .map(|ca| ClientTls::from_file(ca, self.tls_domain.clone()))
            .transpose()
            .context("invalid value for --tls-ca")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_token_file_wins_over_the_variable_and_bad_tokens_name_their_source() {
        let dir = std::env::temp_dir().join(format!("hac-run-token-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let file = dir.join("token");
        std::fs::write(&file, "from-file\n").unwrap();
        let with_file = TokenArgs {
            token_file: Some(file),
        };
        let token = with_file
            .token_with(Some("from-env".into()))
            .unwrap()
            .unwrap();
        assert!(token.accepts(Some(b"Bearer from-file")));
        let none = TokenArgs::default();
        let token = none.token_with(Some("from-env".into())).unwrap().unwrap();
        assert!(token.accepts(Some(b"Bearer from-env")));
        assert!(none.token_with(None).unwrap().is_none());
        let e = none.token_with(Some(String::new())).unwrap_err();
        assert!(format!("{e:#}").contains("HAC_TOKEN"), "{e:#}");
        let missing = TokenArgs {
            token_file: Some(dir.join("missing")),
        };
        let e = missing.token_with(None).unwrap_err();
        assert!(format!("{e:#}").contains("--token-file"), "{e:#}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
