//! Who may talk to a server and how much: loopback by default, TLS (rustls) and a bearer token
//! across machines, and message-size limits on every server and client.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use serde::{Deserialize, Serialize};
use tonic::metadata::MetadataValue;
use tonic::service::Interceptor;
use tonic::transport::{Certificate, Channel, ClientTlsConfig, Endpoint, Identity, Server, ServerTlsConfig};
use tonic::{Request, Status};

/// Largest gRPC message accepted or sent (rollouts travel in parts of [`PART_BYTES`]).
pub const MAX_MESSAGE_BYTES: usize = 4 * PART_BYTES;
/// Size of the parts a rollout or weights blob is split into.
pub const PART_BYTES: usize = 1 << 20;
/// Largest reassembled rollout chunk or weights blob (a 96-env × 1024-step paper rollout is ~20 MiB).
pub const MAX_PAYLOAD_BYTES: usize = 256 << 20;
/// Longest a request handler may run: a whole rollout upload (a 30 MiB vision rollout takes 3 s
/// at 10 MB/s). Streams the server answers (weights, Fly) are not cut by it: their handlers
/// return at once and the stream goes on.
pub const REQUEST_TIMEOUT: Duration = Duration::from_secs(60);
/// Requests one connection may have open at once, and HTTP/2 streams: an actor uses two or three,
/// a client of `Fly` one; the bound keeps one connection from taking every handler.
pub const STREAMS_PER_CONNECTION: u32 = 16;
/// HTTP/2 flow-control windows: several MiB, so streaming 1 MiB parts does not stall.
const WINDOW_BYTES: u32 = 8 << 20;

/// Network security settings of a process (`[network]` in the run config).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct NetworkConfig {
    /// File holding the bearer token every request must carry (none: no token required).
    pub token_file: Option<PathBuf>,
    /// PEM certificate chain of this server (enables TLS on servers).
    pub tls_cert: Option<PathBuf>,
    /// PEM private key of `tls_cert`.
    pub tls_key: Option<PathBuf>,
    /// PEM CA certificate clients trust (enables TLS on clients).
    pub tls_ca: Option<PathBuf>,
    /// Server name clients expect in the certificate (default: the host of the address).
    pub tls_domain: Option<String>,
}

