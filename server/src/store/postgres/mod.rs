//! The PostgreSQL store: the same tables, queries and group commit as
//! SQLite's ([`crate::store::sql`]), on a server that other machines reach.
//!
//! Chosen by a `postgres://` (or `postgresql://`) database URL. Its schema
//! is `migrations/postgres`, applied at start under sqlx's migration lock.
//! One executive uses a database at a time, as with SQLite, unless it is
//! one of several replicas that share it (which divide the missions through
//! leases, [`crate::store::lease`]): it holds a session advisory lock
//! ([`EXECUTIVE_LOCK`]) on a connection of its own for as long as it runs,
//! which the server releases when that connection ends, however the
//! executive ended. Replicas take it shared, so that neither a lone
//! executive joins replicas nor replicas join a lone executive.

use std::path::{Path, PathBuf};
use std::str::FromStr;
use std::sync::Arc;
use std::time::Duration;

use async_trait::async_trait;
use sqlx::postgres::{PgConnectOptions, PgConnection, PgPool, PgPoolOptions, PgRow};
use sqlx::{AssertSqlSafe, ConnectOptions, Connection, Postgres};

use super::StoreError;
use super::sql::SqlStore;
use super::sql::pooled::{Engine, PooledTx};
use super::sql::statement::{Backend, Statement};

static MIGRATOR: sqlx::migrate::Migrator = sqlx::migrate!("../migrations/postgres");

/// The advisory lock key an executive holds on its database ("explore!").
pub const EXECUTIVE_LOCK: i64 = 0x6578_706c_6f72_6521;

/// Missions, robots, tasks and the map log in a PostgreSQL database.
pub type PostgresStore = SqlStore<PostgresBackend>;

/// PostgreSQL under the store.
#[derive(Debug)]
pub struct PostgresBackend {
    pool: PgPool,
    /// The URL without its password, for messages.
    shown: String,
    /// Writers take turns, as with SQLite: a changeset prepared after
    /// another is written after it.
    turn: Arc<tokio::sync::Mutex<()>>,
    /// The connection holding [`EXECUTIVE_LOCK`]; closed at close.
    lock: tokio::sync::Mutex<Option<PgConnection>>,
}

impl SqlStore<PostgresBackend> {
    /// Connects to the database at `url` and applies migrations; refused
    /// while another executive holds it (alone, or `shared` by replicas
    /// when this one is not one of them).
    pub async fn open(
        url: &str,
        shared: bool,
        metrics: Option<Arc<crate::metrics::Metrics>>,
    ) -> Result<Self, StoreError> {
        let options = PgConnectOptions::from_str(url)?
            .application_name(&holder())
            // A statement that hangs (a lock nobody releases) fails instead.
            .options([("statement_timeout", "30s"), ("lock_timeout", "10s")]);
        let shown = without_password(url);
        let mut lock = options.connect().await?;
        take_executive_lock(&mut lock, &shown, shared).await?;
        let pool = PgPoolOptions::new()
            .max_connections(8)
            .acquire_timeout(Duration::from_secs(10))
            .connect_with(options)
            .await?;
        MIGRATOR.run(&pool).await?;
        let backend = PostgresBackend { pool, shown, turn: Arc::default(), lock: tokio::sync::Mutex::new(Some(lock)) };
        Ok(SqlStore::new(backend, metrics))
    }

    /// The database's URL, without its password.
    pub fn shown(&self) -> &str {
        &self.backend().shown
    }
}

/// Who this executive is, as the database sees it (`application_name`).
fn holder() -> String {
    format!("coordinator pid {} on {}", std::process::id(), super::lock::hostname())
}

/// `url` without its password and query (which may hold one too): for
/// messages and logs.
pub fn without_password(url: &str) -> String {
    let Some((scheme, rest)) = url.split_once("://") else { return "(a database URL)".to_owned() };
    let rest = rest.split('?').next().unwrap_or_default();
    match rest.rsplit_once('@') {
        Some((user_info, host_and_path)) => {
            let hidden = if user_info.contains(':') { ":***" } else { "" };
            let user = user_info.split(':').next().unwrap_or_default();
            format!("{scheme}://{user}{hidden}@{host_and_path}")
        }
        None => format!("{scheme}://{rest}"),
    }
}

/// Takes [`EXECUTIVE_LOCK`] on `conn` (`shared` among replicas), or says who holds it.
async fn take_executive_lock(conn: &mut PgConnection, shown: &str, shared: bool) -> Result<(), StoreError> {
    let take = if shared { "SELECT pg_try_advisory_lock_shared($1)" } else { "SELECT pg_try_advisory_lock($1)" };
    let taken: bool = sqlx::query_scalar(take).bind(EXECUTIVE_LOCK).fetch_one(&mut *conn).await?;
    if taken {
        return Ok(());
    }
    let holder: Option<String> = sqlx::query_scalar(
        "SELECT a.application_name FROM pg_locks l JOIN pg_stat_activity a ON a.pid = l.pid
         WHERE l.locktype = 'advisory' AND l.granted AND l.database = (SELECT oid FROM pg_database
               WHERE datname = current_database())
           AND ((l.classid::bigint << 32) | l.objid::bigint) = $1",
    )
    .bind(EXECUTIVE_LOCK)
    .fetch_optional(&mut *conn)
    .await?;
    let holder = holder.filter(|h| !h.is_empty()).unwrap_or_else(|| "an unknown session".to_owned());
    let (this, other) = if shared {
        ("this replica", "an executive that is not a replica")
    } else {
        ("this executive", "another executive")
    };
    Err(StoreError::Locked(format!(
        "the database {shown} is in use by {other} ({holder}; PostgreSQL advisory lock {EXECUTIVE_LOCK}), so \
         {this} cannot use it: stop the other, or give this one another database"
    )))
}

