//! Connections: how many are held at once, and closing the ones left idle.
//!
//! [`Incoming`] accepts TCP connections up to a limit (one beyond it is
//! closed at once, before any byte is read) and wraps each in a [`Tracked`]
//! stream. [`ActivityLayer`] counts each connection's open requests,
//! streams included, until their response ends. A connection with no open
//! request for the idle time is closed by its own reader, which reports the
//! end of the stream to the HTTP/2 server; clients reconnect when they next
//! call, as they do after any lost connection.

use std::io;
use std::pin::Pin;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::Duration;

use futures::task::AtomicWaker;
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio::time::{Instant, Sleep};
use tonic::transport::server::{Connected, TcpConnectInfo};

/// Limits on the connections an executive holds.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ConnectionLimits {
    /// Most connections at once; more are closed as they arrive.
    pub max_connections: usize,
    /// A connection with no open request for this long is closed.
    pub idle_timeout: Duration,
    /// At shutdown, how long open connections may take to finish before
    /// they are dropped (a peer that never completes its handshake would
    /// otherwise hold the shutdown forever).
    pub drain_grace: Duration,
}

impl Default for ConnectionLimits {
    fn default() -> Self {
        Self { max_connections: 10_000, idle_timeout: Duration::from_secs(300), drain_grace: Duration::from_secs(10) }
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
struct Slot(Arc<AtomicUsize>);

impl Drop for Slot {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::AcqRel);
    }
}

/// An accepted connection that ends itself after the idle time.
#[derive(Debug)]
pub struct Tracked {
    stream: TcpStream,
    activity: Arc<Activity>,
    idle_timeout: Duration,
    timer: Pin<Box<Sleep>>,
    _slot: Slot,
}

impl Tracked {
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
}

impl Connected for Tracked {
    type ConnectInfo = ConnectionInfo;

    fn connect_info(&self) -> ConnectionInfo {
        ConnectionInfo { tcp: self.stream.connect_info(), activity: Arc::clone(&self.activity) }
    }
}

impl AsyncRead for Tracked {
    fn poll_read(mut self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &mut ReadBuf<'_>) -> Poll<io::Result<()>> {
        match Pin::new(&mut self.stream).poll_read(cx, buf) {
            Poll::Pending if self.idle(cx) => {
                tracing::debug!(peer = ?self.stream.peer_addr().ok(), "closing an idle connection");
                // End of stream: the HTTP/2 server closes the connection.
                Poll::Ready(Ok(()))
            }
            other => other,
        }
    }
}

impl AsyncWrite for Tracked {
    fn poll_write(mut self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &[u8]) -> Poll<io::Result<usize>> {
        Pin::new(&mut self.stream).poll_write(cx, buf)
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.stream).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.stream).poll_shutdown(cx)
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        Pin::new(&mut self.stream).poll_write_vectored(cx, bufs)
    }

    fn is_write_vectored(&self) -> bool {
        self.stream.is_write_vectored()
    }
}

/// Accepted connections, up to the limit.
#[derive(Debug)]
pub struct Incoming {
    listener: TcpListener,
    limits: ConnectionLimits,
    open: Arc<AtomicUsize>,
    /// When a refusal was last logged (one line per second at most).
    refused_logged: Option<Instant>,
}

impl Incoming {
    /// Accepts on `listener` within `limits`.
    pub fn new(listener: TcpListener, limits: ConnectionLimits) -> Self {
        Self { listener, limits, open: Arc::new(AtomicUsize::new(0)), refused_logged: None }
    }

    fn accept(&mut self, stream: TcpStream) -> Option<Tracked> {
        if self.open.load(Ordering::Acquire) >= self.limits.max_connections {
            if self.refused_logged.is_none_or(|at| at.elapsed() >= Duration::from_secs(1)) {
                tracing::warn!(limit = self.limits.max_connections, "connection limit reached: refusing connections");
                self.refused_logged = Some(Instant::now());
            }
            return None;
        }
        let _ = stream.set_nodelay(true);
        // Dead peers are found by TCP keepalive; idle live ones by the timer.
        let keepalive =
            socket2::TcpKeepalive::new().with_time(Duration::from_secs(30)).with_interval(Duration::from_secs(10));
        let _ = socket2::SockRef::from(&stream).set_tcp_keepalive(&keepalive);
        self.open.fetch_add(1, Ordering::AcqRel);
        let activity = Arc::new(Activity {
            open_requests: AtomicUsize::new(0),
            idle_since: Mutex::new(Instant::now()),
            reader: AtomicWaker::new(),
        });
        Some(Tracked {
            stream,
            activity,
            idle_timeout: self.limits.idle_timeout,
            timer: Box::pin(tokio::time::sleep(self.limits.idle_timeout)),
            _slot: Slot(Arc::clone(&self.open)),
        })
    }
}

impl futures::Stream for Incoming {
    type Item = io::Result<Tracked>;

    fn poll_next(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Self::Item>> {
        loop {
            match self.listener.poll_accept(cx) {
                Poll::Ready(Ok((stream, _))) => {
                    if let Some(tracked) = self.accept(stream) {
                        return Poll::Ready(Some(Ok(tracked)));
                    }
                }
                // Accept errors (a full descriptor table, a reset before
                // accept) are passing: the server logs them and goes on.
                Poll::Ready(Err(e)) => return Poll::Ready(Some(Err(e))),
                Poll::Pending => return Poll::Pending,
            }
        }
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

/// The connection's activity, from the request's extensions (plain or TLS).
fn activity_of<B>(request: &http::Request<B>) -> Option<Arc<Activity>> {
    let extensions = request.extensions();
    extensions
        .get::<ConnectionInfo>()
        .or_else(|| extensions.get::<tonic::transport::server::TlsConnectInfo<ConnectionInfo>>().map(|t| t.get_ref()))
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
