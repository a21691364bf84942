//! Connections: how many are held at once, and closing the ones left idle.
//! One mechanism for every listener: gRPC, the plaintext health listener
//! and the HTTP listener (the view and /metrics).
//!
//! [`Incoming`] accepts TCP connections up to a limit (one beyond it is
//! closed at once, before any byte is read or a TLS handshake begins) and
//! wraps each in a [`Tracked`] stream. [`ActivityLayer`] counts each
//! connection's open requests, streams included, until their response ends.
//! A connection with no open request for the idle time (a peer that sends
//! nothing, or half a request) is closed by its own reader, which reports
//! the end of the stream to the HTTP server; clients reconnect when they
//! next call, as they do after any lost connection. A peer that takes
//! nothing written to it for the idle time (it stopped reading, and would
//! hold its response and its slot for ever) gets a write error instead.

use std::io;
use std::net::SocketAddr;
use std::pin::Pin;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll, ready};
use std::time::Duration;

use futures::task::AtomicWaker;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::gauge::Gauge;
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio::time::{Instant, Sleep};
use tonic::transport::server::{Connected, TcpConnectInfo};

use crate::metrics::{Label, Metrics, RefusalLabels};

/// Limits on the connections an executive holds.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ConnectionLimits {
    /// Most connections at once; more are closed as they arrive.
    pub max_connections: usize,
    /// A connection with no open request for this long is closed, as is one
    /// whose peer takes no byte written to it for this long.
    pub idle_timeout: Duration,
    /// At shutdown, how long open connections may take to finish before
    /// they are dropped (a peer that never completes its handshake would
    /// otherwise hold the shutdown forever).
    pub drain_grace: Duration,
}

impl Default for ConnectionLimits {
    /// gRPC's: a thousand robots with room to spare, and streams that may
    /// be quiet for minutes.
    fn default() -> Self {
        Self { max_connections: 10_000, idle_timeout: Duration::from_secs(300), drain_grace: Duration::from_secs(10) }
    }
}

impl ConnectionLimits {
    /// A listener beside gRPC that anyone reaching its port may open before
    /// any token is checked: at most `max_connections`, and a minute of
    /// silence, so that silent peers cannot take the descriptors the robots'
    /// connections need. (The view's live streams are open requests, so
    /// they are not idle.)
    pub fn side_listener(max_connections: usize) -> Self {
        Self { max_connections, idle_timeout: Duration::from_secs(60), ..Self::default() }
    }
}

/// One connection's open requests, shared by its stream and its requests.
#[derive(Debug)]
struct Activity {
    open_requests: AtomicUsize,
    /// When the last request ended (or the connection opened).
    idle_since: Mutex<Instant>,
    /// The connection's reader, woken when it may have become idle.
    reader: AtomicWaker,
}

impl Activity {
    fn started(&self) {
        self.open_requests.fetch_add(1, Ordering::AcqRel);
    }

    fn ended(&self) {
        // The time first, then the count, so the reader never sees an idle
        // connection with an old time.
        *self.idle_since.lock().unwrap_or_else(|e| e.into_inner()) = Instant::now();
        if self.open_requests.fetch_sub(1, Ordering::AcqRel) == 1 {
            self.reader.wake();
        }
    }
}

/// What the server knows of a connection: its addresses, and its activity
/// for [`ActivityLayer`].
#[derive(Debug, Clone)]
pub struct ConnectionInfo {
    /// The TCP addresses.
    pub tcp: TcpConnectInfo,
    activity: Arc<Activity>,
}

/// Gives back a connection's place under the limit when it closes.
#[derive(Debug)]
struct Slot(Gauge);

impl Drop for Slot {
    fn drop(&mut self) {
        self.0.dec();
    }
}

/// An accepted connection that ends itself after the idle time.
#[derive(Debug)]
pub struct Tracked<S = TcpStream> {
    stream: S,
    /// The peer's address, for the log and for axum.
    peer: SocketAddr,
    activity: Arc<Activity>,
    idle_timeout: Duration,
    timer: Pin<Box<Sleep>>,
    /// Armed while a write waits for the peer to take bytes.
    write_stall: Option<Pin<Box<Sleep>>>,
    _slot: Slot,
}

impl<S> Tracked<S> {
    fn new(stream: S, peer: SocketAddr, idle_timeout: Duration, slot: Slot) -> Self {
        let activity = Arc::new(Activity {
            open_requests: AtomicUsize::new(0),
            idle_since: Mutex::new(Instant::now()),
            reader: AtomicWaker::new(),
        });
        Self {
            stream,
            peer,
            activity,
            idle_timeout,
            timer: Box::pin(tokio::time::sleep(idle_timeout)),
            write_stall: None,
            _slot: slot,
        }
    }

