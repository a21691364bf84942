//! The `exploration.v1` API, generated from `proto/exploration/v1/exploration.proto`.
//!
//! Only types, clients and servers live here; the executive converts them into
//! its domain types at the service boundary.

#![allow(missing_docs, clippy::all, missing_debug_implementations)]

/// Types, clients and servers of package `exploration.v1`.
pub mod v1 {
    tonic::include_proto!("exploration.v1");

    /// The encoded `FileDescriptorSet`, for gRPC server reflection.
    pub const FILE_DESCRIPTOR_SET: &[u8] = tonic::include_file_descriptor_set!("exploration_v1_descriptor");
}

/// Largest message a client or the executive decodes: a map update with big
/// patches, a whole 25-million-cell map with its frontier.
pub const MAX_MESSAGE_BYTES: usize = 64 * 1024 * 1024;

/// Per-cell labels as run-length pairs: (label, run length), each a
/// little-endian `u32`, row-major. The wire form of
/// `SetGivenSegmentationRequest.label_runs`, and how the store keeps labels.
pub mod label_runs {
    /// The runs of `labels`.
    pub fn encode(labels: &[u32]) -> Vec<u8> {
        let mut out = Vec::new();
        let mut rest = labels;
        while let Some(&label) = rest.first() {
            let run = rest.iter().take_while(|&&l| l == label).count().min(u32::MAX as usize);
            out.extend_from_slice(&label.to_le_bytes());
            out.extend_from_slice(&(run as u32).to_le_bytes());
            rest = &rest[run..];
        }
        out
    }

    /// The labels of `len` cells. Runs that are not whole pairs, or that
    /// add up to anything but `len`, are refused before anything is
    /// allocated for them; the error says what they hold.
    pub fn decode(bytes: &[u8], len: usize) -> Result<Vec<u32>, String> {
        if !bytes.len().is_multiple_of(8) {
            return Err(format!("hold {} bytes, not (label, run length) pairs of 8", bytes.len()));
        }
        let pairs = || {
            bytes.chunks_exact(8).map(|p| {
                (u32::from_le_bytes([p[0], p[1], p[2], p[3]]), u32::from_le_bytes([p[4], p[5], p[6], p[7]]) as usize)
            })
        };
        let total: u64 = pairs().map(|(_, run)| run as u64).sum();
        if total != len as u64 {
            return Err(format!("cover {total} cells, not the map's {len}"));
        }
        let mut labels = Vec::with_capacity(len);
        for (label, run) in pairs() {
            labels.extend(std::iter::repeat_n(label, run));
        }
        Ok(labels)
    }
}

/// Prost's codec, except that a message that is not valid protobuf is
/// INVALID_ARGUMENT (the sender's error), not INTERNAL.
pub mod codec {
    use tonic::Status;
    use tonic::codec::{BufferSettings, DecodeBuf, Decoder};
    use tonic_prost::{ProstCodec, ProstDecoder, ProstEncoder};

    /// See the module.
    #[derive(Debug, Clone, Default)]
    pub struct Codec<T, U>(ProstCodec<T, U>);

    impl<T, U> tonic::codec::Codec for Codec<T, U>
    where
        T: prost::Message + Send + 'static,
        U: prost::Message + Default + Send + 'static,
    {
        type Encode = T;
        type Decode = U;
        type Encoder = ProstEncoder<T>;
        type Decoder = StrictDecoder<U>;

        fn encoder(&mut self) -> Self::Encoder {
            self.0.encoder()
        }

        fn decoder(&mut self) -> Self::Decoder {
            StrictDecoder(self.0.decoder())
        }
    }

    /// See the module.
    #[derive(Debug, Clone)]
    pub struct StrictDecoder<U>(ProstDecoder<U>);

    impl<U: prost::Message + Default> Decoder for StrictDecoder<U> {
        type Item = U;
        type Error = Status;

        fn decode(&mut self, buf: &mut DecodeBuf<'_>) -> Result<Option<U>, Status> {
            self.0.decode(buf).map_err(|status| {
                Status::invalid_argument(format!(
                    "the message is not a valid protobuf encoding of the call's request: {}",
                    status.message()
                ))
            })
        }

        fn buffer_settings(&self) -> BufferSettings {
            self.0.buffer_settings()
        }
    }
}

/// Client-side bearer authentication: adds `authorization: Bearer <token>`
/// to every request, or nothing without a token. Use with
/// `XClient::with_interceptor(channel, Bearer::new(token)?)`.
#[derive(Debug, Clone, Default)]
pub struct Bearer(Option<tonic::metadata::MetadataValue<tonic::metadata::Ascii>>);

impl Bearer {
    /// A bearer for `token`; none when `None` or blank.
    pub fn new(token: Option<&str>) -> Result<Self, tonic::metadata::errors::InvalidMetadataValue> {
        match token.map(str::trim).filter(|t| !t.is_empty()) {
            Some(t) => Ok(Self(Some(format!("Bearer {t}").parse()?))),
            None => Ok(Self(None)),
        }
    }
}

impl tonic::service::Interceptor for Bearer {
    fn call(&mut self, mut request: tonic::Request<()>) -> Result<tonic::Request<()>, tonic::Status> {
        if let Some(value) = &self.0 {
            request.metadata_mut().insert("authorization", value.clone());
        }
        Ok(request)
    }
}

/// How the project's clients reach an executive: plaintext or TLS, with the
/// CA to trust and, for mutual TLS, the client's own certificate.
pub mod files;
pub mod replicas;

pub mod client {
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
        (!loopback).then(|| {
            format!("the bearer token will cross the network to {host} in plaintext: use https:// and --tls-ca")
        })
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
}
