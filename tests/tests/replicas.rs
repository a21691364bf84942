//! Executive replicas sharing one PostgreSQL database (where
//! `EXPLORATION_POSTGRES_URL` names a server; `.ci/run` starts one): a
//! fleet's mission survives the replica that holds it killed with SIGKILL
//! three times, a different replica each time; a replica paused past its
//! lease cannot write for the mission once another has taken it; replicas
//! that start or stop share the missions evenly again; a mission is created
//! once however its first claim goes.

mod common;

use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use client_sim::RunConfig;
use common::{
    binary, bundled_map, create_mission, free_port, mission_request, patch, register, registration, update,
    wait_until_serving,
};
use exploration_proto::v1::fleet_client::FleetClient;
use exploration_proto::v1::missions_client::MissionsClient;
use sqlx::Connection;
use tonic::Code;

/// One `coordinator` replica process.
struct Replica {
    id: String,
    port: u16,
    child: Child,
}

impl Replica {
    fn spawn(id: &str, port: u16, db: &str, lease: &str, grace: &str) -> Self {
        let child = Command::new(binary("coordinator"))
            .args(["--listen", &format!("127.0.0.1:{port}"), "--db", db, "--replica-id", id])
            .args(["--lease-period", lease, "--lease-grace", grace])
            .env("RUST_LOG", "warn")
            .stdout(Stdio::null())
            .stderr(Stdio::inherit())
            .spawn()
            .expect("coordinator starts");
        Self { id: id.to_owned(), port, child }
    }

    fn url(&self) -> String {
        format!("http://127.0.0.1:{}", self.port)
    }

    fn signal(&self, signal: &str) {
        let status = Command::new("kill").args([signal, &self.child.id().to_string()]).status().unwrap();
        assert!(status.success(), "kill {signal}");
    }
}