    /// Whether the connection has had no open request for the idle time;
    /// arms the timer (and the reader's waker) otherwise.
    fn idle(&mut self, cx: &mut Context<'_>) -> bool {
        self.activity.reader.register(cx.waker());
        if self.activity.open_requests.load(Ordering::Acquire) > 0 {
            return false;
        }
        let deadline = *self.activity.idle_since.lock().unwrap_or_else(|e| e.into_inner()) + self.idle_timeout;
        if Instant::now() >= deadline {
            return true;
        }
        self.timer.as_mut().reset(deadline);
        self.timer.as_mut().poll(cx).is_ready()
    }

    /// After a write (or flush) of the stream: one that has waited for the
    /// peer for the idle time fails; one that moved on disarms the timer.
    fn watch_write<T>(&mut self, cx: &mut Context<'_>, polled: Poll<io::Result<T>>) -> Poll<io::Result<T>> {
        if polled.is_ready() {
            self.write_stall = None;
            return polled;
        }
        let idle_timeout = self.idle_timeout;
        let stall = self.write_stall.get_or_insert_with(|| Box::pin(tokio::time::sleep(idle_timeout)));
        match stall.as_mut().poll(cx) {
            Poll::Ready(()) => {
                tracing::debug!(peer = %self.peer, "closing a connection whose peer stopped reading");
                Poll::Ready(Err(io::Error::new(io::ErrorKind::TimedOut, "the peer took nothing written to it")))
            }
            Poll::Pending => Poll::Pending,
        }
    }
}

impl Connected for Tracked {
    type ConnectInfo = ConnectionInfo;

    fn connect_info(&self) -> ConnectionInfo {
        ConnectionInfo { tcp: self.stream.connect_info(), activity: Arc::clone(&self.activity) }
    }
}

impl<S: AsyncRead + Unpin> AsyncRead for Tracked<S> {
    fn poll_read(mut self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &mut ReadBuf<'_>) -> Poll<io::Result<()>> {
        match Pin::new(&mut self.stream).poll_read(cx, buf) {
            Poll::Pending if self.idle(cx) => {
                tracing::debug!(peer = %self.peer, "closing an idle connection");
                // End of stream: the HTTP server closes the connection.
                Poll::Ready(Ok(()))
            }
            other => other,
        }
    }
}

impl<S: AsyncWrite + Unpin> AsyncWrite for Tracked<S> {
    fn poll_write(mut self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &[u8]) -> Poll<io::Result<usize>> {
        let polled = Pin::new(&mut self.stream).poll_write(cx, buf);
        self.watch_write(cx, polled)
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        let polled = Pin::new(&mut self.stream).poll_flush(cx);
        self.watch_write(cx, polled)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.stream).poll_shutdown(cx)
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        let polled = Pin::new(&mut self.stream).poll_write_vectored(cx, bufs);
        self.watch_write(cx, polled)
    }

    fn is_write_vectored(&self) -> bool {
        self.stream.is_write_vectored()
    }
}

/// Descriptors the executive needs beside its connections: the database
/// and its journal, the listeners, the runtime, the log.
const DESCRIPTORS_BESIDE_CONNECTIONS: u64 = 256;

/// Raises this process's soft open-files limit (often 1 024) towards what
/// `connections` need, as far as the hard limit allows, and says so; warns
/// when the hard limit is too low. Past the limit, connections wait in the
/// backlog. For binaries: the limit is the whole process's.
pub fn open_files_for(connections: usize) {
    use rustix::process::{Resource, getrlimit, setrlimit};
    let needed = (connections as u64).saturating_add(DESCRIPTORS_BESIDE_CONNECTIONS);
    let limit = getrlimit(Resource::Nofile);
    let Some(soft) = limit.current.filter(|&soft| soft < needed) else { return };
    let raised = limit.maximum.map_or(needed, |hard| hard.min(needed));
    if raised > soft {
        match setrlimit(Resource::Nofile, rustix::process::Rlimit { current: Some(raised), ..limit }) {
            Ok(()) => tracing::info!(from = soft, to = raised, "open-files limit raised for the connections allowed"),
            Err(e) => tracing::warn!(error = %e, "could not raise the open-files limit"),
        }
    }
    let now = getrlimit(Resource::Nofile).current.unwrap_or(u64::MAX);
    if now < needed {
        tracing::warn!(
            limit = now,
            needed,
            "the open-files limit is below what the connections allowed need: those beyond it wait until \
             others close (raise the hard limit: `ulimit -Hn`, systemd's LimitNOFILE)"
        );
    }
}

