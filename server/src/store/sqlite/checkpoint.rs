//! WAL checkpoints beside the writes.
//!
//! SQLite's default copies the write-ahead log back into the database file
//! inside the commit that makes the log pass 1 000 pages: that commit (and
//! every changeset waiting behind it in the group committer) waits for
//! megabytes of copying and a flush of the database file. Here the log is
//! checkpointed by its own task on its own connection, in the PASSIVE mode
//! that never blocks the writer, a few times a second.
//!
//! Under a steady stream of commits a PASSIVE checkpoint never catches up:
//! frames are appended while it copies, so the log is never fully copied
//! when the next transaction begins, and SQLite rewinds it only then. The
//! log grows by the whole write rate (about 10 MB/s for 1 000 robots at
//! twice the real rates). Once it passes [`REWIND_PAGES`] the checkpointer
//! takes the [`WriterTurn`] between two group commits and checkpoints again:
//! with no writer it copies the rest (a fraction of a period's writes), and
//! the next transaction starts the log from its beginning. This replaced a
//! `wal_checkpoint(TRUNCATE)` once the log passed 64 MB, which holds
//! SQLite's writer lock while it copies the rest, flushes and cuts the file:
//! the committer's `BEGIN IMMEDIATE` slept meanwhile in SQLite's busy
//! handler (1, 2, 5, 10, 15 ms ...), 35–105 ms every few seconds at that
//! load, the longest waits any map update had. Waiting on our own turn
//! instead, the committer resumes the moment the checkpoint ends.

use std::sync::Arc;
use std::time::Duration;

use sqlx::sqlite::SqlitePool;
use tokio_util::sync::CancellationToken;

/// How often the log is checkpointed.
const PERIOD: Duration = Duration::from_millis(200);

/// Log pages past which the checkpointer waits for the writer's turn to
/// copy the rest, so that the log is rewound (about 16 MB).
const REWIND_PAGES: i64 = 4_096;

/// Bytes a rewound log file is cut back to (`journal_size_limit`).
pub(super) const LOG_LIMIT_BYTES: i64 = 64 << 20;

/// The right to write to the database: every writer holds it for its
/// transaction, the checkpointer to copy the log while nobody appends.
pub(super) type WriterTurn = Arc<tokio::sync::Mutex<()>>;

/// The checkpointing task of a store.
#[derive(Debug)]
pub(super) struct Checkpointer {
    stop: CancellationToken,
    task: tokio::task::JoinHandle<()>,
}

impl Checkpointer {
    /// Checkpoints `pool`'s database every [`PERIOD`] until stopped.
    pub(super) fn start(pool: SqlitePool, turn: WriterTurn) -> Self {
        let stop = CancellationToken::new();
        Self { task: tokio::spawn(run(pool, turn, stop.clone())), stop }
    }

    /// Stops, after the checkpoint under way if any.
    pub(super) async fn stop(self) {
        self.stop.cancel();
        let _ = self.task.await;
    }
}

async fn run(pool: SqlitePool, turn: WriterTurn, stop: CancellationToken) {
    let mut tick = tokio::time::interval(PERIOD);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tokio::select! {
            () = stop.cancelled() => return,
            _ = tick.tick() => {}
        }
        if let Err(e) = checkpoint_and_rewind(&pool, &turn).await {
            tracing::warn!(error = %e, "WAL checkpoint failed; tried again shortly");
        }
    }
}

/// One checkpoint beside the writer and, if the log has grown past
/// [`REWIND_PAGES`], another in the writer's turn.
async fn checkpoint_and_rewind(pool: &SqlitePool, turn: &WriterTurn) -> Result<(), sqlx::Error> {
    if checkpoint(pool).await?.is_some_and(|log| log > REWIND_PAGES) {
        let _writer = turn.lock().await;
        checkpoint(pool).await?;
    }
    Ok(())
}