impl Drop for Replica {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// The replica holding `mission` now and its fencing token.
async fn holder(db: &mut sqlx::PgConnection, mission: i64) -> Option<(String, i64)> {
    sqlx::query_as("SELECT owner, token FROM mission_leases WHERE mission_id = $1")
        .bind(mission)
        .fetch_optional(db)
        .await
        .unwrap()
}

async fn map_updates(db: &mut sqlx::PgConnection) -> i64 {
    sqlx::query_scalar("SELECT COALESCE(MAX(map_updates), 0) FROM missions").fetch_one(db).await.unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_fleet_completes_through_three_kills_of_its_missions_holder() {
    let Some(url) = common::postgres_database("replicas_kills").await else { return };
    let mut db = sqlx::PgConnection::connect(&url).await.unwrap();
    let (lease, grace) = ("2", "0.5");
    let mut replicas: Vec<Replica> =
        (1..=3).map(|i| Replica::spawn(&format!("r{i}"), free_port(), &url, lease, grace)).collect();
    for replica in &replicas {
        wait_until_serving(&replica.url(), Duration::from_secs(30)).await;
    }
    let list: Vec<String> = replicas.iter().map(Replica::url).collect();
    let mut config = RunConfig::new(bundled_map("nav2_warehouse"), 8, "burgard");
    config.server = Some(list.join(","));
    config.cell_size = Some(0.25);
    config.retry_budget = Duration::from_secs(60);
    let mut fleet = tokio::spawn(async move { client_sim::run(&config).await });

    let mut killed = Vec::new();
    for round in 1..=3 {
        // Well into the mission (again), then kill whoever holds it.
        let before = map_updates(&mut db).await;
        let owner = loop {
            let now = map_updates(&mut db).await;
            if now >= before + 150
                && let Some(owner) = holder(&mut db, 1).await
            {
                break owner;
            }
            if fleet.is_finished() {
                let outcome = (&mut fleet).await;
                panic!("the fleet finished before kill {round}: {outcome:?}");
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        };
        let index = replicas.iter().position(|r| r.id == owner.0).unwrap();
        replicas[index].signal("-KILL");
        let killed_at = Instant::now();
        let at_kill = map_updates(&mut db).await;
        // Taken over: another replica holds it, and the fleet's updates are written again.
        let taken = loop {
            if let Some(now) = holder(&mut db, 1).await
                && now.1 > owner.1
                && map_updates(&mut db).await > at_kill
            {
                break now;
            }
            assert!(killed_at.elapsed() < Duration::from_secs(60), "nobody took the mission over after kill {round}");
            tokio::time::sleep(Duration::from_millis(10)).await;
        };
        eprintln!(
            "kill {round}: {} (token {}) killed, {} (token {}) writing again after {} ms",
            owner.0,
            owner.1,
            taken.0,
            taken.1,
            killed_at.elapsed().as_millis()
        );
        assert_ne!(taken.0, owner.0);
        killed.push(owner.0.clone());
        // The killed one comes back, empty-handed, so that three stay.
        let port = replicas[index].port;
        replicas[index] = Replica::spawn(&owner.0, port, &url, lease, grace);
    }
    let report = fleet.await.unwrap().unwrap();
    assert!(report.completed, "{report:?}");
    assert_eq!(report.coverage, 1.0);
    assert_eq!(
        report.updates_acknowledged, report.map_updates,
        "every acknowledged update is applied exactly once across the kills"
    );
    killed.dedup();
    assert_eq!(killed.len(), 3, "a different replica each time, in turn: {killed:?}");
    no_task_had_two_owners(&mut db).await;
    // The takeover time, as the fleet saw it: the longest waits between two
    // acknowledged map updates (each is stamped when written).
    let gaps: Vec<i64> = sqlx::query_scalar(
        "SELECT gap FROM (SELECT received_at - LAG(received_at) OVER (ORDER BY id) AS gap FROM map_patches) g
         WHERE gap IS NOT NULL ORDER BY gap DESC LIMIT 3",
    )
    .fetch_all(&mut db)
    .await
    .unwrap();
    eprintln!("takeovers (last acknowledged update before a kill to the first after), ms: {gaps:?}");
}

/// Every task's transitions, in the order written, form one chain (each
/// starts where the one before ended, none after the task ended), and no
/// robot is left with two open tasks: two replicas acting for the mission
/// at once would move one task twice, or revive an ended one.
async fn no_task_had_two_owners(db: &mut sqlx::PgConnection) {
    let transitions: Vec<(i64, Option<String>, String)> =
        sqlx::query_as("SELECT task_id, from_state, to_state FROM task_transitions ORDER BY id")
            .fetch_all(&mut *db)
            .await
            .unwrap();
    assert!(transitions.len() > 100, "{} transitions", transitions.len());
    let mut last: std::collections::HashMap<i64, String> = std::collections::HashMap::new();
    for (task, from, to) in transitions {
        let previous = last.get(&task);
        assert_eq!(from.as_ref(), previous, "task {task} moved from {from:?} to {to} after {previous:?}");
        if let Some(previous) = previous {
            assert!(
                matches!(previous.as_str(), "assigned" | "active"),
                "task {task} moved after it ended ({previous})"
            );
        }
        last.insert(task, to);
    }
    let doubled: Vec<(i64, i64)> = sqlx::query_as(
        "SELECT robot_id, COUNT(*) FROM tasks WHERE state IN ('assigned', 'active') GROUP BY robot_id HAVING COUNT(*) > 1",
    )
    .fetch_all(&mut *db)
    .await
    .unwrap();
    assert!(doubled.is_empty(), "robots with two open tasks: {doubled:?}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_replica_paused_past_its_lease_cannot_write_and_gives_the_mission_up() {
    let Some(url) = common::postgres_database("replicas_paused").await else { return };
    let mut db = sqlx::PgConnection::connect(&url).await.unwrap();
    let a = Replica::spawn("a", free_port(), &url, "1", "0.2");
    let b = Replica::spawn("b", free_port(), &url, "1", "0.2");
    wait_until_serving(&a.url(), Duration::from_secs(30)).await;
    wait_until_serving(&b.url(), Duration::from_secs(30)).await;
    // Straight channels, which follow no owner: each call reaches the replica it names.
    let channel = |replica: &Replica| tonic::transport::Endpoint::from_shared(replica.url()).unwrap().connect_lazy();
    let mut missions_a = MissionsClient::new(channel(&a));
    let mut fleet_a = FleetClient::new(channel(&a));
    let mission = create_mission(&mut missions_a, 40, 40, "nearest").await;
    let robot = register(&mut fleet_a, mission.id, "r", 0.55, 0.55).await;
    fleet_a.update_map(update(robot.id, 1, 0.55, 0.55, vec![patch(0, 0, 10, 10, 0.05)])).await.unwrap();
    assert_eq!(holder(&mut db, mission.id as i64).await.map(|h| h.0).as_deref(), Some("a"));

    // B points to A while A holds the mission.
    let mut fleet_b = FleetClient::new(channel(&b));
    let pointed = fleet_b.update_map(update(robot.id, 2, 0.55, 0.55, vec![])).await.unwrap_err();
    assert_eq!(pointed.code(), Code::Unavailable);
    assert_eq!(pointed.metadata().get("exploration-owner").unwrap(), a.url().as_str());

    a.signal("-STOP");
    // Past A's lease and the grace, B takes the mission and writes for it.
    let paused_at = Instant::now();
    let written_by_b = loop {
        match fleet_b.update_map(update(robot.id, 2, 0.55, 0.55, vec![patch(10, 0, 5, 5, 0.05)])).await {
            Ok(answer) => break answer.into_inner(),
            Err(status) => assert_eq!(status.code(), Code::Unavailable, "{status:?}"),
        }
        assert!(paused_at.elapsed() < Duration::from_secs(20), "B never took the mission");
        tokio::time::sleep(Duration::from_millis(50)).await;
    };
    assert_eq!(written_by_b.applied_seq, 2);
    assert_eq!(holder(&mut db, mission.id as i64).await.unwrap(), ("b".to_owned(), 2));

    // A wakes up believing it holds the mission: its write is refused.
    a.signal("-CONT");
    let stale = fleet_a.update_map(update(robot.id, 3, 0.55, 0.55, vec![patch(20, 20, 5, 5, 0.95)])).await.unwrap_err();
    assert_eq!(stale.code(), Code::Unavailable, "{stale:?}");
    let (seq, updates): (i64, i64) = sqlx::query_as(
        "SELECT r.last_map_seq, m.map_updates FROM robots r JOIN missions m ON m.id = r.mission_id WHERE r.id = $1",
    )
    .bind(robot.id as i64)
    .fetch_one(&mut db)
    .await
    .unwrap();
    assert_eq!((seq, updates), (2, 2), "nothing of A's write reached the database");
    // And A has let the mission go: it points to B.
    let woke_at = Instant::now();
    loop {
        let status = fleet_a.update_map(update(robot.id, 3, 0.55, 0.55, vec![])).await.unwrap_err();
        assert_eq!(status.code(), Code::Unavailable, "{status:?}");
        if status.metadata().get("exploration-owner").is_some_and(|o| o == b.url().as_str()) {
            break;
        }
        assert!(woke_at.elapsed() < Duration::from_secs(10), "A kept the mission: {status:?}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    // B carries on where it was.
    let next = fleet_b.update_map(update(robot.id, 3, 0.55, 0.55, vec![])).await.unwrap().into_inner();
    assert_eq!(next.applied_seq, 3);
}

/// A new mission and its lease are written in one transaction, so no
/// other replica's lease keeper ever sees the mission unclaimed (under load
/// in CI one did, between the creation and the creator's claim, and took
/// it). Triggers note the transaction that inserts each.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_mission_is_created_with_its_lease_in_one_transaction() {
    let trigger = "CREATE TABLE inserted_by (what TEXT, xact xid8);
         CREATE FUNCTION note_transaction() RETURNS trigger AS $$ BEGIN
             INSERT INTO inserted_by VALUES (TG_TABLE_NAME, pg_current_xact_id());
             RETURN NEW;
         END $$ LANGUAGE plpgsql;
         CREATE TRIGGER note_mission AFTER INSERT ON missions FOR EACH ROW EXECUTE FUNCTION note_transaction();
         CREATE TRIGGER note_lease AFTER INSERT ON mission_leases FOR EACH ROW EXECUTE FUNCTION note_transaction();";
    let Some((mut db, _a, channel)) = lone_replica_with("replicas_created_claimed", trigger).await else { return };
    let mission = create_mission(&mut MissionsClient::new(channel.clone()), 40, 40, "nearest").await;
    let transactions: Vec<(String, String)> =
        sqlx::query_as("SELECT what, xact::text FROM inserted_by ORDER BY what").fetch_all(&mut db).await.unwrap();
    assert_eq!(transactions.len(), 2, "{transactions:?}");
    assert_eq!(transactions[0].1, transactions[1].1, "the mission and its lease in two transactions: {transactions:?}");
    assert_eq!(holder(&mut db, mission.id as i64).await, Some(("a".to_owned(), 1)));
    // Held at once: its first robot is not told to retry.
    FleetClient::new(channel).register_robot(registration(mission.id, "r", 0.55, 0.55)).await.unwrap();
}

/// A mission whose lease cannot be written is not created either: the
/// caller is told, and may create it again without making two.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_mission_whose_lease_cannot_be_written_is_not_created() {
    let trigger = "CREATE FUNCTION no_claims() RETURNS trigger AS $$ BEGIN
             RAISE EXCEPTION 'leases refused by the test';
         END $$ LANGUAGE plpgsql;
         CREATE TRIGGER no_claims BEFORE INSERT ON mission_leases FOR EACH ROW EXECUTE FUNCTION no_claims();";
    let Some((mut db, _a, channel)) = lone_replica_with("replicas_claim_fails", trigger).await else { return };
    let mut missions = MissionsClient::new(channel.clone());
    let refused = missions.create_mission(mission_request(40, 40, "nearest")).await.unwrap_err();
    assert_ne!(refused.code(), Code::Ok);
    let stored: i64 = sqlx::query_scalar("SELECT COUNT(*) FROM missions").fetch_one(&mut db).await.unwrap();
    assert_eq!(stored, 0, "a mission was stored without its lease");
    sqlx::raw_sql("DROP TRIGGER no_claims ON mission_leases").execute(&mut db).await.unwrap();
    let mission = create_mission(&mut missions, 40, 40, "nearest").await;
    let stored: i64 = sqlx::query_scalar("SELECT COUNT(*) FROM missions").fetch_one(&mut db).await.unwrap();
    assert_eq!(stored, 1);
    assert_eq!(holder(&mut db, mission.id as i64).await, Some(("a".to_owned(), 1)));
    FleetClient::new(channel).register_robot(registration(mission.id, "r", 0.55, 0.55)).await.unwrap();
}

/// One replica, "a", serving a fresh database named `name` on which `sql`
/// was run (a trigger standing in for another replica or a failing store);
/// `None` where no PostgreSQL server is configured.
async fn lone_replica_with(
    name: &str,
    sql: &'static str,
) -> Option<(sqlx::PgConnection, Replica, tonic::transport::Channel)> {
    let url = common::postgres_database(name).await?;
    let mut db = sqlx::PgConnection::connect(&url).await.unwrap();
    let a = Replica::spawn("a", free_port(), &url, "2", "0.5");
    wait_until_serving(&a.url(), Duration::from_secs(30)).await;
    sqlx::raw_sql(sql).execute(&mut db).await.unwrap();
    let channel = tonic::transport::Endpoint::from_shared(a.url()).unwrap().connect_lazy();
    Some((db, a, channel))
}

/// How many missions each replica holds now, by name.
async fn holdings(db: &mut sqlx::PgConnection) -> Vec<(String, i64)> {
    sqlx::query_as(
        "SELECT owner, COUNT(*) FROM mission_leases WHERE expires_at > (EXTRACT(EPOCH FROM now()) * 1000)::BIGINT
         GROUP BY owner ORDER BY owner",
    )
    .fetch_all(db)
    .await
    .unwrap()
}

/// The sum of every mission's fencing token: it grows by one at each claim.
async fn claims(db: &mut sqlx::PgConnection) -> i64 {
    sqlx::query_scalar("SELECT COALESCE(SUM(token), 0)::BIGINT FROM mission_leases").fetch_one(db).await.unwrap()
}

/// When each replica named announced itself last runs out, by name.
async fn announcements(db: &mut sqlx::PgConnection, names: &[&str]) -> Vec<i64> {
    let names: Vec<String> = names.iter().map(|n| (*n).to_owned()).collect();
    sqlx::query_scalar("SELECT expires_at FROM replicas WHERE id = ANY($1) ORDER BY id")
        .bind(&names)
        .fetch_all(db)
        .await
        .unwrap()
}

/// Waits until every replica named has announced itself `rounds` more times.
async fn keeper_rounds(db: &mut sqlx::PgConnection, names: &[&str], rounds: usize) {
    let mut last = announcements(db, names).await;
    let mut seen = vec![0; names.len()];
    let start = Instant::now();
    while seen.iter().any(|&s| s < rounds) {
        assert!(start.elapsed() < Duration::from_secs(30), "the replicas stopped announcing themselves");
        tokio::time::sleep(Duration::from_millis(20)).await;
        let now = announcements(db, names).await;
        for (i, (before, after)) in last.iter().zip(&now).enumerate() {
            if after > before {
                seen[i] += 1;
            }
        }
        last = now;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn replicas_share_the_missions_evenly_as_they_come_and_go() {
    let Some(url) = common::postgres_database("replicas_share").await else { return };
    let mut db = sqlx::PgConnection::connect(&url).await.unwrap();
    // Alone, r1 creates and holds six missions.
    let r1 = Replica::spawn("r1", free_port(), &url, "1", "0.25");
    wait_until_serving(&r1.url(), Duration::from_secs(30)).await;
    let mut missions = MissionsClient::new(channel_to(&r1));
    for _ in 0..6 {
        create_mission(&mut missions, 20, 20, "nearest").await;
    }
    assert_eq!(holdings(&mut db).await, vec![("r1".to_owned(), 6)]);

    // Two more start: r1 hands on what is beyond its share, and they take it.
    let r2 = Replica::spawn("r2", free_port(), &url, "1", "0.25");
    let r3 = Replica::spawn("r3", free_port(), &url, "1", "0.25");
    let even = |n: i64| vec![("r1".to_owned(), n), ("r2".to_owned(), n), ("r3".to_owned(), n)];
    let start = Instant::now();
    while holdings(&mut db).await != even(2) {
        assert!(start.elapsed() < Duration::from_secs(20), "not shared evenly: {:?}", holdings(&mut db).await);
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    // Once even, it stays so: no mission changes hands in later rounds.
    let settled = claims(&mut db).await;
    keeper_rounds(&mut db, &["r1", "r2", "r3"], 3).await;
    assert_eq!((claims(&mut db).await, holdings(&mut db).await), (settled, even(2)));
    // Each mission answers at its holder.
    for mission in 1..=6 {
        let (owner, _) = holder(&mut db, mission).await.unwrap();
        let replica = [&r1, &r2, &r3].into_iter().find(|r| r.id == owner).unwrap();
        let mut client = MissionsClient::new(channel_to(replica));
        let request = exploration_proto::v1::GetMissionRequest { mission_id: mission as u64 };
        client.get_mission(request).await.unwrap_or_else(|e| panic!("mission {mission} at {owner}: {e:?}"));
    }

    // r3 stops (SIGTERM): it withdraws, and r1 and r2 take three each.
    r3.signal("-TERM");
    let start = Instant::now();
    while holdings(&mut db).await != vec![("r1".to_owned(), 3), ("r2".to_owned(), 3)] {
        assert!(start.elapsed() < Duration::from_secs(20), "r3's missions not taken: {:?}", holdings(&mut db).await);
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// A mission deleted at its holder is gone for every replica: no other
/// lists it or claims it, and its rows, lease included, are purged.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_mission_deleted_at_its_holder_is_gone_for_every_replica() {
    let Some(url) = common::postgres_database("replicas_delete").await else { return };
    let mut db = sqlx::PgConnection::connect(&url).await.unwrap();
    let r1 = Replica::spawn("r1", free_port(), &url, "1", "0.25");
    wait_until_serving(&r1.url(), Duration::from_secs(30)).await;
    let mut at_r1 = MissionsClient::new(channel_to(&r1));
    let gone = create_mission(&mut at_r1, 40, 40, "nearest").await;
    let stays = create_mission(&mut at_r1, 40, 40, "nearest").await;
    let mut fleet = FleetClient::new(channel_to(&r1));
    let robot = register(&mut fleet, gone.id, "r", 0.55, 0.55).await;
    fleet.update_map(update(robot.id, 1, 0.55, 0.55, vec![patch(0, 0, 10, 10, 0.05)])).await.unwrap();
    let control = exploration_proto::v1::MissionControlRequest { mission_id: gone.id, ..Default::default() };
    at_r1.pause_mission(control.clone()).await.unwrap();
    let r2 = Replica::spawn("r2", free_port(), &url, "1", "0.25");
    wait_until_serving(&r2.url(), Duration::from_secs(30)).await;
    let mut at_r2 = MissionsClient::new(channel_to(&r2));

    at_r1.delete_mission(control.clone()).await.unwrap();
    let request = exploration_proto::v1::GetMissionRequest { mission_id: gone.id };
    let missing = at_r2.get_mission(request).await.unwrap_err();
    assert_eq!(missing.code(), Code::NotFound, "{missing:?}");
    let listed = at_r2.list_missions(exploration_proto::v1::ListMissionsRequest::default()).await.unwrap();
    let listed = listed.into_inner().missions;
    assert_eq!(listed.iter().map(|m| m.id).collect::<Vec<_>>(), vec![stays.id]);
    let start = Instant::now();
    loop {
        let (robots, leases, purged): (i64, i64, i64) = sqlx::query_as(
            "SELECT (SELECT COUNT(*) FROM robots WHERE mission_id = $1),
                    (SELECT COUNT(*) FROM mission_leases WHERE mission_id = $1),
                    (SELECT purged FROM missions WHERE id = $1)",
        )
        .bind(gone.id as i64)
        .fetch_one(&mut db)
        .await
        .unwrap();
        if (robots, leases, purged) == (0, 0, 1) {
            break;
        }
        assert!(start.elapsed() < Duration::from_secs(20), "not purged: {robots} robots, {leases} leases");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    // The other mission is still held, by one of them.
    assert!(holder(&mut db, stays.id as i64).await.is_some());
    assert_eq!(holder(&mut db, gone.id as i64).await, None);
}

fn channel_to(replica: &Replica) -> tonic::transport::Channel {
    tonic::transport::Endpoint::from_shared(replica.url()).unwrap().connect_lazy()
}
