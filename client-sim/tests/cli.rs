//! `fleet-sim run --json` as a user runs it: the last line is one JSON
//! object with the figures the README promises.

use std::path::Path;
use std::process::Command;

#[test]
fn run_json_prints_the_promised_figures() {
    let map = Path::new(env!("CARGO_MANIFEST_DIR")).join("../maps/nav2_depot.yaml");
    let output = Command::new(env!("CARGO_BIN_EXE_fleet-sim"))
        .args(["run", "--robots", "2", "--policy", "nearest", "--seed", "4", "--cell-size", "0.25", "--json", "--map"])
        .arg(&map)
        .output()
        .unwrap();
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    let stdout = String::from_utf8(output.stdout).unwrap();
    let last = stdout.lines().last().unwrap();
    let report: serde_json::Value = serde_json::from_str(last).unwrap();
    for key in [
        "mission_id",
        "policy",
        "robots",
        "completed",
        "steps",
        "coverage",
        "t50",
        "t90",
        "t95",
        "t100",
        "distance_per_robot",
        "replans",
    ] {
        assert!(report.get(key).is_some(), "{key} is missing from {last}");
    }
    assert_eq!(report["policy"], "nearest");
    assert_eq!(report["robots"], 2);
    assert_eq!(report["completed"], true);
    assert_eq!(report["coverage"], 1.0);
    assert_eq!(report["distance_per_robot"].as_array().unwrap().len(), 2);
}

#[test]
fn bad_arguments_fail_with_a_message() {
    let output = Command::new(env!("CARGO_BIN_EXE_fleet-sim"))
        .args(["run", "--map", "/nonexistent.yaml", "--robots", "1"])
        .output()
        .unwrap();
    assert!(!output.status.success());
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(stderr.contains("/nonexistent.yaml"), "{stderr}");

    let output = Command::new(env!("CARGO_BIN_EXE_fleet-sim"))
        .args(["run", "--map", "x.yaml", "--param", "beta"])
        .output()
        .unwrap();
    assert!(!output.status.success());
    assert!(String::from_utf8_lossy(&output.stderr).contains("key=value"));

    // Values that panicked (a NaN or huge duration) or were clamped or taken
    // without a word: each refused with what is wrong, before the run.
    for (flag, value, said) in [
        ("--retry-for", "NaN", "--retry-for NaN: give seconds from 0 to a day"),
        ("--retry-for", "1e300", "--retry-for 1e300: give seconds from 0 to a day"),
        ("--interference", "2", "interference 2: a move's probability must lie in [0, 1]"),
        ("--interference", "NaN", "interference NaN"),
        ("--comm-range", "NaN", "communication range \"NaN\""),
        ("--max-steps", "0", "--max-steps must be at least 1"),
        ("--start", "NaN,3", "--start \"NaN,3\": \"NaN\" is not a finite number of metres"),
        ("--start", "3,abc", "--start \"3,abc\": \"abc\" is not a finite number of metres"),
    ] {
        let map = Path::new(env!("CARGO_MANIFEST_DIR")).join("../maps/nav2_depot.yaml");
        let output = Command::new(env!("CARGO_BIN_EXE_fleet-sim"))
            .args(["run", flag, value, "--map"])
            .arg(&map)
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert_eq!(output.status.code(), Some(1), "{flag} {value}: {stderr}");
        assert!(stderr.contains(said), "{flag} {value}: {stderr}");
    }

    for size in ["20xabc", "infx20"] {
        let output = Command::new(env!("CARGO_BIN_EXE_fleet-sim"))
            .args(["run", "--world", "office", "--size", size])
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert_eq!(output.status.code(), Some(1), "{size}: {stderr}");
        assert!(stderr.starts_with(&format!("fleet-sim: --size {size:?}: ")), "{size}: {stderr}");
        assert!(stderr.contains("is not a finite number of metres"), "{size}: {stderr}");
    }

    // Load rates no robot sends (1e9 Hz never finished; NaN sent at 1e-3 Hz).
    for (args, said) in [
        (["--heartbeat-hz", "NaN"], "--heartbeat-hz NaN (× --rate-scale 1): a robot's rate must lie in [0, 100]"),
        (["--rate-scale", "1e9"], "--heartbeat-hz 2 (× --rate-scale 1e9)"),
        (["--capacity-callers", "0"], "--capacity-callers must be at least 1"),
        (["--missions", "1000000"], "--missions 1000000 × --robots 50: at most 100000 robots in all"),
    ] {
        let output = Command::new(env!("CARGO_BIN_EXE_fleet-sim")).arg("load").args(args).output().unwrap();
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert_eq!(output.status.code(), Some(1), "{args:?}: {stderr}");
        assert!(stderr.contains(said), "{args:?}: {stderr}");
    }

    // A file without end in place of the map's YAML (it read until memory
    // ran out), and an experiment config likewise: refused, in one line.
    for args in [["run", "--map", "/dev/zero"], ["experiment", "--config", "/dev/zero"]] {
        let output = Command::new(env!("CARGO_BIN_EXE_fleet-sim")).args(args).output().unwrap();
        assert!(!output.status.success());
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert!(stderr.contains("/dev/zero: larger than 1 MiB"), "{args:?}: {stderr}");
        assert_eq!(stderr.lines().count(), 1, "{args:?}: {stderr}");
    }
}

/// `fleet-sim run --json | head -c 0`: the reader leaves before the report
/// is written, and with it the reader of the messages. That is no failure
/// of the run, and nothing panics.
#[test]
fn a_reader_that_leaves_early_is_no_failure() {
    let map = Path::new(env!("CARGO_MANIFEST_DIR")).join("../maps/nav2_depot.yaml");
    for json in [true, false] {
        let (reader, writer) = std::io::pipe().unwrap();
        drop(reader);
        let mut command = Command::new(env!("CARGO_BIN_EXE_fleet-sim"));
        command.args(["run", "--robots", "1", "--policy", "nearest", "--cell-size", "0.25", "--max-steps", "20"]);
        command.arg("--map").arg(&map);
        if json {
            command.arg("--json");
        }
        let status = command.stdout(writer.try_clone().unwrap()).stderr(writer).status().unwrap();
        assert!(status.success(), "--json {json}: {status}");
    }
}

/// A call the executive could not answer is one line a person can read: the
/// call, the code, the message and the transport's root cause, not tonic's
/// debugging dump ("code: 'The service is currently unavailable', …,
/// source: tonic::transport::Error(Transport, ConnectError(…))").
#[test]
fn an_unreachable_executive_is_reported_in_one_readable_line() {
    // A port nobody listens on: bound, then let go.
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let map = Path::new(env!("CARGO_MANIFEST_DIR")).join("../maps/nav2_depot.yaml");
    let output = Command::new(env!("CARGO_BIN_EXE_fleet-sim"))
        .args(["run", "--server", &format!("http://127.0.0.1:{port}"), "--retry-for", "0", "--map"])
        .arg(&map)
        .output()
        .unwrap();
    assert_eq!(output.status.code(), Some(1));
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(
        stderr.starts_with(
            "fleet-sim: the run failed: CreateMission: the executive stayed unreachable for 0ns: Unavailable: "
        ),
        "{stderr}"
    );
    assert!(stderr.contains("Connection refused"), "{stderr}");
    assert!(!stderr.contains("code: '") && !stderr.contains("source:") && !stderr.contains("robot failed"), "{stderr}");
    assert_eq!(stderr.lines().count(), 1, "{stderr}");
}
