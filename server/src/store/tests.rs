//! Where a store is, as `--db` names it.

use super::{Location, sqlite::Durability};

/// Files, SQLite URLs and PostgreSQL URLs are stores; another database's
/// URL is refused when opened, and neither the refusal nor the location
/// shows its password.
#[tokio::test]
async fn other_databases_urls_are_refused_without_their_password() {
    assert_eq!(Location::parse("/var/lib/x.db"), Location::Sqlite("/var/lib/x.db".into()));
    assert_eq!(Location::parse("sqlite:///var/lib/x.db"), Location::Sqlite("/var/lib/x.db".into()));
    assert_eq!(Location::parse("./a://b.db"), Location::Sqlite("./a://b.db".into()), "`./a` is no scheme");
    assert!(matches!(Location::parse("postgresql://h/fleet"), Location::Postgres(_)));
    let location = Location::parse("mysql://ann:s3cret@db.example/fleet");
    assert!(matches!(location, Location::Unsupported(_)), "{location:?}");
    let Err(error) = location.open(Durability::Full, false, None).await else { panic!("mysql:// opened") };
    let said = format!("could not open the store {location}: {error}");
    assert_eq!(
        said,
        "could not open the store mysql://ann:***@db.example/fleet: mysql:// is not a store this executive has: \
         give a SQLite file or a postgres:// URL"
    );
}
