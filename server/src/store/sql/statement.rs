//! What the SQL of the store needs from a database, in terms both engines
//! speak: statements with `$1 … $N` parameters (PostgreSQL's form; SQLite
//! reads `$N` as the N-th parameter too), values of four kinds, rows read
//! by column name, and transactions.
//!
//! The store's queries and writes are written once against these
//! ([`super::SqlStore`], [`super::write`], [`super::rows`]); each engine
//! says how to run them ([`crate::store::sqlite`], [`crate::store::postgres`]).

use std::borrow::Cow;
use std::path::{Path, PathBuf};

use async_trait::async_trait;

use crate::store::StoreError;

/// A value bound to a statement. Integers are `BIGINT`, reals `DOUBLE
/// PRECISION`, in both engines' schemas.
#[derive(Debug, Clone, PartialEq)]
pub enum Param {
    /// An integer, or NULL.
    Int(Option<i64>),
    /// A real, or NULL.
    Real(Option<f64>),
    /// A text, or NULL.
    Text(Option<String>),
    /// Bytes.
    Bytes(Vec<u8>),
}

/// SQL text with its parameters.
#[derive(Debug, Clone, PartialEq)]
pub struct Statement {
    /// The SQL, parameters written `$1 … $N`, or `?` when `positional`.
    pub text: Cow<'static, str>,
    /// The parameters, in order.
    pub params: Vec<Param>,
    /// Parameters written `?`, each bound once, in order of appearance.
    pub positional: bool,
}

impl Statement {
    /// `text`, parameters written `$1 … $N`, with none bound yet.
    pub fn new(text: impl Into<Cow<'static, str>>) -> Self {
        Self { text: text.into(), params: Vec::new(), positional: false }
    }

    /// `text`, parameters written `?`, with none bound yet: for statements
    /// of thousands of parameters (many rows in one), because SQLite finds a
    /// numbered parameter's name by walking a list of them all, which made
    /// binding a 4 096-parameter statement quadratic (2 % of the
    /// executive's time at a thousand robots' map updates). PostgreSQL,
    /// which knows only `$N`, is given them numbered ([`Statement::numbered`]).
    pub fn positional(text: impl Into<Cow<'static, str>>) -> Self {
        Self { positional: true, ..Self::new(text) }
    }

    /// The text with its parameters written `$1 … $N`. A positional
    /// statement's text holds no `?` but its parameters (it is written by
    /// the store, never from input).
    pub fn numbered(&self) -> Cow<'static, str> {
        if !self.positional {
            return self.text.clone();
        }
        let mut numbered = String::with_capacity(self.text.len() + 4 * self.params.len());
        for (n, part) in self.text.split('?').enumerate() {
            if n > 0 {
                numbered.push('$');
                numbered.push_str(&n.to_string());
            }
            numbered.push_str(part);
        }
        Cow::Owned(numbered)
    }

    /// Binds the next parameter to an integer (or NULL).
    pub fn int(mut self, value: impl Into<Option<i64>>) -> Self {
        self.params.push(Param::Int(value.into()));
        self
    }

    /// Binds the next parameter to a real (or NULL).
    pub fn real(mut self, value: impl Into<Option<f64>>) -> Self {
        self.params.push(Param::Real(value.into()));
        self
    }

    /// Binds the next parameter to a text.
    pub fn text(self, value: &str) -> Self {
        self.maybe_text(Some(value))
    }

    /// Binds the next parameter to a text, or NULL.
    pub fn maybe_text(mut self, value: Option<&str>) -> Self {
        self.params.push(Param::Text(value.map(str::to_owned)));
        self
    }

    /// Binds the next parameter to bytes.
    pub fn bytes(mut self, value: Vec<u8>) -> Self {
        self.params.push(Param::Bytes(value));
        self
    }
}

/// A type a column can be read as in either engine.
pub trait Value:
    for<'r> sqlx::Decode<'r, sqlx::Sqlite>
    + sqlx::Type<sqlx::Sqlite>
    + for<'r> sqlx::Decode<'r, sqlx::Postgres>
    + sqlx::Type<sqlx::Postgres>
{
}

impl<T> Value for T where
    T: for<'r> sqlx::Decode<'r, sqlx::Sqlite>
        + sqlx::Type<sqlx::Sqlite>
        + for<'r> sqlx::Decode<'r, sqlx::Postgres>
        + sqlx::Type<sqlx::Postgres>
{
}

/// A row, read by column name.
pub trait Columns {
    /// The column `name` as a `T`.
    fn value<T: Value>(&self, name: &str) -> Result<T, sqlx::Error>;
}

impl Columns for sqlx::sqlite::SqliteRow {
    fn value<T: Value>(&self, name: &str) -> Result<T, sqlx::Error> {
        sqlx::Row::try_get(self, name)
    }
}

impl Columns for sqlx::postgres::PgRow {
    fn value<T: Value>(&self, name: &str) -> Result<T, sqlx::Error> {
        sqlx::Row::try_get(self, name)
    }
}

/// An open transaction. Dropped without [`Transaction::commit`], it writes
/// nothing, and its connection is closed rather than reused: after a
/// failure (a full disk, a lost server) nobody can vouch for the state the
/// connection was left in.
#[async_trait]
pub trait Transaction: Send {
    /// The engine's rows.
    type Row: Columns + Send;

    /// Runs a statement that returns no rows; how many rows it changed.
    async fn execute(&mut self, statement: Statement) -> Result<u64, StoreError>;

    /// Every row a statement returns.
    async fn fetch_all(&mut self, statement: Statement) -> Result<Vec<Self::Row>, StoreError>;

    /// The one row a statement returns.
    async fn fetch_one(&mut self, statement: Statement) -> Result<Self::Row, StoreError>;

    /// Makes the transaction durable (as durable as the engine was set to).
    async fn commit(self) -> Result<(), StoreError>;
}

/// A database engine the store runs on.
#[async_trait]
pub trait Backend: Send + Sync + std::fmt::Debug + 'static {
    /// Its rows.
    type Row: Columns + Send;
    /// Its transactions.
    type Tx: Transaction<Row = Self::Row>;

    /// Every row a statement returns, read outside any transaction.
    async fn fetch_all(&self, statement: Statement) -> Result<Vec<Self::Row>, StoreError>;

    /// The row a statement returns, if any, read outside any transaction.
    async fn fetch_optional(&self, statement: Statement) -> Result<Option<Self::Row>, StoreError>;

    /// A transaction that writes. Writers take turns: one writes at a time.
    async fn begin_write(&self) -> Result<Self::Tx, StoreError>;

    /// A transaction whose reads all see the database at one moment.
    async fn begin_read(&self) -> Result<Self::Tx, StoreError>;

    /// Writes a consistent copy of the whole store to a new file at `path`.
    async fn backup(&self, path: &Path) -> Result<(), StoreError>;

    /// Where a backup may be written for a while.
    fn backup_dir(&self) -> PathBuf;

    /// Closes every connection and lets go of the database.
    async fn close(&self);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn positional_parameters_are_numbered_for_postgres() {
        let statement = Statement::positional("INSERT INTO t VALUES (?, ?), ((SELECT 1 WHERE ? > 0), ?)");
        assert_eq!(statement.numbered(), "INSERT INTO t VALUES ($1, $2), ((SELECT 1 WHERE $3 > 0), $4)");
        let numbered = Statement::new("SELECT $1, $1");
        assert_eq!(numbered.numbered(), "SELECT $1, $1", "numbered text is left as it is");
    }
}
