//! The experiment runner end to end: a small matrix of real missions, its
//! CSV files, plots, pictures and report; resuming; runs that fail or hang
//! recorded as such without stopping the rest; limited communication
//! through the real service.

use std::path::Path;

use client_sim::experiment::run_experiment;
use client_sim::fleet::{CommRange, RunConfig, WorldSpec};
use client_sim::generate::Generator;
use client_sim::runs::read_runs;

fn workspace() -> &'static Path {
    Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/.."))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_ci_experiment_runs_end_to_end_and_resumes() {
    let out = tempfile::tempdir().unwrap();
    let config = workspace().join("experiments/ci-small.toml");
    run_experiment(&config, out.path(), 2, None, false).await.unwrap();
    let rows = read_runs(out.path()).unwrap();
    assert_eq!(rows.len(), 8, "1 world × 2 team sizes × 2 policies × 2 seeds");
    assert!(rows.iter().all(|r| r["status"] == "ok" && r["completed"] == "true"), "{rows:?}");
    let summary = std::fs::read_to_string(out.path().join("summary.csv")).unwrap();
    assert_eq!(summary.lines().count(), 1 + 4, "a header and one line per cell:\n{summary}");
    assert!(summary.lines().next().unwrap().contains("steps_ci95"));
    for plot in ["plot1-time_vs_robots-office", "plot2-coverage_over_time-office"] {
        for ext in ["png", "svg"] {
            let file = out.path().join(format!("{plot}.{ext}"));
            assert!(std::fs::metadata(&file).unwrap().len() > 1000, "{}", file.display());
        }
    }
    assert_eq!(std::fs::read_dir(out.path().join("pictures")).unwrap().count(), 4);
    // Running again does nothing new: every run is there.
    run_experiment(&config, out.path(), 2, None, false).await.unwrap();
    assert_eq!(read_runs(out.path()).unwrap().len(), 8);
    // The report reads the results.
    let experiment = client_sim::experiment::Experiment::load(&config).unwrap();
    // No run takes fewer steps than the lower bound of its cell, and the
    // bound is more than nothing.
    let bounds = client_sim::bound::matrix_bounds(&experiment, config.parent().unwrap()).unwrap();
    assert_eq!(bounds.len(), 4, "2 team sizes × 2 seeds");
    for row in &rows {
        let cell = bounds
            .iter()
            .find(|c| c.run.robots.to_string() == row["robots"] && c.run.seed.to_string() == row["seed"])
            .unwrap();
        let steps: u64 = row["steps"].parse().unwrap();
        assert!(cell.bound.steps() > 0 && steps >= cell.bound.steps(), "{steps} steps against {:?}", cell.bound);
    }
    let report = out.path().join("results.md");
    client_sim::report::write_report(&[(experiment, out.path().to_owned())], out.path(), &report).unwrap();
    let text = std::fs::read_to_string(&report).unwrap();
    assert!(text.contains("**Claim.**") && text.contains("| robots | nearest | burgard |"), "{text}");
    // It says where its runs are and how to make them again, as they were
    // made here, not as the repository's own report does.
    let results = out.path().display();
    assert!(text.contains(&format!("from the runs in `{results}/`")), "{text}");
    assert!(text.contains(&format!("--out {results}/$e")), "{text}");
    assert!(text.contains(&format!("report --out {} --results {results} ", report.display())), "{text}");
    assert!(!text.contains("docs/results"), "{text}");
}

/// An experiment not run yet is reported as such, with no time spent (an
/// empty sum of f64 is -0, which printed as "-0 s").
#[test]
fn an_experiment_without_runs_is_reported_with_none_done() {
    let out = tempfile::tempdir().unwrap();
    let experiment = client_sim::experiment::Experiment::load(&workspace().join("experiments/ci-small.toml")).unwrap();
    let report = out.path().join("results.md");
    client_sim::report::write_report(&[(experiment, out.path().to_owned())], out.path(), &report).unwrap();
    let text = std::fs::read_to_string(&report).unwrap();
    assert!(text.contains("Runs: 0 done"), "{text}");
    assert!(text.contains(", 0 s of run time in all") && !text.contains("-0 s"), "{text}");
}