/// Accepted connections, up to the limit.
#[derive(Debug)]
pub struct Incoming {
    /// Which listener, for the log.
    name: &'static str,
    listener: TcpListener,
    limits: ConnectionLimits,
    /// Its open connections: its own count, or the executive's metric of
    /// them once [`Incoming::counted_in`].
    open: Gauge,
    /// When a refusal was last logged (one line per second at most).
    refused_logged: Option<Instant>,
    /// Armed when accepting failed for want of a resource (descriptors,
    /// memory): no accept is tried before it fires.
    backoff: Option<Pin<Box<Sleep>>>,
    /// Where its connections are counted, if anywhere.
    counted: Option<ListenerFigures>,
}

/// A listener's figures in the executive's metrics.
#[derive(Debug)]
struct ListenerFigures {
    at_limit: Counter,
    accept_errors: Counter,
}

/// How long accepting pauses after it failed for want of a resource. The
/// connection waiting in the backlog makes the listener ready again at once,
/// so retrying without a pause spins a core until a descriptor is freed.
const ACCEPT_BACKOFF: Duration = Duration::from_millis(100);

impl Incoming {
    /// Accepts on `listener` (called `name` in the log) within `limits`.
    pub fn new(name: &'static str, listener: TcpListener, limits: ConnectionLimits) -> Self {
        Self { name, listener, limits, open: Gauge::default(), refused_logged: None, backoff: None, counted: None }
    }

    /// Counts its open connections, those turned away and failed accepts in
    /// `metrics`, under its name. Before it accepts anything.
    pub fn counted_in(mut self, metrics: &Metrics) -> Self {
        let refused = |reason: &str| {
            metrics
                .connections_refused
                .get_or_create(&RefusalLabels { listener: self.name.to_owned(), reason: reason.to_owned() })
                .clone()
        };
        // Nothing is open yet: the metric takes over the count.
        self.open = metrics.connections.get_or_create(&Label { name: self.name.to_owned() }).clone();
        self.counted = Some(ListenerFigures { at_limit: refused("limit"), accept_errors: refused("accept error") });
        self
    }

    /// The address it listens on.
    pub fn local_addr(&self) -> io::Result<SocketAddr> {
        self.listener.local_addr()
    }

    fn admit(&mut self, stream: TcpStream, peer: SocketAddr) -> Option<Tracked> {
        if usize::try_from(self.open.get()).is_ok_and(|open| open >= self.limits.max_connections) {
            if let Some(counted) = &self.counted {
                counted.at_limit.inc();
            }
            if self.refused_logged.is_none_or(|at| at.elapsed() >= Duration::from_secs(1)) {
                tracing::warn!(
                    listener = self.name,
                    limit = self.limits.max_connections,
                    "connection limit reached: refusing connections"
                );
                self.refused_logged = Some(Instant::now());
            }
            return None;
        }
        let _ = stream.set_nodelay(true);
        // Dead peers are found by TCP keepalive; idle live ones by the timer.
        let keepalive =
            socket2::TcpKeepalive::new().with_time(Duration::from_secs(30)).with_interval(Duration::from_secs(10));
        let _ = socket2::SockRef::from(&stream).set_tcp_keepalive(&keepalive);
        self.open.inc();
        Some(Tracked::new(stream, peer, self.limits.idle_timeout, Slot(self.open.clone())))
    }
}

impl futures::Stream for Incoming {
    type Item = io::Result<Tracked>;

    /// Never yields an error: a connection that failed before it was
    /// accepted is skipped, and a want of descriptors or memory is logged and
    /// waited out here (tonic would retry at once).
    fn poll_next(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Self::Item>> {
        loop {
            if let Some(backoff) = self.backoff.as_mut() {
                ready!(backoff.as_mut().poll(cx));
                self.backoff = None;
            }
            match ready!(self.listener.poll_accept(cx)) {
                Ok((stream, peer)) => {
                    if let Some(tracked) = self.admit(stream, peer) {
                        return Poll::Ready(Some(Ok(tracked)));
                    }
                }
                Err(e) if is_connection_error(&e) => {
                    tracing::debug!(listener = self.name, error = %e, "a connection failed before it was accepted");
                }
                Err(e) => {
                    if let Some(counted) = &self.counted {
                        counted.accept_errors.inc();
                    }
                    if self.refused_logged.is_none_or(|at| at.elapsed() >= Duration::from_secs(1)) {
                        tracing::warn!(
                            listener = self.name,
                            error = %e,
                            "cannot accept connections (raise the hard open-files limit, `ulimit -Hn` or systemd's LimitNOFILE, or lower the connection limits); retrying"
                        );
                        self.refused_logged = Some(Instant::now());
                    }
                    self.backoff = Some(Box::pin(tokio::time::sleep(ACCEPT_BACKOFF)));
                }
            }
        }
    }
}

/// Whether an accept failed for the one connection only (its peer gave up
/// or reset before it was taken), rather than for the listener's process.
fn is_connection_error(e: &io::Error) -> bool {
    matches!(
        e.kind(),
        io::ErrorKind::ConnectionAborted
            | io::ErrorKind::ConnectionReset
            | io::ErrorKind::ConnectionRefused
            | io::ErrorKind::Interrupted
    )
}

/// The HTTP listener's way in (axum's).
impl axum::serve::Listener for Incoming {
    type Io = Tracked;
    type Addr = SocketAddr;

