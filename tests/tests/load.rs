//! `fleet-sim load` as a user runs it, small: two missions of five robots
//! against an embedded executive for a few seconds, then the capacity phase.

mod common;

#[test]
fn a_small_load_run_reports_every_figure_and_loses_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let json = dir.path().join("load.json");
    let output = std::process::Command::new(common::binary("fleet-sim"))
        .args(["load", "--missions", "2", "--robots", "5", "--duration", "3", "--capacity", "1"])
        .args(["--capacity-callers", "8", "--map"])
        .arg(common::bundled_map("nav2_depot"))
        .arg("--json")
        .arg(&json)
        .env("RUST_LOG", "warn")
        .output()
        .unwrap();
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    let summary = String::from_utf8_lossy(&output.stderr);
    assert!(summary.contains("trigger → next task") && summary.contains("capacity"), "{summary}");
    let report: serde_json::Value = serde_json::from_slice(&std::fs::read(&json).unwrap()).unwrap();
    assert_eq!(report["robots"], 10);
    assert_eq!(report["acknowledged_in_store"], true);
    for call in ["Heartbeat", "UpdateMap", "Health (empty)"] {
        let statuses = report["calls"][call]["statuses"].as_object().unwrap_or_else(|| panic!("{call}: {report}"));
        assert!(statuses.keys().all(|k| k == "Ok"), "{call}: {statuses:?}");
        assert!(report["calls"][call]["latency_ms"]["count"].as_u64().unwrap() > 0);
    }
    // 10 robots × 1 Hz for 3 s, within a second or so of slack.
    let updates = report["map_updates_acknowledged"].as_u64().unwrap();
    assert!((20..=40).contains(&updates), "{updates}");
    assert!(report["capacity"]["empty_calls_per_s"].as_f64().unwrap() > 0.0);
    assert!(report["capacity"]["empty_calls_one_connection_per_s"].as_f64().unwrap() > 0.0);
    assert!(report["capacity"]["map_updates_per_s"].as_f64().unwrap() > 0.0);
    assert!(report["executive"]["shared_with_load_generator"].as_bool().unwrap());
    // A trigger is missed only when older than the grace at the end: none in 3 s.
    assert_eq!(report["triggers_unanswered"], 0, "{report}");
    for key in ["triggers_ended_by_completion", "triggers_pending_at_end"] {
        assert!(report[key].is_u64(), "{key}: {report}");
    }
    assert!(report["missions_completed_s"].is_object(), "{report}");
}
