//! The SQLite store: one file, WAL journal, migrations embedded at build
//! time, held by one executive at a time ([`StoreLock`]), checkpointed
//! beside the writes ([`checkpoint`]).

mod checkpoint;

use std::path::{Path, PathBuf};
use std::str::FromStr;
use std::sync::Arc;
use std::time::Duration;

use async_trait::async_trait;
use sqlx::Sqlite;
use sqlx::sqlite::{
    SqliteConnectOptions, SqliteJournalMode, SqlitePool, SqlitePoolOptions, SqliteRow, SqliteSynchronous,
};

use super::StoreError;
use super::lock::StoreLock;
use super::sql::SqlStore;
use super::sql::pooled::{Engine, PooledTx};
use super::sql::statement::{Backend, Statement};

static MIGRATOR: sqlx::migrate::Migrator = sqlx::migrate!("../migrations/sqlite");

/// How hard SQLite works to keep a commit across failures.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Durability {
    /// Every commit survives a power cut (`synchronous = FULL`).
    #[default]
    Full,
    /// Every commit survives a crash of the process, the last ones may not
    /// survive a power cut (`synchronous = NORMAL`, safe in WAL mode).
    Normal,
}

/// Missions, robots, tasks and the map log in one SQLite file.
pub type SqliteStore = SqlStore<SqliteBackend>;

/// SQLite under the store: its pool, its file, its lock and its checkpointer.
#[derive(Debug)]
pub struct SqliteBackend {
    pool: SqlitePool,
    path: PathBuf,
    /// Held by every writer for its transaction, and by the checkpointer
    /// to rewind the log.
    turn: checkpoint::WriterTurn,
    /// The checkpointer (see [`checkpoint`]) and how to stop it; taken at close.
    checkpointer: std::sync::Mutex<Option<checkpoint::Checkpointer>>,
    /// Held until the store is closed or dropped.
    lock: std::sync::Mutex<Option<StoreLock>>,
}

impl SqlStore<SqliteBackend> {
    /// Opens (creating if needed) the database at `path` and applies
    /// migrations; refused while another executive holds it.
    pub async fn open(path: &Path, durability: Durability) -> Result<Self, StoreError> {
        Self::open_measured(path, durability, None).await
    }

    /// [`SqliteStore::open`], with commit latency and group sizes counted in `metrics`.
    pub async fn open_measured(
        path: &Path,
        durability: Durability,
        metrics: Option<Arc<crate::metrics::Metrics>>,
    ) -> Result<Self, StoreError> {
        check_path(path)?;
        let lock = StoreLock::acquire(path)?;
        let options = SqliteConnectOptions::from_str("sqlite:")?
            .filename(path)
            .create_if_missing(true)
            .journal_mode(SqliteJournalMode::Wal)
            .synchronous(match durability {
                Durability::Full => SqliteSynchronous::Full,
                Durability::Normal => SqliteSynchronous::Normal,
            })
            .foreign_keys(true)
            // Checkpoints run beside the writes, not inside them (see `checkpoint`).
            .pragma("wal_autocheckpoint", "0")
            .pragma("journal_size_limit", checkpoint::LOG_LIMIT_BYTES.to_string())
            .busy_timeout(Duration::from_secs(5));
        let pool = SqlitePoolOptions::new().max_connections(4).connect_with(options).await?;
        MIGRATOR.run(&pool).await?;
        let turn = checkpoint::WriterTurn::default();
        let checkpointer = checkpoint::Checkpointer::start(pool.clone(), turn.clone());
        let backend = SqliteBackend {
            pool,
            path: path.to_owned(),
            turn,
            checkpointer: std::sync::Mutex::new(Some(checkpointer)),
            lock: std::sync::Mutex::new(Some(lock)),
        };
        Ok(SqlStore::new(backend, metrics))
    }

    /// The database file.
    pub fn path(&self) -> &Path {
        &self.backend().path
    }
}

#[async_trait]
impl Backend for SqliteBackend {
    type Row = SqliteRow;
    type Tx = PooledTx<Sqlite>;

    async fn fetch_all(&self, statement: Statement) -> Result<Vec<SqliteRow>, StoreError> {
        Ok(Sqlite::query(statement).fetch_all(&self.pool).await?)
    }

    async fn fetch_optional(&self, statement: Statement) -> Result<Option<SqliteRow>, StoreError> {
        Ok(Sqlite::query(statement).fetch_optional(&self.pool).await?)
    }

    async fn begin_write(&self) -> Result<PooledTx<Sqlite>, StoreError> {
        let turn = Arc::clone(&self.turn).lock_owned().await;
        // IMMEDIATE: take SQLite's write lock now, not halfway through.
        PooledTx::begin(self.pool.acquire().await?, "BEGIN IMMEDIATE", Some(turn)).await
    }

    async fn begin_read(&self) -> Result<PooledTx<Sqlite>, StoreError> {
        // DEFERRED: the first read fixes the snapshot every later one sees.
        PooledTx::begin(self.pool.acquire().await?, "BEGIN", None).await
    }

    async fn backup(&self, path: &Path) -> Result<(), StoreError> {
        // VACUUM INTO copies a consistent snapshot (one read transaction)
        // while writers go on, and refuses to overwrite an existing file.
        let target = path.to_str().ok_or_else(|| StoreError::LockFile {
            path: path.to_owned(),
            cause: std::io::Error::new(std::io::ErrorKind::InvalidInput, "the path is not UTF-8"),
        })?;
        sqlx::query("VACUUM INTO $1").bind(target).execute(&self.pool).await?;
        Ok(())
    }

    fn backup_dir(&self) -> PathBuf {
        match self.path.parent() {
            Some(dir) if !dir.as_os_str().is_empty() => dir.to_owned(),
            _ => PathBuf::from("."),
        }
    }

    async fn close(&self) {
        let checkpointer = self.checkpointer.lock().unwrap_or_else(|e| e.into_inner()).take();
        if let Some(checkpointer) = checkpointer {
            checkpointer.stop().await;
        }
        self.pool.close().await;
        self.lock.lock().unwrap_or_else(|e| e.into_inner()).take();
    }
}

/// Refuses what is not a database file SQLite can keep across restarts: an
/// in-memory database (each pooled connection would get its own, and all of
/// it would be lost), a folder, or a file in a folder that does not exist.
fn check_path(path: &Path) -> Result<(), StoreError> {
    let text = path.to_string_lossy();
    let bad = |why: String| Err(StoreError::Path(format!("--db {}: {why}", path.display())));
    if text.is_empty() || text == ":memory:" || text.starts_with("file:") || text.contains("mode=memory") {
        return bad("the executive keeps everything it acknowledges in a database file: give a file path".to_owned());
    }
    if path.is_dir() {
        return bad("is a folder; give a file in it (created if missing)".to_owned());
    }
    // A device or a pipe (`/dev/null`) cannot hold a database, and its lock
    // file would land in /dev.
    if path.exists() && !path.is_file() {
        return bad("is not a regular file (a device or a pipe); give a database file (created if missing)".to_owned());
    }
    match path.parent().filter(|p| !p.as_os_str().is_empty()) {
        Some(dir) if !dir.is_dir() => bad(format!("the folder {} does not exist", dir.display())),
        _ => Ok(()),
    }
}

#[cfg(test)]
mod tests;
