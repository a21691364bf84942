//! Group commit: the changesets that wait while one transaction is written
//! are written together in the next, and each is acknowledged only once the
//! transaction holding it is durable.
//!
//! With `synchronous = FULL` (or PostgreSQL's `synchronous_commit`) every
//! commit waits for the disk, and the store writes one transaction at a
//! time; a thousand robots reporting several
//! times a second would queue behind the disk one changeset after another.
//! Grouping pays the wait once per group. If a group fails, its changesets
//! are written again one by one, in order, so that one bad changeset (a
//! constraint it breaks) fails alone, with those that follow it
//! ([`crate::store::Store::submit`]): a mission's map updates are queued
//! while earlier ones are still being written, so one group may hold
//! several changesets of a mission, each prepared on the one before.

use std::collections::HashMap;
use std::sync::Arc;
use std::time::Instant;

use tokio::sync::{mpsc, oneshot};

use super::statement::{Backend, Transaction};
use super::write;
use crate::metrics::Metrics;
use crate::store::{Changeset, CommitId, FailureKind, StoreError};

/// Most changesets written in one transaction.
const MAX_GROUP: usize = 256;

/// One changeset waiting, what it follows, and where to answer.
#[derive(Debug)]
pub(super) struct Pending {
    pub(super) id: CommitId,
    pub(super) after: Option<CommitId>,
    pub(super) changes: Changeset,
    pub(super) reply: oneshot::Sender<Result<Changeset, StoreError>>,
    /// When it was queued.
    pub(super) queued_at: Instant,
}

/// The queue the committer drains; closing it (dropping every sender) ends
/// the committer once the queue is empty.
pub(super) fn start<B: Backend>(
    backend: Arc<B>,
    metrics: Option<Arc<Metrics>>,
) -> (mpsc::Sender<Pending>, tokio::task::JoinHandle<()>) {
    let (sender, receiver) = mpsc::channel(4 * MAX_GROUP);
    (sender, tokio::spawn(run(backend, receiver, metrics)))
}

async fn run<B: Backend>(backend: Arc<B>, mut queue: mpsc::Receiver<Pending>, metrics: Option<Arc<Metrics>>) {
    let mut received = Vec::with_capacity(MAX_GROUP);
    let mut broken = Broken::default();
    while queue.recv_many(&mut received, MAX_GROUP).await > 0 {
        let started = Instant::now();
        if let Some(metrics) = &metrics {
            for pending in &received {
                metrics.store_queued.observe((started - pending.queued_at).as_secs_f64());
            }
        }
        let group: Vec<Pending> = received.drain(..).filter_map(|p| broken.unless_abandoned(p)).collect();
        let size = group.len();
        if size == 0 {
            continue;
        }
        let changesets: Vec<Changeset> = group.iter().map(|p| p.changes.clone()).collect();
        match write_group(&*backend, &changesets).await {
            Ok(()) => {
                for pending in group {
                    let _ = pending.reply.send(Ok(pending.changes));
                }
            }
            // The transaction could not even begin (the database busy past
            // its timeout, unreachable): no changeset is the cause, and
            // written again one by one each would wait for it anew.
            Err(GroupFailure::Begin(e)) => {
                for pending in group {
                    let Some(pending) = broken.unless_abandoned(pending) else { continue };
                    let error = StoreError::Unwritten { kind: e.kind(), cause: e.to_string() };
                    broken.failed(pending.id, &error);
                    let _ = pending.reply.send(Err(error));
                }
            }
            // Written again one by one: only the changesets that fail alone
            // fail, and those that follow them.
            Err(GroupFailure::Write(e)) => {
                let mut first_error = Some(e);
                for pending in group {
                    let Some(pending) = broken.unless_abandoned(pending) else { continue };
                    let outcome = match first_error.take().filter(|_| size == 1) {
                        Some(e) => Err(e),
                        None => write_group(&*backend, std::slice::from_ref(&pending.changes))
                            .await
                            .map_err(GroupFailure::into_error),
                    };
                    match outcome {
                        Ok(()) => {
                            let _ = pending.reply.send(Ok(pending.changes));
                        }
                        Err(e) => {
                            broken.failed(pending.id, &e);
                            let _ = pending.reply.send(Err(e));
                        }
                    }
                }
            }
        }
        if let Some(metrics) = &metrics {
            metrics.store_commit.observe(started.elapsed().as_secs_f64());
            metrics.commit_group.observe(size as f64);
        }
    }
}

/// The changesets that were not written and may still be followed, each
/// with the first failure of its chain. A changeset is followed by at most
/// one other, which takes its place here when it is abandoned in turn: one
/// entry per broken chain.
#[derive(Debug, Default)]
struct Broken(HashMap<CommitId, (FailureKind, String)>);

impl Broken {
    /// `pending`, unless it follows a changeset that was not written: then
    /// it is answered with [`StoreError::Abandoned`] and takes that one's place.
    fn unless_abandoned(&mut self, pending: Pending) -> Option<Pending> {
        let Some((kind, cause)) = pending.after.and_then(|after| self.0.remove(&after)) else { return Some(pending) };
        self.0.insert(pending.id, (kind, cause.clone()));
        let _ = pending.reply.send(Err(StoreError::Abandoned { kind, cause }));
        None
    }

    /// `id` failed with `error`.
    fn failed(&mut self, id: CommitId, error: &StoreError) {
        self.0.insert(id, (error.kind(), error.to_string()));
    }
}

/// Why a group was not written.
#[derive(Debug)]
enum GroupFailure {
    /// The transaction did not begin: nothing of the group was tried.
    Begin(StoreError),
    /// Writing or committing failed: a changeset may be the cause.
    Write(StoreError),
}

impl GroupFailure {
    fn into_error(self) -> StoreError {
        match self {
            Self::Begin(e) | Self::Write(e) => e,
        }
    }
}

/// Writes `changesets` in one transaction; on a failure, none of them
/// (see [`Transaction`]).
async fn write_group(backend: &impl Backend, changesets: &[Changeset]) -> Result<(), GroupFailure> {
    let mut tx = backend.begin_write().await.map_err(GroupFailure::Begin)?;
    write::group(&mut tx, changesets).await.map_err(GroupFailure::Write)?;
    tx.commit().await.map_err(GroupFailure::Write)
}
