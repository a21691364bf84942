//! A channel to executive replicas that share one database, following each
//! mission to the replica that holds it.
//!
//! A replica that does not hold a request's mission answers UNAVAILABLE and
//! names the holder's address in [`OWNER_METADATA`]; [`Replicas`] sends the
//! next calls there, so that the client's retry of an UNAVAILABLE call (the
//! project's clients retry them) reaches the owner. When the replica it
//! talks to cannot be reached, or says UNAVAILABLE without naming another,
//! it moves on to the next address it was given. A call answered with an
//! owner's address is sent on to it at once (the call was not carried out:
//! the replica that answered does not hold the mission). A mission whose owner died
//! is answered by whichever replica claims it once the owner's lease has run
//! out; until then the other replicas name the dead owner, and the client
//! goes round the list, retrying, until one of them holds the mission.

use std::collections::HashMap;
use std::future::Future;
use std::pin::Pin;
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};

use tonic::body::Body;
use tonic::codegen::{Service, http};
use tonic::transport::{Channel, Endpoint};

use crate::client::{BadAddress, ClientTls};

/// The response metadata naming the replica that holds a mission.
pub const OWNER_METADATA: &str = "exploration-owner";

/// gRPC's UNAVAILABLE, as `grpc-status` carries it.
const UNAVAILABLE: &str = "14";

/// Channels to a list of replicas (or one executive), the calls going to
/// the one that answered last, or that was named as a mission's owner.
#[derive(Clone)]
pub struct Replicas {
    shared: Arc<Shared>,
}

impl std::fmt::Debug for Replicas {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Replicas").field("given", &self.shared.given).field("current", &self.current()).finish()
    }
}

struct Shared {
    /// The addresses given, in order.
    given: Vec<String>,
    tls: Option<ClientTls>,
    state: Mutex<State>,
}

struct State {
    current: String,
    channels: HashMap<String, Channel>,
}

impl Replicas {
    /// Channels to `addresses` (URLs, at least one), over TLS as
    /// [`crate::client::endpoint`] decides; none connects before its first call.
    pub fn new(addresses: &[String], tls: Option<&ClientTls>) -> Result<Self, BadAddress> {
        if addresses.is_empty() {
            return Err(BadAddress::from_problem("give at least one address: http://HOST:PORT or https://HOST:PORT"));
        }
        let mut channels = HashMap::new();
        for address in addresses {
            channels.insert(address.clone(), Self::connect(address, tls)?);
        }
        let current = addresses.first().cloned().unwrap_or_default();
        Ok(Self {
            shared: Arc::new(Shared {
                given: addresses.to_vec(),
                tls: tls.cloned(),
                state: Mutex::new(State { current, channels }),
            }),
        })
    }

    /// A comma-separated list of URLs, as `--server` takes them.
    pub fn from_list(list: &str, tls: Option<&ClientTls>) -> Result<Self, BadAddress> {
        let addresses: Vec<String> =
            list.split(',').map(str::trim).filter(|a| !a.is_empty()).map(str::to_owned).collect();
        Self::new(&addresses, tls)
    }

    /// The address calls go to now.
    pub fn current(&self) -> String {
        self.shared.lock().current.clone()
    }

    fn connect(address: &str, tls: Option<&ClientTls>) -> Result<Channel, BadAddress> {
        Ok(crate::client::endpoint(address, tls)?.tcp_nodelay(true).connect_lazy())
    }
}

impl Shared {
    fn lock(&self) -> std::sync::MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// The channel calls go to now, and its address.
    fn current(&self) -> (String, Channel) {
        let state = self.lock();
        let channel = state.channels.get(&state.current).cloned();
        match channel {
            Some(channel) => (state.current.clone(), channel),
            // Every current address has a channel (the list is never empty).
            None => (state.current.clone(), Endpoint::from_static("http://[::1]:1").connect_lazy()),
        }
    }

    /// Sends the next calls to `owner`, which a replica named.
    fn follow(&self, owner: &str) {
        let mut state = self.lock();
        if !state.channels.contains_key(owner) {
            match Replicas::connect(owner, self.tls.as_ref()) {
                Ok(channel) => {
                    state.channels.insert(owner.to_owned(), channel);
                }
                // An address we cannot dial: keep where we are.
                Err(_) => return,
            }
        }
        state.current = owner.to_owned();
    }