/// Creates the database `name` (dropping one of that name first) on the
/// server `server_url` names, and returns its URL: a fresh database for a
/// test. `server_url` must end in `/database` (any existing one).
pub async fn fresh_database(server_url: &str, name: &str) -> Result<String, StoreError> {
    let bad = |why: &str| StoreError::Path(format!("{}: {why}", without_password(server_url)));
    if name.is_empty() || !name.bytes().all(|b| b.is_ascii_lowercase() || b.is_ascii_digit() || b == b'_') {
        return Err(bad(&format!("{name:?} is not a plain database name")));
    }
    let (server, _) =
        server_url.rsplit_once('/').filter(|(s, _)| s.contains("://")).ok_or_else(|| bad("no database"))?;
    let mut admin = PgConnection::connect(server_url).await?;
    // The name is checked above: plain letters, digits and underscores.
    sqlx::query(AssertSqlSafe(format!("DROP DATABASE IF EXISTS {name} WITH (FORCE)"))).execute(&mut admin).await?;
    sqlx::query(AssertSqlSafe(format!("CREATE DATABASE {name}"))).execute(&mut admin).await?;
    admin.close().await?;
    Ok(format!("{server}/{name}"))
}

/// For tests: a fresh database `name` on the server that
/// `EXPLORATION_POSTGRES_URL` names (`.ci/run` starts one and sets it);
/// `None`, and a line saying what is skipped, where it is not set.
pub async fn test_database(name: &str) -> Option<String> {
    let Ok(server) = std::env::var("EXPLORATION_POSTGRES_URL") else {
        eprintln!(
            "SKIPPED {name} on PostgreSQL: set EXPLORATION_POSTGRES_URL to a server's URL (.ci/run starts one and \
             sets it) to run it"
        );
        return None;
    };
    Some(fresh_database(&server, name).await.unwrap_or_else(|e| panic!("a test database on {server}: {e}")))
}

#[async_trait]
impl Backend for PostgresBackend {
    type Row = PgRow;
    type Tx = PooledTx<Postgres>;

    async fn fetch_all(&self, statement: Statement) -> Result<Vec<PgRow>, StoreError> {
        Ok(Postgres::query(statement).fetch_all(&self.pool).await?)
    }

    async fn fetch_optional(&self, statement: Statement) -> Result<Option<PgRow>, StoreError> {
        Ok(Postgres::query(statement).fetch_optional(&self.pool).await?)
    }

    async fn begin_write(&self) -> Result<PooledTx<Postgres>, StoreError> {
        let turn = Arc::clone(&self.turn).lock_owned().await;
        PooledTx::begin(self.pool.acquire().await?, "BEGIN", Some(turn)).await
    }

    async fn begin_read(&self) -> Result<PooledTx<Postgres>, StoreError> {
        // READ COMMITTED would let each statement see a later moment.
        PooledTx::begin(self.pool.acquire().await?, "BEGIN ISOLATION LEVEL REPEATABLE READ READ ONLY", None).await
    }

    async fn backup(&self, _path: &Path) -> Result<(), StoreError> {
        Err(StoreError::Unsupported(format!(
            "the store is the PostgreSQL database {}: back it up with PostgreSQL's tools (pg_dump, or the \
             provider's snapshots), which copy it consistently while the executive runs",
            self.shown
        )))
    }

    fn backup_dir(&self) -> PathBuf {
        std::env::temp_dir()
    }

    async fn close(&self) {
        self.pool.close().await;
        if let Some(lock) = self.lock.lock().await.take() {
            let _ = lock.close().await;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::store::Store;

    /// The database password crosses the network: the store speaks TLS to
    /// the server and checks its certificate (`sslmode=verify-full`),
    /// refusing one that its CA did not sign. Needs a server with TLS and
    /// its CA in `EXPLORATION_POSTGRES_CA` (`.ci/run` makes both).
    #[tokio::test]
    async fn the_store_speaks_tls_to_postgres_and_checks_the_certificate() {
        let Some(url) = test_database("store_tls").await else { return };
        let Ok(ca) = std::env::var("EXPLORATION_POSTGRES_CA") else {
            eprintln!("SKIPPED store_tls: set EXPLORATION_POSTGRES_CA to the CA of the server's TLS certificate");
            return;
        };
        let verified = format!("{url}?sslmode=verify-full&sslrootcert={ca}");
        let store = PostgresStore::open(&verified, false, None).await.unwrap();
        assert!(store.missions().await.unwrap().is_empty());
        // Backups are PostgreSQL's own tools' to make: refused, saying so.
        let refused = store.backup(Path::new("/tmp/never-written.db")).await.unwrap_err();
        assert!(matches!(&refused, StoreError::Unsupported(why) if why.contains("pg_dump")), "{refused}");
        store.close().await;
        // Other CAs (the system's), none of which signed the server's certificate.
        let refused = PostgresStore::open(&format!("{url}?sslmode=verify-full"), false, None).await;
        let err = refused.expect_err("a server whose certificate no trusted CA signed was trusted");
        assert!(err.to_string().contains("certificate"), "{err}");
    }

    #[test]
    fn passwords_never_leave_the_url() {
        assert_eq!(
            without_password("postgres://ann:s3cret@db.example:5432/fleet?sslmode=require"),
            "postgres://ann:***@db.example:5432/fleet"
        );
        assert_eq!(without_password("postgresql://ann@localhost/fleet"), "postgresql://ann@localhost/fleet");
        assert_eq!(without_password("postgres://localhost"), "postgres://localhost");
        assert_eq!(without_password("postgres://a:b:c@h/d"), "postgres://a:***@h/d");
        assert_eq!(without_password("not a url s3cret"), "(a database URL)");
    }
}
