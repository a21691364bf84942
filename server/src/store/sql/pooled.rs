//! Statements run on sqlx's pools and pooled connections, the same way for
//! both engines; an [`Engine`] says only how its statements are written and
//! what a result counts.

use async_trait::async_trait;
use sqlx::pool::PoolConnection;
use sqlx::{AssertSqlSafe, Database, Encode, Executor, Type};

use super::statement::{Columns, Param, Statement, Transaction};
use crate::store::StoreError;

/// A database engine of sqlx's that the store runs on.
pub trait Engine: Database
where
    Option<i64>: for<'q> Encode<'q, Self> + Type<Self>,
    Option<f64>: for<'q> Encode<'q, Self> + Type<Self>,
    Option<String>: for<'q> Encode<'q, Self> + Type<Self>,
    Vec<u8>: for<'q> Encode<'q, Self> + Type<Self>,
{
    /// The statement's text as this engine reads it.
    fn text(statement: &Statement) -> std::borrow::Cow<'static, str>;

    /// How many rows a statement changed.
    fn rows_affected(result: &Self::QueryResult) -> u64;

    /// `statement` as sqlx's query, its parameters bound.
    fn query(statement: Statement) -> sqlx::query::Query<'static, Self, <Self as Database>::Arguments> {
        let mut query = sqlx::query(AssertSqlSafe(Self::text(&statement)));
        for param in statement.params {
            query = match param {
                Param::Int(v) => query.bind(v),
                Param::Real(v) => query.bind(v),
                Param::Text(v) => query.bind(v),
                Param::Bytes(v) => query.bind(v),
            };
        }
        query
    }
}

impl Engine for sqlx::Sqlite {
    fn text(statement: &Statement) -> std::borrow::Cow<'static, str> {
        // SQLite reads both `$N` and positional `?`.
        statement.text.clone()
    }

    fn rows_affected(result: &sqlx::sqlite::SqliteQueryResult) -> u64 {
        result.rows_affected()
    }
}

impl Engine for sqlx::Postgres {
    fn text(statement: &Statement) -> std::borrow::Cow<'static, str> {
        statement.numbered()
    }

    fn rows_affected(result: &sqlx::postgres::PgQueryResult) -> u64 {
        result.rows_affected()
    }
}

/// A transaction on a pooled connection of its own, holding the writers'
/// turn when it writes.
#[derive(Debug)]
pub struct PooledTx<DB: Database> {
    conn: PoolConnection<DB>,
    _turn: Option<tokio::sync::OwnedMutexGuard<()>>,
    committed: bool,
}

impl<DB: Database> PooledTx<DB>
where
    for<'c> &'c mut DB::Connection: Executor<'c, Database = DB>,
{
    /// Runs `begin` on `conn`; the connection is closed if that fails.
    pub async fn begin(
        mut conn: PoolConnection<DB>,
        begin: &'static str,
        turn: Option<tokio::sync::OwnedMutexGuard<()>>,
    ) -> Result<Self, StoreError> {
        if let Err(e) = (&mut *conn).execute(begin).await {
            conn.close_on_drop();
            return Err(e.into());
        }
        Ok(Self { conn, _turn: turn, committed: false })
    }
}

impl<DB: Database> Drop for PooledTx<DB> {
    fn drop(&mut self) {
        // Closing the connection rolls back whatever is still open: after a
        // full disk SQLite may or may not have rolled back by itself, and
        // sqlx's count of open transactions may be off.
        if !self.committed {
            self.conn.close_on_drop();
        }
    }
}

#[async_trait]
impl<DB: Engine> Transaction for PooledTx<DB>
where
    Option<i64>: for<'q> Encode<'q, DB> + Type<DB>,
    Option<f64>: for<'q> Encode<'q, DB> + Type<DB>,
    Option<String>: for<'q> Encode<'q, DB> + Type<DB>,
    Vec<u8>: for<'q> Encode<'q, DB> + Type<DB>,
    for<'c> &'c mut DB::Connection: Executor<'c, Database = DB>,
    <DB as Database>::Arguments: sqlx::IntoArguments<DB>,
    DB::Row: Columns,
{
    type Row = DB::Row;

    async fn execute(&mut self, statement: Statement) -> Result<u64, StoreError> {
        Ok(DB::rows_affected(&DB::query(statement).execute(&mut *self.conn).await?))
    }

    async fn fetch_all(&mut self, statement: Statement) -> Result<Vec<DB::Row>, StoreError> {
        Ok(DB::query(statement).fetch_all(&mut *self.conn).await?)
    }

    async fn fetch_one(&mut self, statement: Statement) -> Result<DB::Row, StoreError> {
        Ok(DB::query(statement).fetch_one(&mut *self.conn).await?)
    }

    async fn commit(mut self) -> Result<(), StoreError> {
        (&mut *self.conn).execute("COMMIT").await?;
        self.committed = true;
        Ok(())
    }
}