    /// `failed` did not answer: the next calls go to the next address given.
    fn move_on(&self, failed: &str) {
        let mut state = self.lock();
        if state.current != failed || self.given.len() < 2 {
            return;
        }
        let next = match self.given.iter().position(|a| a == failed) {
            Some(i) => self.given[(i + 1) % self.given.len()].clone(),
            None => self.given[0].clone(),
        };
        state.current = next;
    }
}

/// Most times one call is sent on to a named owner (an owner changing
/// hands as the call is made is named again, once).
const MAX_REDIRECTS: usize = 3;

impl Service<http::Request<Body>> for Replicas {
    type Response = http::Response<Body>;
    type Error = Box<dyn std::error::Error + Send + Sync>;
    type Future = Pin<Box<dyn Future<Output = Result<Self::Response, Self::Error>> + Send>>;

    fn poll_ready(&mut self, _: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        // Each call waits for its own channel, chosen when it is made.
        Poll::Ready(Ok(()))
    }

    fn call(&mut self, request: http::Request<Body>) -> Self::Future {
        let shared = Arc::clone(&self.shared);
        Box::pin(async move {
            // The project's calls send one message: kept, to send again to an owner.
            let (parts, body) = request.into_parts();
            let message = http_body_util::BodyExt::collect(body).await?.to_bytes();
            let mut redirects = 0;
            loop {
                let (address, mut channel) = shared.current();
                let request = copy_request(&parts, message.clone());
                std::future::poll_fn(|cx| Service::poll_ready(&mut channel, cx)).await?;
                let response = match Service::call(&mut channel, request).await {
                    Ok(response) => response,
                    Err(e) => {
                        shared.move_on(&address);
                        return Err(e.into());
                    }
                };
                let headers = response.headers();
                let unavailable = headers.get("grpc-status").is_some_and(|s| s == UNAVAILABLE);
                match headers.get(OWNER_METADATA).and_then(|o| o.to_str().ok()) {
                    Some(owner) if unavailable && owner != address && redirects < MAX_REDIRECTS => {
                        shared.follow(owner);
                        redirects += 1;
                    }
                    Some(owner) => {
                        shared.follow(owner);
                        return Ok(response);
                    }
                    None if unavailable => {
                        shared.move_on(&address);
                        return Ok(response);
                    }
                    None => return Ok(response),
                }
            }
        })
    }
}

/// A request of `parts` carrying `message`.
fn copy_request(parts: &http::request::Parts, message: bytes::Bytes) -> http::Request<Body> {
    let mut request = http::Request::new(Body::new(http_body_util::Full::new(message)));
    *request.method_mut() = parts.method.clone();
    *request.uri_mut() = parts.uri.clone();
    *request.version_mut() = parts.version;
    *request.headers_mut() = parts.headers.clone();
    request
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn a_failed_replica_hands_over_to_the_next_and_an_owner_is_followed() {
        let list = "http://127.0.0.1:1, http://127.0.0.1:2,http://127.0.0.1:3";
        let replicas = Replicas::from_list(list, None).unwrap();
        assert_eq!(replicas.current(), "http://127.0.0.1:1");
        replicas.shared.move_on("http://127.0.0.1:1");
        assert_eq!(replicas.current(), "http://127.0.0.1:2");
        // A stale failure (of an address no longer current) changes nothing.
        replicas.shared.move_on("http://127.0.0.1:1");
        assert_eq!(replicas.current(), "http://127.0.0.1:2");
        replicas.shared.move_on("http://127.0.0.1:2");
        replicas.shared.move_on("http://127.0.0.1:3");
        assert_eq!(replicas.current(), "http://127.0.0.1:1", "round the list");
        replicas.shared.follow("http://127.0.0.1:9");
        assert_eq!(replicas.current(), "http://127.0.0.1:9", "an owner outside the list");
        replicas.shared.move_on("http://127.0.0.1:9");
        assert_eq!(replicas.current(), "http://127.0.0.1:1", "back to the list when it fails");
        replicas.shared.follow("not a url");
        assert_eq!(replicas.current(), "http://127.0.0.1:1", "an address that cannot be dialled is not followed");
    }
}