/// Runs one PASSIVE checkpoint; the log's size in pages, or `None` if it
/// could not run because another connection was checkpointing (SQLite then
/// reports a log of -1 pages, which must not read as an empty log).
async fn checkpoint(pool: &SqlitePool) -> Result<Option<i64>, sqlx::Error> {
    // (busy, log pages, pages checkpointed)
    let (busy, log, _): (i64, i64, i64) = sqlx::query_as("PRAGMA wal_checkpoint(PASSIVE)").fetch_one(pool).await?;
    Ok((busy == 0).then_some(log))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::store::Store;
    use crate::store::sqlite::Durability;
    use crate::store::sqlite::tests::store_with_mission;
    use crate::store::suite::note;

    /// The log's size in pages, from a checkpoint that ran: the store's own
    /// checkpointer, every [`PERIOD`], may be copying when the test asks.
    async fn log_pages(pool: &SqlitePool) -> i64 {
        loop {
            if let Some(log) = checkpoint(pool).await.unwrap() {
                return log;
            }
            tokio::task::yield_now().await;
        }
    }

    /// With SQLite's own checkpoints turned off, the log stays bounded by
    /// ours: it is rewound after each, however much is written.
    #[tokio::test]
    async fn the_log_is_rewound_after_each_checkpoint() {
        let dir = tempfile::tempdir().unwrap();
        let (store, mission) = store_with_mission(&dir.path().join("wal.db"), Durability::Full).await;
        let wal = dir.path().join("wal.db-wal");
        let mut sizes = Vec::new();
        for round in 0..6 {
            for i in 0..200 {
                let detail = format!("round {round}, event {i}: {}", "x".repeat(500));
                store.commit(note(mission.id, i, detail)).await.unwrap();
            }
            let size = std::fs::metadata(&wal).unwrap().len();
            // The file, not the frames our checkpoint sees: the background
            // checkpointer (every 200 ms) may have just rewound the log.
            assert!(size > 0, "round {round} wrote to the log");
            sizes.push(size);
            log_pages(&store.backend().pool).await;
        }
        // Unchecked, six rounds would make it six times the first round's
        // size (the background checkpoints may also have rewound it).
        assert!(sizes[5] <= 2 * sizes[0], "the log grew from {} to {} bytes: {sizes:?}", sizes[0], sizes[5]);
        assert_eq!(store.events(mission.id, 0, u32::MAX).await.unwrap().len(), 1200);
    }

    /// A reader that keeps an old snapshot pins the log: no checkpoint can
    /// copy past it, however large the log grows. Checkpoints in the
    /// writer's turn must then neither stall the committer nor wait for the
    /// reader, and once the reader is gone the log is rewound.
    #[tokio::test]
    async fn a_reader_pinning_the_log_holds_up_no_commit() {
        use sqlx::Connection;
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("pinned.db");
        let (store, mission) = store_with_mission(&path, Durability::Normal).await;
        let mut reader = sqlx::SqliteConnection::connect(&format!("sqlite:{}", path.display())).await.unwrap();
        sqlx::query("BEGIN").execute(&mut reader).await.unwrap();
        let _: i64 = sqlx::query_scalar("SELECT COUNT(*) FROM missions").fetch_one(&mut reader).await.unwrap();

        let big = "x".repeat(64 << 10);
        for i in 0..300 {
            store.commit(note(mission.id, i, big.clone())).await.unwrap();
        }
        let turn = store.backend().turn.clone();
        assert!(log_pages(&store.backend().pool).await > REWIND_PAGES, "the log passed the rewinding size");
        let checkpoints = tokio::spawn({
            let (pool, turn) = (store.backend().pool.clone(), turn.clone());
            async move {
                for _ in 0..20 {
                    checkpoint_and_rewind(&pool, &turn).await.unwrap();
                }
            }
        });
        for i in 300..320 {
            let committed = tokio::time::timeout(Duration::from_secs(2), store.commit(note(mission.id, i, "y".into())));
            committed.await.expect("a commit waited for the reader").unwrap();
        }
        checkpoints.await.unwrap();

        sqlx::query("COMMIT").execute(&mut reader).await.unwrap();
        // What checkpoint_and_rewind does in the writer's turn, made sure to
        // run rather than meet the store's own checkpointer copying.
        {
            let _writer = turn.lock().await;
            log_pages(&store.backend().pool).await;
        }
        store.commit(note(mission.id, 320, "z".into())).await.unwrap();
        let log = log_pages(&store.backend().pool).await;
        assert!(log < 16, "the log was not rewound once the reader had gone: {log} pages");
        assert_eq!(store.events(mission.id, 0, u32::MAX).await.unwrap().len(), 321);
    }
}
