//! Calls run to their end even when the caller stops waiting.
//!
//! hyper drops a call's future when the client resets its stream, and
//! tonic when the call's deadline passes. An executive operation dropped
//! between its write and its apply would leave the live state behind the
//! store (the write lands, the mission never learns of it), and a map update
//! dropped while its write is in flight would leave nobody to undo it if
//! the write failed. So every call runs as its own task: the client may give
//! up on the answer, never on the operation, as with a database transaction
//! whose commit is under way.

use std::pin::Pin;
use std::task::{Context, Poll};

/// Runs each call as its own task (see the module).
#[derive(Debug, Clone, Copy, Default)]
pub struct RunToEndLayer;

impl<S> tower::Layer<S> for RunToEndLayer {
    type Service = RunToEnd<S>;

    fn layer(&self, inner: S) -> Self::Service {
        RunToEnd(inner)
    }
}

/// See [`RunToEndLayer`].
#[derive(Debug, Clone)]
pub struct RunToEnd<S>(S);

impl<S, Request> tower::Service<Request> for RunToEnd<S>
where
    S: tower::Service<Request>,
    S::Future: Send + 'static,
    S::Response: Send + 'static,
    S::Error: Send + 'static,
{
    type Response = S::Response;
    type Error = S::Error;
    type Future = Pin<Box<dyn std::future::Future<Output = Result<S::Response, S::Error>> + Send>>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        self.0.poll_ready(cx)
    }

    fn call(&mut self, request: Request) -> Self::Future {
        let call = tokio::spawn(self.0.call(request));
        Box::pin(async move {
            match call.await {
                Ok(outcome) => outcome,
                // A panic goes on as if it had happened here.
                Err(e) if e.is_panic() => std::panic::resume_unwind(e.into_panic()),
                // Never aborted: cancelled only as the runtime shuts down,
                // which drops this future too.
                Err(_) => std::future::pending().await,
            }
        })
    }
}
