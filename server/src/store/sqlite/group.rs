//! Group commit: the changesets that wait while one transaction is written
//! are written together in the next, and each is acknowledged only once the
//! transaction holding it is durable.
//!
//! With `synchronous = FULL` every commit waits for the disk, and SQLite
//! writes one transaction at a time; a thousand robots reporting several
//! times a second would queue behind the disk one changeset after another.
//! Grouping pays the wait once per group. Changesets of one mission never
//! wait side by side (the mission's lock orders them), so a group never
//! holds two that depend on each other's outcome. If a group fails, its
//! changesets are written again one by one, so that one bad changeset (a
//! constraint it breaks) fails alone.

use std::time::Instant;

use sqlx::sqlite::SqlitePool;
use sqlx::{Connection, SqliteConnection};
use tokio::sync::{mpsc, oneshot};

use super::write;
use crate::metrics::Metrics;
use crate::store::{Changeset, StoreError};

/// Most changesets written in one transaction.
const MAX_GROUP: usize = 256;

/// One changeset waiting, and where to answer.
pub(super) type Pending = (Changeset, oneshot::Sender<Result<Changeset, StoreError>>);

/// The queue the committer drains; closing it (dropping every sender) ends
/// the committer once the queue is empty.
pub(super) fn start(
    pool: SqlitePool,
    metrics: Option<std::sync::Arc<Metrics>>,
) -> (mpsc::Sender<Pending>, tokio::task::JoinHandle<()>) {
    let (sender, receiver) = mpsc::channel(4 * MAX_GROUP);
    (sender, tokio::spawn(run(pool, receiver, metrics)))
}

async fn run(pool: SqlitePool, mut queue: mpsc::Receiver<Pending>, metrics: Option<std::sync::Arc<Metrics>>) {
    let mut group = Vec::with_capacity(MAX_GROUP);
    while queue.recv_many(&mut group, MAX_GROUP).await > 0 {
        let started = Instant::now();
        let size = group.len();
        let (changesets, replies): (Vec<Changeset>, Vec<_>) = group.drain(..).unzip();
        match write_group(&pool, &changesets).await {
            Ok(()) => {
                for (changes, reply) in changesets.into_iter().zip(replies) {
                    let _ = reply.send(Ok(changes));
                }
            }
            Err(e) if size == 1 => {
                if let Some(reply) = replies.into_iter().next() {
                    let _ = reply.send(Err(e));
                }
            }
            // Written again one by one: only the changesets that fail alone fail.
            Err(_) => {
                for (changes, reply) in changesets.into_iter().zip(replies) {
                    let outcome = write_group(&pool, std::slice::from_ref(&changes)).await.map(|()| changes);
                    let _ = reply.send(outcome);
                }
            }
        }
        if let Some(metrics) = &metrics {
            metrics.store_commit.observe(started.elapsed().as_secs_f64());
            metrics.commit_group.observe(size as f64);
        }
    }
}

/// Writes `changesets` in one transaction. A failure never returns its
/// connection to the pool: after a full disk SQLite may or may not have
/// rolled back by itself and sqlx's count of open transactions may be off,
/// so the connection is closed, which rolls back whatever is still open.
async fn write_group(pool: &SqlitePool, changesets: &[Changeset]) -> Result<(), StoreError> {
    let mut conn = pool.acquire().await?;
    let written = write_in_transaction(&mut conn, changesets).await;
    if written.is_err() {
        conn.close_on_drop();
    }
    written
}

async fn write_in_transaction(conn: &mut SqliteConnection, changesets: &[Changeset]) -> Result<(), StoreError> {
    // IMMEDIATE: take the write lock now, not halfway through.
    let mut tx = conn.begin_with("BEGIN IMMEDIATE").await?;
    write::group(&mut tx, changesets).await?;
    tx.commit().await?;
    Ok(())
}
