//! How the project's clients reach an executive: plaintext or TLS, with the
//! CA to trust and, for mutual TLS, the client's own certificate; and how
//! they tell a person what went wrong.

use std::time::Duration;

use tonic::transport::{Certificate, ClientTlsConfig, Endpoint, Identity};

/// TLS settings of a client.
#[derive(Clone, Default)]
pub struct ClientTls {
    /// PEM CA certificates to trust; the system's roots when `None`.
    pub ca_pem: Option<Vec<u8>>,
    /// PEM certificate and key to present (mutual TLS).
    pub identity: Option<(Vec<u8>, Vec<u8>)>,
}

impl std::fmt::Debug for ClientTls {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ClientTls")
            .field("ca", &self.ca_pem.is_some())
            .field("identity", &self.identity.is_some())
            .finish()
    }
}

impl ClientTls {
    /// Reads the PEM files named by `--tls-ca`, `--tls-cert` and `--tls-key`.
    pub fn from_files(
        ca: Option<&std::path::Path>,
        cert: Option<&std::path::Path>,
        key: Option<&std::path::Path>,
    ) -> std::io::Result<Self> {
        let read = crate::files::read_pem;
        let identity = match (cert, key) {
            (Some(cert), Some(key)) => Some((read(cert)?, read(key)?)),
            (None, None) => None,
            _ => {
                return Err(std::io::Error::new(
                    std::io::ErrorKind::InvalidInput,
                    "a client certificate needs both --tls-cert and --tls-key",
                ));
            }
        };
        Ok(Self { ca_pem: ca.map(read).transpose()?, identity })
    }
}

/// The header in which the executive says how long to wait before
/// retrying a call it refused to shed load (gRPC's own name for it).
pub const RETRY_PUSHBACK_METADATA: &str = "grpc-retry-pushback-ms";

/// How long the executive asked to wait before retrying `status`'s call
/// (at most 10 s), if it did.
pub fn retry_pushback(status: &tonic::Status) -> Option<Duration> {
    let ms = status.metadata().get(RETRY_PUSHBACK_METADATA)?.to_str().ok()?.parse::<u64>().ok()?;
    Some(Duration::from_millis(ms.min(10_000)))
}

/// A refused or failed call on one line, for a person: the code, the
/// executive's message, the transport's root cause when the message does
/// not say it (refused, reset, a certificate's fault), and what to change
/// when the cause is a mismatch the user made (TLS against plaintext, a
/// certificate that cannot serve).
pub fn status_line(status: &tonic::Status) -> String {
    let mut line = format!("{:?}", status.code());
    if !status.message().is_empty() {
        line.push_str(": ");
        line.push_str(status.message());
    }
    let root = std::iter::successors(std::error::Error::source(status), |e| e.source()).last();
    if let Some(root) = root.map(ToString::to_string).filter(|r| !status.message().contains(r.as_str())) {
        line.push_str(": ");
        line.push_str(&root);
    }
    if let Some(hint) = mismatch_hint(&line) {
        line.push_str(" (");
        line.push_str(hint);
        line.push(')');
    }
    line
}

/// What the user should change, for the failures whose words do not say it.
fn mismatch_hint(failure: &str) -> Option<&'static str> {
    const NOT_OUR_CA: &str = "the executive's certificate is not signed by the CA given with --tls-ca";
    const PLAINTEXT_TO_TLS: &str = "if the executive there serves TLS, use https://";
    const NOT_ITS_NAME: &str = "the executive's certificate does not name the host of the URL";
    const HINTS: [(&str, &str); 8] = [
        // rustls read a plaintext HTTP/2 frame where a TLS record belonged.
        ("InvalidContentType", "the executive there does not serve TLS: use http://"),
        // A TLS server closes on a plaintext preface, before our writes end
        // (most often) or after (h2 then reads its alert as a frame).
        ("stream closed because of a broken pipe", PLAINTEXT_TO_TLS),
        ("frame with invalid size", PLAINTEXT_TO_TLS),
        (
            "CaUsedAsEndEntity",
            "the executive's certificate is a CA's (basicConstraints CA:TRUE): serve a certificate the CA signed",
        ),
        ("UnknownIssuer", NOT_OUR_CA),
        // A CA of the same name as the issuer, but another key.
        ("BadSignature", NOT_OUR_CA),
        // rustls writes the error with the names in it, and without them as its variant's name.
        ("not valid for name", NOT_ITS_NAME),
        ("NotValidForName", NOT_ITS_NAME),
    ];
    HINTS.iter().find(|(words, _)| failure.contains(words)).map(|(_, hint)| *hint)
}