/// A security setting that cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum SecurityError {
    /// A file could not be read.
    #[error("{field} = {path}: {source}")]
    Read {
        /// Config field naming the file.
        field: &'static str,
        /// The file.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// An inconsistent or invalid setting.
    #[error("network: {0}")]
    Invalid(String),
    /// TLS or transport set-up failed.
    #[error("network: {0}")]
    Transport(#[from] tonic::transport::Error),
}

/// Loaded security material.
#[derive(Clone, Debug, Default)]
pub struct Security {
    token: Option<Arc<str>>,
    server_identity: Option<(Vec<u8>, Vec<u8>)>,
    client_ca: Option<Vec<u8>>,
    domain: Option<String>,
}

fn read(field: &'static str, path: &Path) -> Result<Vec<u8>, SecurityError> {
    std::fs::read(path).map_err(|source| SecurityError::Read { field, path: path.to_path_buf(), source })
}

impl Security {
    /// Reads the files a config names.
    pub fn load(config: &NetworkConfig) -> Result<Self, SecurityError> {
        let token = match &config.token_file {
            Some(path) => {
                let text = String::from_utf8(read("network.token_file", path)?)
                    .map_err(|_| SecurityError::Invalid(format!("network.token_file = {}: not UTF-8 text", path.display())))?;
                let token = text.trim();
                if token.is_empty() || !token.chars().all(|c| c.is_ascii_graphic()) {
                    return Err(SecurityError::Invalid(format!(
                        "network.token_file = {}: the token must be one line of printable ASCII",
                        path.display()
                    )));
                }
                Some(Arc::from(token))
            }
            None => None,
        };
        let server_identity = match (&config.tls_cert, &config.tls_key) {
            (Some(cert), Some(key)) => Some((read("network.tls_cert", cert)?, read("network.tls_key", key)?)),
            (None, None) => None,
            _ => return Err(SecurityError::Invalid("tls_cert and tls_key go together".into())),
        };
        let client_ca = config.tls_ca.as_deref().map(|p| read("network.tls_ca", p)).transpose()?;
        Ok(Self { token, server_identity, client_ca, domain: config.tls_domain.clone() })
    }

    /// Refuses to listen beyond loopback without TLS and a token: rollouts and weights are
    /// not for the whole network to read or forge.
    pub fn check_listen(&self, addr: &SocketAddr) -> Result<(), SecurityError> {
        if !addr.ip().is_loopback() && (self.server_identity.is_none() || self.token.is_none()) {
            return Err(SecurityError::Invalid(format!(
                "listening on {addr} (beyond loopback) needs network.tls_cert, network.tls_key and network.token_file"
            )));
        }
        Ok(())
    }

    /// A server builder with TLS (when configured), large flow-control windows, a request
    /// timeout and a bound on each connection's concurrent streams.
    pub fn server(&self) -> Result<Server, SecurityError> {
        let mut server = Server::builder()
            .initial_stream_window_size(WINDOW_BYTES)
            .initial_connection_window_size(WINDOW_BYTES)
            .http2_keepalive_interval(Some(Duration::from_secs(10)))
            .http2_keepalive_timeout(Some(Duration::from_secs(20)))
            .timeout(REQUEST_TIMEOUT)
            .max_concurrent_streams(STREAMS_PER_CONNECTION)
            .concurrency_limit_per_connection(STREAMS_PER_CONNECTION as usize);
        if let Some((cert, key)) = &self.server_identity {
            let tls = ServerTlsConfig::new().identity(Identity::from_pem(cert, key)).timeout(crate::listener::HANDSHAKE_TIMEOUT);
            server = server.tls_config(tls)?;
        }
        Ok(server)
    }

    /// The token of actor `actor` under this run's token: what that actor's machine holds in
    /// its `network.token_file` instead of the run's (`dronerace token --actor NAME`). It
    /// proves the actor's name to the learner and the task controller, and nothing else.
    pub fn actor_token(&self, actor: &str) -> Result<String, SecurityError> {
        crate::link::check_actor_name(actor).map_err(|e| SecurityError::Invalid(e.to_string()))?;
        let token =
            self.token.as_deref().ok_or_else(|| SecurityError::Invalid("an actor token is made from network.token_file: set it".into()))?;
        if token.starts_with(ACTOR_TOKEN_PREFIX) {
            return Err(SecurityError::Invalid("network.token_file holds an actor's token; actor tokens are made from the run's".into()));
        }
        let mac = hmac::Mac::finalize(actor_mac(token, actor)).into_bytes();
        Ok(format!("{ACTOR_TOKEN_PREFIX}{actor}:{}", mac.iter().map(|b| format!("{b:02x}")).collect::<String>()))
    }

    /// The actor this process's token belongs to, if it is an actor's token: that process must
    /// run under that name, or every call it makes is refused.
    pub fn token_actor(&self) -> Option<&str> {
        self.token.as_deref()?.strip_prefix(ACTOR_TOKEN_PREFIX)?.rsplit_once(':').map(|(actor, _)| actor)
    }

    /// The interceptor servers wrap their services in.
    pub fn token_check(&self) -> TokenCheck {
        TokenCheck { token: self.token.clone() }
    }

    /// A lazily connecting channel to `url` (`http://` or, with `tls_ca`, `https://`). A token
    /// without `tls_ca` goes to loopback addresses only: anywhere else it would cross the
    /// network in plaintext.
    pub fn channel(&self, url: &str) -> Result<Channel, SecurityError> {
        let endpoint = Endpoint::from_shared(url.to_string()).map_err(|e| SecurityError::Invalid(format!("address {url:?}: {e}")))?;
        if self.token.is_some() && self.client_ca.is_none() && !is_loopback(endpoint.uri()) {
            return Err(SecurityError::Invalid(format!(
                "network.token_file is set without network.tls_ca: the token would travel in plaintext to {url}; \
                 give network.tls_ca (the CA that signed the server's certificate) or connect over loopback"
            )));
        }
        let mut endpoint = endpoint
            .connect_timeout(Duration::from_secs(5))
            .initial_stream_window_size(WINDOW_BYTES)
            .initial_connection_window_size(WINDOW_BYTES)
            .http2_keep_alive_interval(Duration::from_secs(10))
            .keep_alive_timeout(Duration::from_secs(20));
        if let Some(ca) = &self.client_ca {
            let mut tls = ClientTlsConfig::new().ca_certificate(Certificate::from_pem(ca));
            if let Some(domain) = &self.domain {
                tls = tls.domain_name(domain.clone());
            }
            endpoint = endpoint.tls_config(tls)?;
        }
        Ok(endpoint.connect_lazy())
    }

    /// The interceptor clients wrap their channel in (adds the bearer token).
    #[allow(clippy::expect_used, reason = "Security::load admits only printable ASCII tokens")]
    pub fn token_header(&self) -> AddToken {
        AddToken { header: self.token.as_ref().map(|t| format!("Bearer {t}").parse().expect("printable ASCII token")) }
    }
}

/// The URI names this machine: `localhost` or a loopback IP.
fn is_loopback(uri: &tonic::codegen::http::Uri) -> bool {
    match uri.host() {
        Some(host) => {
            let host = host.trim_start_matches('[').trim_end_matches(']');
            host.eq_ignore_ascii_case("localhost") || host.parse::<std::net::IpAddr>().is_ok_and(|ip| ip.is_loopback())
        }
        None => false,
    }
}

/// Whether `given` is `token`, in time that depends on `given`'s length only: neither where the
/// two differ nor the token's length shows in it.
fn same_token(given: &[u8], token: &[u8]) -> bool {
    if token.is_empty() {
        return false;
    }
    let mut diff = usize::from(given.len() != token.len());
    for (i, &g) in given.iter().enumerate() {
        // Cycling through the token keeps every comparison the same work whatever its length.
        diff |= usize::from(g ^ token[i % token.len()]);
    }
    std::hint::black_box(diff) == 0
}

/// Who a request comes from, as its bearer token proves: [`TokenCheck`] puts it in the
/// request's extensions, and a handler that takes an actor's name checks it with
/// [`Caller::may_speak_for`].
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Caller {
    /// The run's own token (or a server with no token, on loopback): may speak for any actor.
    Operator,
    /// An actor's own token ([`Security::actor_token`]): may speak for that actor only, so one
    /// compromised actor machine cannot register, report or send rollouts as another.
    Actor(String),
}

impl Caller {
    /// Who sent `request` (a request that passed no [`TokenCheck`] is the operator's: such a
    /// server has no token and listens on loopback only).
    pub fn of<T>(request: &Request<T>) -> Caller {
        request.extensions().get::<Caller>().cloned().unwrap_or(Caller::Operator)
    }

    /// PERMISSION_DENIED unless this caller may speak for `actor` (the name a message carries).
    pub fn may_speak_for(&self, actor: &str) -> Result<(), Status> {
        match self {
            Caller::Actor(me) if me != actor => Err(crate::refusal::status(
                tonic::Code::PermissionDenied,
                format!("this token is actor {me:?}'s: it cannot speak for actor {actor:?}"),
            )),
            _ => Ok(()),
        }
    }
}

/// What an actor's token starts with: `actor:<name>:<64 hex digits of the MAC>`.
const ACTOR_TOKEN_PREFIX: &str = "actor:";

/// The MAC of an actor's name under the run's token (the key): HMAC-SHA-256, domain-separated.
fn actor_mac(run_token: &str, actor: &str) -> hmac::Hmac<sha2::Sha256> {
    use hmac::Mac;
    #[allow(clippy::expect_used, reason = "HMAC takes a key of any length")]
    let mut mac = hmac::Hmac::<sha2::Sha256>::new_from_slice(run_token.as_bytes()).expect("HMAC takes a key of any length");
    mac.update(b"dronerace actor token v1\0");
    mac.update(actor.as_bytes());
    mac
}

/// Server side: UNAUTHENTICATED unless the request carries `authorization: Bearer <token>` with
/// the run's token ([`Caller::Operator`]) or an actor's token made from it ([`Caller::Actor`]).
#[derive(Clone, Debug)]
pub struct TokenCheck {
    token: Option<Arc<str>>,
}

impl TokenCheck {
    /// Who `given` (the bearer token) proves the caller to be, if anyone.
    fn caller(&self, given: &str, token: &str) -> Option<Caller> {
        if same_token(given.as_bytes(), token.as_bytes()) {
            return Some(Caller::Operator);
        }
        let (actor, mac) = given.strip_prefix(ACTOR_TOKEN_PREFIX)?.rsplit_once(':')?;
        let mac = decode_hex(mac)?;
        crate::link::check_actor_name(actor).ok()?;
        // Constant-time comparison of the MAC (hmac's verify).
        hmac::Mac::verify_slice(actor_mac(token, actor), &mac).ok()?;
        Some(Caller::Actor(actor.to_owned()))
    }
}

/// Lower-case hex of 32 bytes, or `None`.
fn decode_hex(hex: &str) -> Option<Vec<u8>> {
    if hex.len() != 64 {
        return None;
    }
    (0..hex.len()).step_by(2).map(|i| u8::from_str_radix(hex.get(i..i + 2)?, 16).ok()).collect()
}

impl Interceptor for TokenCheck {
    fn call(&mut self, mut request: Request<()>) -> Result<Request<()>, Status> {
        let Some(token) = &self.token else { return Ok(request) };
        let given = request.metadata().get("authorization").and_then(|v| v.to_str().ok());
        let Some(given) = given.and_then(|v| v.strip_prefix("Bearer ")) else {
            return Err(Status::unauthenticated("missing bearer token (authorization: Bearer <token>)"));
        };
        match self.caller(given, token) {
            Some(caller) => {
                request.extensions_mut().insert(caller);
                Ok(request)
            }
            None => Err(Status::unauthenticated("wrong bearer token")),
        }
    }
}

/// Client side: adds the bearer token to every request.
#[derive(Clone, Debug)]
pub struct AddToken {
    header: Option<MetadataValue<tonic::metadata::Ascii>>,
}

impl Interceptor for AddToken {
    fn call(&mut self, mut request: Request<()>) -> Result<Request<()>, Status> {
        if let Some(h) = &self.header {
            request.metadata_mut().insert("authorization", h.clone());
        }
        Ok(request)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn with_token(token: Option<&str>) -> Request<()> {
        let mut r = Request::new(());
        if let Some(t) = token {
            r.metadata_mut().insert("authorization", t.parse().unwrap());
        }
        r
    }

    #[test]
    fn token_check_refuses_missing_and_wrong_tokens() {
        let mut check = TokenCheck { token: Some(Arc::from("s3cret")) };
        assert!(check.call(with_token(Some("Bearer s3cret"))).is_ok());
        // Wrong, missing, without the scheme, longer, shorter, and a repetition of the token (the
        // comparison cycles through the token, so it must still see the length differ).
        for bad in [
            None,
            Some("Bearer s3creT"),
            Some("s3cret"),
            Some("Bearer s3cret2"),
            Some("Bearer s3cre"),
            Some("Bearer s3crets3cret"),
            Some("Bearer "),
        ] {
            assert_eq!(check.call(with_token(bad)).unwrap_err().code(), tonic::Code::Unauthenticated, "{bad:?}");
        }
        let mut open = TokenCheck { token: None };
        assert!(open.call(with_token(None)).is_ok());
    }

    #[test]
    fn an_actor_token_proves_its_name_and_only_its_name() {
        let run = Security { token: Some(Arc::from("s3cret")), ..Security::default() };
        let mut check = run.token_check();
        let token = run.actor_token("actor-1").unwrap();
        let caller = |check: &mut TokenCheck, t: &str| {
            check.call(with_token(Some(&format!("Bearer {t}")))).map(|r| r.extensions().get::<Caller>().cloned())
        };
        assert_eq!(caller(&mut check, &token).unwrap(), Some(Caller::Actor("actor-1".into())));
        assert_eq!(caller(&mut check, "s3cret").unwrap(), Some(Caller::Operator));
        // Another name with this MAC, a changed MAC, and one made under another run's token.
        let other = Security { token: Some(Arc::from("other")), ..Security::default() }.actor_token("actor-1").unwrap();
        let flipped = format!("{}{}", &token[..token.len() - 1], if token.ends_with('0') { '1' } else { '0' });
        for forged in [token.replace("actor-1", "actor-2"), flipped, other, "actor:actor-1:zz".into(), "actor:".into()] {
            assert_eq!(caller(&mut check, &forged).unwrap_err().code(), tonic::Code::Unauthenticated, "{forged}");
        }
        // What the holder may do with it.
        let me = Caller::Actor("actor-1".into());
        assert!(me.may_speak_for("actor-1").is_ok());
        assert_eq!(me.may_speak_for("actor-2").unwrap_err().code(), tonic::Code::PermissionDenied);
        assert!(Caller::Operator.may_speak_for("actor-2").is_ok());
        // An actor's machine holds its own token: it knows whose it is, and cannot mint others.
        let holder = Security { token: Some(Arc::from(token.as_str())), ..Security::default() };
        assert_eq!(holder.token_actor(), Some("actor-1"));
        assert!(holder.actor_token("actor-2").is_err());
        assert_eq!(run.token_actor(), None);
    }

    #[test]
    fn a_token_without_a_ca_goes_to_loopback_only() {
        let token_only = Security { token: Some(Arc::from("s3cret")), ..Security::default() };
        let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
        let _guard = rt.enter();
        for local in ["http://127.0.0.1:50051", "http://localhost:50051", "http://[::1]:50051"] {
            assert!(token_only.channel(local).is_ok(), "{local}");
        }
        for remote in ["http://learner:50052", "http://10.0.0.7:50052", "https://learner.example:50052"] {
            let e = token_only.channel(remote).unwrap_err().to_string();
            assert!(e.contains("plaintext") && e.contains("network.tls_ca"), "{remote}: {e}");
        }
        assert!(Security::default().channel("http://learner:50052").is_ok(), "no token, nothing to leak");
    }

    #[test]
    fn listening_beyond_loopback_needs_tls_and_a_token() {
        let plain = Security::default();
        assert!(plain.check_listen(&"127.0.0.1:1".parse().unwrap()).is_ok());
        let e = plain.check_listen(&"0.0.0.0:1".parse().unwrap()).unwrap_err().to_string();
        assert!(e.contains("tls_cert") && e.contains("token_file"), "{e}");
    }
}
