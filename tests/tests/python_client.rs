//! The Python client package (clients/python) passes its own tests, run with
//! pytest against this workspace's `coordinator` binary.
//!
//! Runs where `EXPLORATION_PYTHON` names a Python that has the package and
//! pytest installed (`.ci/run` makes such a virtual environment); elsewhere
//! it says it is skipped. Where `EXPLORATION_POSTGRES_URL` names a
//! PostgreSQL server, the client's replica test gets a fresh database of it
//! (`EXPLORATION_REPLICAS_DB`); only that test may be skipped without one.
//! The TLS tests get certificates made here (`EXPLORATION_TLS_DIR`).

mod common;

use std::path::Path;
use std::process::Command;

#[tokio::test]
async fn the_python_client_passes_its_tests_against_the_real_executive() {
    let Some(python) = std::env::var_os("EXPLORATION_PYTHON") else {
        eprintln!(
            "SKIPPED: the Python client's tests need EXPLORATION_PYTHON, a Python with clients/python[test] \
             installed (.ci/run creates one)"
        );
        return;
    };
    let replicas_db = common::postgres_database("python_replicas").await;
    let certificates = tempfile::tempdir().unwrap();
    common::Pki::new(certificates.path());
    let repository = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let mut pytest = Command::new(&python);
    pytest
        .args(["-m", "pytest", "-q", "-rs", "-p", "no:cacheprovider", "clients/python/tests"])
        .current_dir(&repository)
        .env("COORDINATOR_BIN", common::binary("coordinator"))
        .env("EXPLORATION_TLS_DIR", certificates.path());
    if let Some(url) = &replicas_db {
        pytest.env("EXPLORATION_REPLICAS_DB", url);
    }
    let output = pytest.output().expect("the Python named by EXPLORATION_PYTHON runs");
    let report = String::from_utf8_lossy(&output.stdout);
    eprintln!("{report}{}", String::from_utf8_lossy(&output.stderr));
    assert!(output.status.success(), "the Python client's tests failed:\n{report}");
    let skipped = report.lines().filter(|line| line.starts_with("SKIPPED")).count();
    let may_skip = usize::from(replicas_db.is_none());
    assert!(
        skipped <= may_skip && (skipped == 0 || report.contains("EXPLORATION_REPLICAS_DB")),
        "none of the Python client's tests may be skipped here but the replicas' without PostgreSQL:\n{report}"
    );
}
