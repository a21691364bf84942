//! WAL checkpoints beside the writes.
//!
//! SQLite's default copies the write-ahead log back into the database file
//! inside the commit that makes the log pass 1 000 pages: that commit (and
//! every changeset waiting behind it in the group committer) waits for
//! megabytes of copying and a flush of the database file. Here the log is
//! checkpointed by its own task on its own connection, in the PASSIVE mode
//! that never blocks the writer, a few times a second; a log that
//! nevertheless grew large (a reader held it) is truncated once it can be.

use std::time::Duration;

use sqlx::sqlite::SqlitePool;
use tokio_util::sync::CancellationToken;

/// How often the log is checkpointed.
const PERIOD: Duration = Duration::from_millis(200);

/// Log pages past which the checkpoint also truncates the file (about 64 MB).
const TRUNCATE_PAGES: i64 = 16_384;

/// The checkpointing task of a store.
#[derive(Debug)]
pub(super) struct Checkpointer {
    stop: CancellationToken,
    task: tokio::task::JoinHandle<()>,
}

impl Checkpointer {
    /// Checkpoints `pool`'s database every [`PERIOD`] until stopped.
    pub(super) fn start(pool: SqlitePool) -> Self {
        let stop = CancellationToken::new();
        Self { task: tokio::spawn(run(pool, stop.clone())), stop }
    }

    /// Stops, after the checkpoint under way if any.
    pub(super) async fn stop(self) {
        self.stop.cancel();
        let _ = self.task.await;
    }
}

async fn run(pool: SqlitePool, stop: CancellationToken) {
    let mut tick = tokio::time::interval(PERIOD);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tokio::select! {
            () = stop.cancelled() => return,
            _ = tick.tick() => {}
        }
        match checkpoint(&pool, "PRAGMA wal_checkpoint(PASSIVE)").await {
            Ok(pages) if pages > TRUNCATE_PAGES => {
                if let Err(e) = checkpoint(&pool, "PRAGMA wal_checkpoint(TRUNCATE)").await {
                    tracing::debug!(error = %e, "the write-ahead log could not be truncated yet");
                }
            }
            Ok(_) => {}
            Err(e) => tracing::warn!(error = %e, "WAL checkpoint failed; tried again shortly"),
        }
    }
}

/// Runs one checkpoint pragma; the log's size in pages.
async fn checkpoint(pool: &SqlitePool, pragma: &'static str) -> Result<i64, sqlx::Error> {
    // (busy, log pages, pages checkpointed)
    let (_, log, _): (i64, i64, i64) = sqlx::query_as(pragma).fetch_one(pool).await?;
    Ok(log)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::domain::Timestamp;
    use crate::store::Store;
    use crate::store::sqlite::tests::{note, spec};
    use crate::store::sqlite::{Durability, SqliteStore};

    /// With SQLite's own checkpoints turned off, the log stays bounded by
    /// ours: it is rewound after each, however much is written.
    #[tokio::test]
    async fn the_log_is_rewound_after_each_checkpoint() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("wal.db");
        let store = SqliteStore::open(&path, Durability::Full).await.unwrap();
        let mission = store.create_mission(&spec(), Timestamp(1)).await.unwrap();
        let wal = dir.path().join("wal.db-wal");
        let mut sizes = Vec::new();
        for round in 0..6 {
            for i in 0..200 {
                let detail = format!("round {round}, event {i}: {}", "x".repeat(500));
                store.commit(note(mission.id, i, detail)).await.unwrap();
            }
            sizes.push(std::fs::metadata(&wal).unwrap().len());
            let log = checkpoint(&store.pool, "PRAGMA wal_checkpoint(PASSIVE)").await.unwrap();
            assert!(log > 0, "round {round} wrote to the log");
        }
        // Unchecked, six rounds would make it six times the first round's
        // size (the background checkpoints may also have rewound it).
        assert!(sizes[5] <= 2 * sizes[0], "the log grew from {} to {} bytes: {sizes:?}", sizes[0], sizes[5]);
        assert_eq!(store.events(mission.id, 0, u32::MAX).await.unwrap().len(), 1200);
    }
}
