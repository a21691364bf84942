//! The Python client package (clients/python) passes its own tests, run with
//! pytest against this workspace's `coordinator` binary.
//!
//! Runs where `EXPLORATION_PYTHON` names a Python that has the package and
//! pytest installed (`.ci/run` makes such a virtual environment); elsewhere
//! it says it is skipped.

mod common;

use std::path::Path;
use std::process::Command;

#[test]
fn the_python_client_passes_its_tests_against_the_real_executive() {
    let Some(python) = std::env::var_os("EXPLORATION_PYTHON") else {
        eprintln!(
            "SKIPPED: the Python client's tests need EXPLORATION_PYTHON, a Python with clients/python[test] \
             installed (.ci/run creates one)"
        );
        return;
    };
    let repository = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let output = Command::new(&python)
        .args(["-m", "pytest", "-q", "-p", "no:cacheprovider", "clients/python/tests"])
        .current_dir(&repository)
        .env("COORDINATOR_BIN", common::binary("coordinator"))
        .output()
        .expect("the Python named by EXPLORATION_PYTHON runs");
    let report = String::from_utf8_lossy(&output.stdout);
    eprintln!("{report}{}", String::from_utf8_lossy(&output.stderr));
    assert!(output.status.success(), "the Python client's tests failed:\n{report}");
    assert!(!report.contains("skipped"), "none of the Python client's tests may be skipped here:\n{report}");
}