    async fn accept(&mut self) -> (Tracked, SocketAddr) {
        loop {
            match futures::StreamExt::next(self).await {
                Some(Ok(tracked)) => {
                    let peer = tracked.peer;
                    return (tracked, peer);
                }
                // Not yielded: accept errors are waited out in the stream.
                Some(Err(_)) => continue,
                // A listener's stream does not end.
                None => return std::future::pending().await,
            }
        }
    }

    fn local_addr(&self) -> io::Result<SocketAddr> {
        Incoming::local_addr(self)
    }
}

impl axum::extract::connect_info::Connected<axum::serve::IncomingStream<'_, Incoming>> for ConnectionInfo {
    fn connect_info(stream: axum::serve::IncomingStream<'_, Incoming>) -> Self {
        stream.io().connect_info()
    }
}

/// Counts a connection's open requests, from the request until its response
/// body ends (a stream's end, or the client going away).
#[derive(Debug, Clone, Copy, Default)]
pub struct ActivityLayer;

impl<S> tower::Layer<S> for ActivityLayer {
    type Service = ActivityService<S>;

    fn layer(&self, inner: S) -> Self::Service {
        ActivityService { inner }
    }
}

/// See [`ActivityLayer`].
#[derive(Debug, Clone)]
pub struct ActivityService<S> {
    inner: S,
}

/// The connection's activity, from the request's extensions: tonic's, plain
/// or TLS, or axum's.
fn activity_of<B>(request: &http::Request<B>) -> Option<Arc<Activity>> {
    let extensions = request.extensions();
    extensions
        .get::<ConnectionInfo>()
        .or_else(|| extensions.get::<tonic::transport::server::TlsConnectInfo<ConnectionInfo>>().map(|t| t.get_ref()))
        .or_else(|| extensions.get::<axum::extract::ConnectInfo<ConnectionInfo>>().map(|c| &c.0))
        .map(|info| Arc::clone(&info.activity))
}

/// Ends one open request of a connection when dropped.
#[derive(Debug)]
struct OpenRequest(Arc<Activity>);

impl OpenRequest {
    fn new(activity: Arc<Activity>) -> Self {
        activity.started();
        Self(activity)
    }
}

impl Drop for OpenRequest {
    fn drop(&mut self) {
        self.0.ended();
    }
}

impl<S, B, R> tower::Service<http::Request<B>> for ActivityService<S>
where
    S: tower::Service<http::Request<B>, Response = http::Response<R>>,
    S::Future: Send + 'static,
    R: http_body::Body + Send + 'static,
{
    type Response = http::Response<Counted<R>>;
    type Error = S::Error;
    type Future = Pin<Box<dyn std::future::Future<Output = Result<Self::Response, S::Error>> + Send>>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, request: http::Request<B>) -> Self::Future {
        let open = activity_of(&request).map(OpenRequest::new);
        let response = self.inner.call(request);
        Box::pin(async move {
            let response = response.await?;
            Ok(response.map(|body| Counted { body, _open: open }))
        })
    }
}

pin_project_lite::pin_project! {
    /// A response body that keeps its request open until it ends.
    #[derive(Debug)]
    pub struct Counted<B> {
        #[pin]
        body: B,
        _open: Option<OpenRequest>,
    }
}

impl<B: http_body::Body> http_body::Body for Counted<B> {
    type Data = B::Data;
    type Error = B::Error;