/// What would panic a run (a negative or NaN time limit), never finish
/// making the list of runs (a hundred billion seeds) or fail every run alike
/// (a team of no robots) is refused when the file is read, naming the
/// field; every experiment of the repository still loads.
#[test]
fn experiment_files_that_cannot_run_are_refused_when_read() {
    let base = std::fs::read_to_string(workspace().join("experiments/ci-small.toml")).unwrap();
    let dir = tempfile::tempdir().unwrap();
    for (from, to, said) in [
        ("time_limit_s = 120", "time_limit_s = -1", "time_limit_s -1: give seconds above 0"),
        ("time_limit_s = 120", "time_limit_s = nan", "time_limit_s NaN: give seconds above 0"),
        ("time_limit_s = 120", "time_limit_s = 1e6", "time_limit_s 1000000: give seconds above 0, at most 86400"),
        ("seeds = 2", "seeds = 100000000000", "400000000000 runs (seeds × worlds × ranges × team sizes × policies)"),
        ("robots = [1, 2]", "robots = [1, 0]", "robots: a team has at least one robot"),
    ] {
        assert!(base.contains(from), "{from}");
        let config = dir.path().join("e.toml");
        std::fs::write(&config, base.replace(from, to)).unwrap();
        let refused = client_sim::experiment::Experiment::load(&config).map(|_| ()).unwrap_err().to_string();
        assert!(refused.contains(said), "{to}: {refused}");
    }
    for entry in std::fs::read_dir(workspace().join("experiments")).unwrap() {
        let path = entry.unwrap().path();
        client_sim::experiment::Experiment::load(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn runs_that_hang_or_fail_are_recorded_and_the_rest_go_on() {
    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("bad.toml");
    std::fs::write(
        &config,
        r#"
name = "bad"
seeds = 1
time_limit_s = 0.05
robots = [2]

[[worlds]]
name = "office"
generator = "office"
width_m = 25
height_m = 20

[[worlds]]
name = "missing"
map = "no/such/map.yaml"

[[policies]]
name = "burgard"
"#,
    )
    .unwrap();
    let out = dir.path().join("out");
    run_experiment(&config, &out, 2, None, false).await.unwrap();
    let rows = read_runs(&out).unwrap();
    assert_eq!(rows.len(), 2);
    let office = rows.iter().find(|r| r["world"] == "office").unwrap();
    assert_eq!(office["status"], "timeout", "{office:?}");
    assert!(office["error"].contains("time limit"));
    let missing = rows.iter().find(|r| r["world"] == "missing").unwrap();
    assert_eq!(missing["status"], "failed");
    assert!(missing["error"].contains("no/such/map.yaml"), "{missing:?}");
}

/// Burgard et al. 2005 §II-D through the real service: with a tiny range the
/// robots coordinate alone and each must see most of the map itself; with a
/// range spanning the map they coordinate as one team.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn limited_communication_runs_through_the_service() {
    let world = WorldSpec::Generated { generator: Generator::Office, width_m: 20.0, height_m: 15.0 };
    let run = |range: Option<CommRange>| {
        let world = world.clone();
        async move {
            let mut config = RunConfig::on(world, 3, "burgard");
            config.cell_size = Some(0.25);
            config.seed = 4;
            config.start = client_sim::world::StartChoice::Random;
            config.comm_range = range;
            client_sim::run(&config).await.unwrap()
        }
    };
    let alone = run(Some(CommRange::Metres(0.1))).await;
    let together = run(Some(CommRange::OfDiameter(2.0))).await;
    assert!(alone.completed && together.completed, "{alone:?} {together:?}");
    assert_eq!(alone.comm_range_m, Some(0.1));
    assert!(together.steps < alone.steps, "a team that talks finishes sooner: {} vs {}", together.steps, alone.steps);
    assert_eq!(alone.updates_acknowledged, alone.map_updates);
}

/// Robots that meet again pass on what they learnt apart, their own
/// measurements and those forwarded to them (Burgard et al. 2005 §III), and
/// report their new peers before anyone moves: each then knows the map the
/// executive plans its sub-team on, so it never has to refuse a target as
/// unreachable for want of a map. (Before, this run had 44 such failures,
/// each blacklisting a good target.)
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn robots_that_meet_plan_on_their_sub_teams_map() {
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("comm.db");
    let world = WorldSpec::Generated { generator: Generator::Office, width_m: 20.0, height_m: 15.0 };
    let mut config = RunConfig::on(world, 4, "burgard");
    config.cell_size = Some(0.25);
    config.seed = 4;
    config.start = client_sim::world::StartChoice::Random;
    config.comm_range = Some(CommRange::OfDiameter(0.2));
    config.db = Some(db.clone());
    let report = client_sim::run(&config).await.unwrap();
    assert!(report.completed, "{report:?}");

    let pool = sqlx::SqlitePool::connect(&format!("sqlite://{}", db.display())).await.unwrap();
    let sub_team_changes: i64 =
        sqlx::query_scalar("SELECT COUNT(*) FROM task_transitions WHERE cause LIKE '%sub-team changed%'")
            .fetch_one(&pool)
            .await
            .unwrap();
    assert!(sub_team_changes > 0, "the sub-teams split and merged during the run");
    let failed: Vec<String> = sqlx::query_scalar("SELECT cause FROM task_transitions WHERE to_state = 'failed'")
        .fetch_all(&pool)
        .await
        .unwrap();
    assert!(failed.is_empty(), "no robot refused a target its sub-team's map leads to: {failed:?}");
}
