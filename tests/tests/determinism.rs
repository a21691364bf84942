//! A seed gives the same run on any machine at any load: the embedded
//! executive's clock advances with the simulation's steps, and every step
//! waits for the plans it triggered, so nothing depends on how fast the
//! executive answers.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use client_sim::fleet::{Fault, FaultKind, RunConfig, RunReport, WorldSpec};
use client_sim::generate::Generator;

/// Everything a run reports except how long it took on the wall clock.
fn measured(report: &RunReport) -> (serde_json::Value, Vec<Vec<exploration::grid::Cell>>, Vec<f32>) {
    let mut json = serde_json::to_value(report).unwrap();
    json.as_object_mut().unwrap().remove("wall_time_s");
    (json, report.trajectories.clone(), report.coverage_curve.clone())
}

async fn run_once(config: &RunConfig) -> RunReport {
    let report = client_sim::run(config).await.unwrap();
    assert!(report.completed, "{} seed {}: ended {}", config.policy, config.seed, report.ended);
    report
}

/// Keeps a core busy until dropped.
struct BusyCore(Arc<AtomicBool>, Option<std::thread::JoinHandle<u64>>);

impl BusyCore {
    fn start() -> Self {
        let stop = Arc::new(AtomicBool::new(false));
        let flag = stop.clone();
        let spinner = std::thread::spawn(move || {
            let mut x = 0u64;
            while !flag.load(Ordering::Relaxed) {
                x = x.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            }
            x
        });
        BusyCore(stop, Some(spinner))
    }
}

impl Drop for BusyCore {
    fn drop(&mut self) {
        self.0.store(true, Ordering::Relaxed);
        if let Some(spinner) = self.1.take() {
            let _ = spinner.join();
        }
    }
}

/// Leases and stalls are in simulated seconds (short ones here, and a robot
/// that dies, so that they matter), the team starts packed around one cell
/// and robots block each other: all of it must repeat exactly with the
/// other core busy. On the wall clock the lease would run out after a
/// number of steps that depends on how fast this machine is at the moment.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_seed_gives_the_same_run_with_the_other_core_busy() {
    for policy in ["minpos", "burgard", "simmons"] {
        let world = WorldSpec::Generated { generator: Generator::Office, width_m: 15.0, height_m: 10.0 };
        let mut config = RunConfig::on(world, 4, policy);
        config.cell_size = Some(0.25);
        config.seed = 11;
        config.lease_s = Some(5.0);
        config.stall_s = Some(20.0);
        // Robot 1 goes silent at step 30: its lease runs out 5 simulated
        // seconds later, wherever the wall clock is by then.
        config.faults = vec![Fault { robot: 1, kind: FaultKind::Dies(30) }];
        let quiet = run_once(&config).await;
        let lost = &quiet.fault_record.as_ref().expect("faults are reported").lost_robots;
        assert_eq!(lost, &["robot-1".to_owned()], "{policy}");
        let busy = {
            let _busy = BusyCore::start();
            run_once(&config).await
        };
        let (quiet, busy) = (measured(&quiet), measured(&busy));
        assert_eq!(quiet.0, busy.0, "{policy}: the reports differ");
        assert!(quiet.1 == busy.1, "{policy}: the trajectories differ");
        assert!(quiet.2 == busy.2, "{policy}: the coverage curves differ");
    }
}
