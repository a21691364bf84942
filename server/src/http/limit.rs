//! The HTTP listener's connections: how many at once, and closing the quiet
//! ones.
//!
//! Anyone who reaches the HTTP port may open a connection before any token
//! is checked. Without a limit, idle or half-sent connections were held for
//! ever, and enough of them took every file descriptor of the process, so
//! that robots' gRPC connections could no longer be accepted. So at most
//! [`HttpLimits::max_connections`] are held (one beyond is closed as it
//! arrives, before any byte is read or a TLS handshake begins), and a
//! connection that moves no byte either way for [`HttpLimits::idle`] is
//! closed. Live views send a comment well within that time
//! ([`super::view`]), so only silent peers are dropped.

use std::io;
use std::net::SocketAddr;
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::Duration;

use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{OwnedSemaphorePermit, Semaphore};
use tokio::time::{Instant, Sleep};

/// Limits on the HTTP listener's connections.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct HttpLimits {
    /// Most connections at once. Operators' browsers and a Prometheus
    /// scraper need a few; the default leaves the process's descriptors to
    /// gRPC (whose own limit is separate).
    pub max_connections: usize,
    /// A connection that moves no byte either way for this long is closed.
    pub idle: Duration,
}

impl Default for HttpLimits {
    fn default() -> Self {
        Self { max_connections: 1_024, idle: Duration::from_secs(60) }
    }
}

/// TCP connections accepted up to [`HttpLimits::max_connections`].
pub(crate) struct Limited {
    listener: TcpListener,
    slots: Arc<Semaphore>,
    idle: Duration,
}

impl Limited {
    pub(crate) fn new(listener: TcpListener, limits: HttpLimits) -> Self {
        Self { listener, slots: Arc::new(Semaphore::new(limits.max_connections)), idle: limits.idle }
    }

    pub(crate) fn local_addr(&self) -> io::Result<SocketAddr> {
        self.listener.local_addr()
    }

    /// The next connection there is room for; those beyond the limit are
    /// closed unread. Accept errors (descriptors run out) are waited out.
    pub(crate) async fn accept(&self) -> (Quiet<TcpStream>, SocketAddr) {
        loop {
            match self.listener.accept().await {
                Ok((stream, peer)) => match Arc::clone(&self.slots).try_acquire_owned() {
                    Ok(slot) => return (Quiet::new(stream, slot, self.idle), peer),
                    Err(_) => tracing::debug!(%peer, "HTTP connection closed: the listener holds its most"),
                },
                Err(e) => {
                    tracing::debug!(error = %e, "HTTP accept failed");
                    tokio::time::sleep(Duration::from_millis(50)).await;
                }
            }
        }
    }
}

impl axum::serve::Listener for Limited {
    type Io = Quiet<TcpStream>;
    type Addr = SocketAddr;

    async fn accept(&mut self) -> (Self::Io, Self::Addr) {
        Limited::accept(self).await
    }

    fn local_addr(&self) -> io::Result<Self::Addr> {
        Limited::local_addr(self)
    }
}

/// A connection that holds a slot of its listener until dropped, and fails
/// with `TimedOut` once it has moved no byte for its idle time.
pub(crate) struct Quiet<S> {
    inner: S,
    _slot: OwnedSemaphorePermit,
    idle: Duration,
    deadline: Pin<Box<Sleep>>,
}

impl<S> Quiet<S> {
    fn new(inner: S, slot: OwnedSemaphorePermit, idle: Duration) -> Self {
        Self { inner, _slot: slot, idle, deadline: Box::pin(tokio::time::sleep(idle)) }
    }

    /// After a poll of the inner stream: bytes moved push the deadline on;
    /// waiting past it ends the connection.
    fn watch<T>(&mut self, cx: &mut Context<'_>, polled: Poll<io::Result<T>>, moved: bool) -> Poll<io::Result<T>> {
        match polled {
            Poll::Ready(result) => {
                if moved {
                    self.deadline.as_mut().reset(Instant::now() + self.idle);
                }
                Poll::Ready(result)
            }
            Poll::Pending => match self.deadline.as_mut().poll(cx) {
                Poll::Ready(()) => Poll::Ready(Err(io::Error::new(io::ErrorKind::TimedOut, "idle HTTP connection"))),
                Poll::Pending => Poll::Pending,
            },
        }
    }
}