    fn poll_frame(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<http_body::Frame<Self::Data>, Self::Error>>> {
        self.project().body.poll_frame(cx)
    }

    fn is_end_stream(&self) -> bool {
        self.body.is_end_stream()
    }

    fn size_hint(&self) -> http_body::SizeHint {
        self.body.size_hint()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tokio::io::{AsyncReadExt, AsyncWriteExt, DuplexStream};

    fn tracked(stream: DuplexStream, idle_timeout: Duration) -> Tracked<DuplexStream> {
        let peer = SocketAddr::from(([127, 0, 0, 1], 9));
        Tracked::new(stream, peer, idle_timeout, Slot(Gauge::default()))
    }

    /// No open request for the idle time ends the connection (its reader
    /// sees the end); an open request, however long, keeps it, and the idle
    /// time starts again when the request ends.
    #[tokio::test(start_paused = true)]
    async fn a_connection_without_an_open_request_for_the_idle_time_is_closed() {
        let (server, _peer) = tokio::io::duplex(64);
        let mut server = tracked(server, Duration::from_secs(60));
        let activity = Arc::clone(&server.activity);
        let start = Instant::now();
        let request = tokio::spawn(async move {
            tokio::time::sleep(Duration::from_secs(30)).await;
            let open = OpenRequest::new(activity);
            tokio::time::sleep(Duration::from_secs(600)).await;
            drop(open);
        });
        let mut byte = [0u8; 1];
        let read = tokio::time::timeout(Duration::from_secs(3_600), server.read(&mut byte)).await;
        assert_eq!(read.expect("closed within the hour").unwrap(), 0, "closed");
        assert_eq!(start.elapsed(), Duration::from_secs(30 + 600 + 60), "a full idle time after the request ended");
        request.await.unwrap();
    }

    /// A peer that takes nothing written to it for the idle time gets a
    /// write error; one that reads in time starts the time again.
    #[tokio::test(start_paused = true)]
    async fn a_peer_that_stops_reading_is_cut_off_after_the_idle_time() {
        let (server, mut peer) = tokio::io::duplex(4);
        let mut server = tracked(server, Duration::from_secs(60));
        let start = Instant::now();
        let reader = tokio::spawn(async move {
            tokio::time::sleep(Duration::from_secs(59)).await;
            let mut taken = [0u8; 4];
            peer.read_exact(&mut taken).await.unwrap();
            peer // held open, never read again
        });
        let written = tokio::time::timeout(Duration::from_secs(3_600), server.write_all(b"12345678_and_more")).await;
        let error = written.expect("cut off within the hour").unwrap_err();
        assert_eq!(error.kind(), io::ErrorKind::TimedOut);
        assert_eq!(start.elapsed(), Duration::from_secs(59 + 60), "a full idle time after the peer last read");
        drop(reader.await.unwrap());
    }

    /// Beyond the limit a connection is closed unread; a slot comes back
    /// when a held connection ends.
    /// `--max-connections 18446744073709551615` overflowed the count of
    /// descriptors needed; the limit is only ever raised.
    #[test]
    fn any_count_of_connections_raises_the_open_files_limit_at_most_to_the_hard_one() {
        use rustix::process::{Resource, getrlimit};
        let before = getrlimit(Resource::Nofile);
        open_files_for(usize::MAX);
        open_files_for(0);
        let after = getrlimit(Resource::Nofile);
        assert!(after.current >= before.current, "{before:?} → {after:?}");
        assert_eq!(after.maximum, before.maximum);
    }

    #[tokio::test]
    async fn connections_beyond_the_limit_are_closed_as_they_arrive() {
        use axum::serve::Listener;
        let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
        let address = listener.local_addr().unwrap();
        let metrics = Metrics::new();
        let mut incoming = Incoming::new("test", listener, ConnectionLimits::side_listener(2)).counted_in(&metrics);
        let figure = |name: &str| {
            let text = metrics.encode();
            text.lines().find(|l| l.starts_with(name)).map(|l| l.rsplit(' ').next().unwrap().to_owned())
        };
        let (_a, _b) = (TcpStream::connect(address).await.unwrap(), TcpStream::connect(address).await.unwrap());
        let held = [incoming.accept().await.0, incoming.accept().await.0];
        assert_eq!(figure("coordinator_connections{name=\"test\"}").as_deref(), Some("2"));
        let mut third = TcpStream::connect(address).await.unwrap();
        let next = tokio::spawn(async move { incoming.accept().await.1 });
        let mut byte = [0u8; 1];
        assert_eq!(third.read(&mut byte).await.unwrap(), 0, "closed at once");
        let refused = "coordinator_connections_refused_total{listener=\"test\",reason=\"limit\"}";
        assert_eq!(figure(refused).as_deref(), Some("1"));
        drop(held);
        assert_eq!(figure("coordinator_connections{name=\"test\"}").as_deref(), Some("0"));
        let fourth = TcpStream::connect(address).await.unwrap();
        assert_eq!(next.await.unwrap(), fourth.local_addr().unwrap(), "a slot came back");
    }
}