/// Why an executive's address cannot be dialled.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BadAddress(String);

impl std::fmt::Display for BadAddress {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for BadAddress {}

impl BadAddress {
    /// A problem that concerns no one address.
    pub fn from_problem(problem: &str) -> Self {
        Self(problem.to_owned())
    }
}

impl From<tonic::transport::Error> for BadAddress {
    fn from(e: tonic::transport::Error) -> Self {
        Self(e.to_string())
    }
}

/// Checks what the transport would take silently: `htp://host` dialled
/// as if it were `http://`, `host:99999` dialled on port 80.
pub fn check_url(url: &str) -> Result<(), BadAddress> {
    let bad = |problem: &str| Err(BadAddress(format!("`{}` {problem}", url.escape_debug())));
    let Ok(uri) = url.parse::<tonic::codegen::http::Uri>() else {
        return bad("is not a URL; give http://HOST:PORT or https://HOST:PORT");
    };
    if !matches!(uri.scheme_str(), Some("http" | "https")) {
        return bad("must start with http:// or https://");
    }
    let Some(authority) = uri.authority().filter(|a| !a.host().is_empty()) else {
        return bad("names no host");
    };
    // The port is what follows the last colon past the host (an IPv6
    // host is in brackets); the URI parser forgets one it cannot read.
    let after_host = authority.as_str().rsplit_once(']').map_or(authority.as_str(), |(_, rest)| rest);
    if after_host.contains(':') && authority.port_u16().is_none_or(|port| port == 0) {
        return bad("has a port outside 1 to 65535");
    }
    Ok(())
}

/// An endpoint for `url`: TLS when the URL is `https://` or `tls` is
/// given (then the URL must be `https://`).
pub fn endpoint(url: &str, tls: Option<&ClientTls>) -> Result<Endpoint, BadAddress> {
    check_url(url)?;
    let endpoint = Endpoint::from_shared(url.to_owned())?.connect_timeout(Duration::from_secs(5));
    if tls.is_none() && !url.starts_with("https://") {
        return Ok(endpoint);
    }
    let mut config = ClientTlsConfig::new();
    match tls.and_then(|t| t.ca_pem.as_ref()) {
        Some(ca) => config = config.ca_certificate(Certificate::from_pem(ca)),
        None => config = config.with_native_roots(),
    }
    if let Some((cert, key)) = tls.and_then(|t| t.identity.as_ref()) {
        config = config.identity(Identity::from_pem(cert, key));
    }
    Ok(endpoint.tls_config(config)?)
}

/// A warning to print when a bearer token would cross a network in
/// plaintext: a token, an `http://` URL, and a host that is not loopback.
pub fn plaintext_token_warning(url: &str, token: Option<&str>) -> Option<String> {
    token.filter(|t| !t.trim().is_empty())?;
    let rest = url.strip_prefix("http://")?;
    let host = rest.split(['/', '?']).next().unwrap_or("");
    let host = match host.strip_prefix('[') {
        Some(v6) => v6.split(']').next().unwrap_or(""),
        None => host.rsplit_once(':').map_or(host, |(h, _)| h),
    };
    let loopback =
        host.eq_ignore_ascii_case("localhost") || host.parse::<std::net::IpAddr>().is_ok_and(|ip| ip.is_loopback());
    (!loopback)
        .then(|| format!("the bearer token will cross the network to {host} in plaintext: use https:// and --tls-ca"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tokens_over_plaintext_to_other_hosts_are_flagged() {
        let token = Some("t0ken");
        assert!(plaintext_token_warning("http://10.0.0.5:50051", token).is_some());
        assert!(plaintext_token_warning("http://robots.example:50051/", token).is_some());
        assert!(plaintext_token_warning("http://127.0.0.1:50051", token).is_none());
        assert!(plaintext_token_warning("http://[::1]:50051", token).is_none());
        assert!(plaintext_token_warning("http://localhost:50051", token).is_none());
        assert!(plaintext_token_warning("https://10.0.0.5:50051", token).is_none());
        assert!(plaintext_token_warning("http://10.0.0.5:50051", None).is_none());
    }

    /// What the transport would dial somewhere else than meant is refused
    /// with the address and what is wrong with it.
    #[test]
    fn addresses_the_transport_would_misread_are_refused() {
        for good in ["http://127.0.0.1:50051", "https://robots.example", "http://[::1]:1", "http://h:65535/"] {
            assert_eq!(check_url(good), Ok(()), "{good}");
        }
        let problem = |url: &str| check_url(url).unwrap_err().to_string();
        assert_eq!(problem("htp://x"), "`htp://x` must start with http:// or https://");
        assert_eq!(problem("127.0.0.1:50051"), "`127.0.0.1:50051` must start with http:// or https://");
        assert_eq!(problem("http://127.0.0.1:99999"), "`http://127.0.0.1:99999` has a port outside 1 to 65535");
        assert_eq!(problem("http://h:0"), "`http://h:0` has a port outside 1 to 65535");
        assert_eq!(problem("http://[::1]:70000"), "`http://[::1]:70000` has a port outside 1 to 65535");
        assert!(problem("http://").contains("is not a URL"), "{}", problem("http://"));
        assert_eq!(
            problem("http://a\u{1}b"),
            "`http://a\\u{1}b` is not a URL; give http://HOST:PORT or https://HOST:PORT"
        );
        assert!(endpoint("htp://x", None).is_err());
    }

    /// The words rustls 0.23 writes for a certificate issued to another
    /// host, with and without the names, both get the hint (the hint once
    /// read "NotValidForName" only, which the first never contains).
    #[test]
    fn a_certificate_for_another_host_is_named_as_such() {
        let with_names = "invalid peer certificate: certificate not valid for name \"127.0.0.1\"; \
                          certificate is only valid for DnsName(\"example.org\")";
        for failure in [with_names, "invalid peer certificate: NotValidForName"] {
            let hint = mismatch_hint(failure);
            assert_eq!(hint, Some("the executive's certificate does not name the host of the URL"), "{failure}");
        }
        assert_eq!(mismatch_hint("tcp connect error: Connection refused (os error 111)"), None);
    }

    /// The hint comes from the network: anything but a number of
    /// milliseconds is no hint, and a huge one is held to 10 s.
    #[test]
    fn a_retry_hint_is_read_only_when_it_is_a_sane_number() {
        let hinted = |value: &str| {
            let mut status = tonic::Status::resource_exhausted("busy");
            status.metadata_mut().insert(RETRY_PUSHBACK_METADATA, value.parse().unwrap());
            retry_pushback(&status)
        };
        assert_eq!(retry_pushback(&tonic::Status::resource_exhausted("busy")), None);
        assert_eq!(hinted("100"), Some(Duration::from_millis(100)));
        assert_eq!(hinted("18446744073709551615"), Some(Duration::from_secs(10)));
        for garbage in ["", "-5", "1e3", "abc", "99999999999999999999999"] {
            assert_eq!(hinted(garbage), None, "{garbage:?}");
        }
    }
}