impl<S: AsyncRead + Unpin> AsyncRead for Quiet<S> {
    fn poll_read(self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &mut ReadBuf<'_>) -> Poll<io::Result<()>> {
        let this = self.get_mut();
        let before = buf.filled().len();
        let polled = Pin::new(&mut this.inner).poll_read(cx, buf);
        let moved = buf.filled().len() > before;
        this.watch(cx, polled, moved)
    }
}

impl<S: AsyncWrite + Unpin> AsyncWrite for Quiet<S> {
    fn poll_write(self: Pin<&mut Self>, cx: &mut Context<'_>, data: &[u8]) -> Poll<io::Result<usize>> {
        let this = self.get_mut();
        let polled = Pin::new(&mut this.inner).poll_write(cx, data);
        let moved = matches!(polled, Poll::Ready(Ok(n)) if n > 0);
        this.watch(cx, polled, moved)
    }

    fn poll_flush(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        let this = self.get_mut();
        let polled = Pin::new(&mut this.inner).poll_flush(cx);
        this.watch(cx, polled, false)
    }

    fn poll_shutdown(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.get_mut().inner).poll_shutdown(cx)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tokio::io::{AsyncReadExt, AsyncWriteExt};

    fn quiet(stream: tokio::io::DuplexStream, idle: Duration) -> Quiet<tokio::io::DuplexStream> {
        let slot = Arc::new(Semaphore::new(1)).try_acquire_owned().unwrap();
        Quiet::new(stream, slot, idle)
    }

    /// Silence for the idle time ends the connection; a byte in either
    /// direction before it starts the time again.
    #[tokio::test(start_paused = true)]
    async fn a_connection_silent_for_its_idle_time_is_closed() {
        let (server, mut peer) = tokio::io::duplex(64);
        let mut server = quiet(server, Duration::from_secs(60));
        let reading = tokio::spawn(async move {
            let mut byte = [0u8; 1];
            let first = server.read(&mut byte).await.map(|_| Instant::now());
            server.write_all(b"x").await.unwrap();
            let second = server.read(&mut byte).await;
            (first, second.map_err(|e| (e.kind(), Instant::now())))
        });
        let start = Instant::now();
        tokio::time::sleep(Duration::from_secs(59)).await;
        peer.write_all(b"a").await.unwrap();
        let (first, second) = reading.await.unwrap();
        assert_eq!(first.unwrap() - start, Duration::from_secs(59), "a byte in time is read");
        let (kind, at) = second.unwrap_err();
        assert_eq!(kind, io::ErrorKind::TimedOut);
        assert_eq!(at - start, Duration::from_secs(59 + 60), "closed a full idle time after the last byte");
    }

    /// Beyond the limit a connection is closed unread; a slot comes back
    /// when a held connection ends.
    #[tokio::test]
    async fn connections_beyond_the_limit_are_closed_as_they_arrive() {
        let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
        let address = listener.local_addr().unwrap();
        let limited =
            Arc::new(Limited::new(listener, HttpLimits { max_connections: 2, idle: Duration::from_secs(60) }));
        let held = tokio::spawn({
            let limited = Arc::clone(&limited);
            async move { [limited.accept().await.0, limited.accept().await.0] }
        });
        let (_a, _b) = (TcpStream::connect(address).await.unwrap(), TcpStream::connect(address).await.unwrap());
        let held = held.await.unwrap();
        let mut third = TcpStream::connect(address).await.unwrap();
        let next = tokio::spawn({
            let limited = Arc::clone(&limited);
            async move { limited.accept().await.1 }
        });
        let mut byte = [0u8; 1];
        assert_eq!(third.read(&mut byte).await.unwrap(), 0, "closed at once");
        drop(held);
        let fourth = TcpStream::connect(address).await.unwrap();
        assert_eq!(next.await.unwrap(), fourth.local_addr().unwrap(), "a slot came back");
    }
}
