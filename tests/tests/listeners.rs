//! Whoever reaches a port before any token is checked: the HTTP listener
//! and the plaintext health listener hold at most their budgets of
//! connections, so that silent ones cannot take the descriptors the robots'
//! gRPC connections need.

mod common;

use std::net::SocketAddr;
use std::time::Duration;

use common::TestExecutive;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;
use tokio_util::sync::CancellationToken;

/// Opens `count` connections to `address` that send nothing.
async fn silent(address: SocketAddr, count: usize) -> Vec<TcpStream> {
    let mut held = Vec::with_capacity(count);
    for _ in 0..count {
        held.push(TcpStream::connect(address).await.unwrap());
    }
    held
}

/// A new connection to `address` is closed before it sends a byte.
async fn refused(address: SocketAddr) -> bool {
    closed_unread(&mut TcpStream::connect(address).await.unwrap()).await
}

/// The server closes `stream` (within 20 s) without answering.
async fn closed_unread(stream: &mut TcpStream) -> bool {
    let mut byte = [0u8; 1];
    matches!(tokio::time::timeout(Duration::from_secs(20), stream.read(&mut byte)).await, Ok(Ok(0) | Err(_)))
}

/// The health service's answer at `address` (1: serving).
async fn health_status(address: SocketAddr) -> Result<i32, Box<dyn std::error::Error>> {
    use tonic_health::pb::{HealthCheckRequest, health_client::HealthClient};
    let channel = tonic::transport::Endpoint::from_shared(format!("http://{address}"))?.connect().await?;
    let answer = HealthClient::new(channel).check(HealthCheckRequest { service: String::new() }).await?;
    Ok(answer.into_inner().status)
}

/// Whether a probe at `address` is answered within 200 tries (a slot given
/// back is seen once the server has read the close).
async fn answers_a_probe(address: SocketAddr) -> bool {
    for _ in 0..200 {
        if health_status(address).await.is_ok() {
            return true;
        }
        tokio::task::yield_now().await;
    }
    false
}

/// Connections beyond the HTTP limit are closed as they arrive, gRPC
/// answers all along, and once a held one closes the page is served.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn silent_connections_beyond_the_http_limit_are_closed_and_grpc_answers() {
    let dir = tempfile::tempdir().unwrap();
    let mut config = coordinator::Config::new(dir.path().join("limit.db"));
    config.http_connections.max_connections = 3;
    let exec = TestExecutive::start_with_http(config).await;
    let http = exec.http.unwrap();
    let mut held = silent(http, 3).await;
    for _ in 0..5 {
        assert!(refused(http).await, "a connection beyond the limit is closed unread");
    }
    let mut missions = exec.missions();
    common::create_mission(&mut missions, 20, 10, "nearest").await;
    drop(held.pop());
    let mut served = false;
    for _ in 0..200 {
        let mut stream = TcpStream::connect(http).await.unwrap();
        stream
            .write_all(format!("GET / HTTP/1.1\r\nHost: {http}\r\nConnection: close\r\n\r\n").as_bytes())
            .await
            .unwrap();
        let mut answer = Vec::new();
        let _ = tokio::time::timeout(Duration::from_secs(20), stream.read_to_end(&mut answer)).await;
        if answer.starts_with(b"HTTP/1.1 200") {
            served = true;
            break;
        }
    }
    assert!(served, "a slot given back serves the page");
    exec.stop().await;
}

/// Reads from `stream` until `text` has come `times` times in all; false if
/// the stream ends (or stalls for 20 s) first.
async fn until_seen(stream: &mut TcpStream, seen: &mut String, text: &str, times: usize) -> bool {
    let mut chunk = [0u8; 4096];
    while seen.matches(text).count() < times {
        match tokio::time::timeout(Duration::from_secs(20), stream.read(&mut chunk)).await {
            Ok(Ok(n)) if n > 0 => seen.push_str(&String::from_utf8_lossy(&chunk[..n])),
            _ => return false,
        }
    }
    true
}

/// On the HTTP listener, a connection with no request open for the idle
/// time is closed (half a request is none), while a live view, a request
/// open for as long as it is watched, outlives it however quiet its mission.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_quiet_live_view_outlives_the_http_idle_time_and_a_half_request_does_not() {
    let dir = tempfile::tempdir().unwrap();
    let mut config = coordinator::Config::new(dir.path().join("idle.db"));
    config.http_connections.idle_timeout = Duration::from_millis(300);
    let exec = TestExecutive::start_with_http(config).await;
    let http = exec.http.unwrap();
    let (mut missions, mut fleet) = (exec.missions(), exec.fleet());
    let mission = common::create_mission(&mut missions, 20, 10, "nearest").await;
    let robot = common::register(&mut fleet, mission.id, "scout", 0.5, 0.5).await;

    let mut view = TcpStream::connect(http).await.unwrap();
    let request = format!("GET /api/missions/{}/live HTTP/1.1\r\nHost: {http}\r\n\r\n", mission.id);
    view.write_all(request.as_bytes()).await.unwrap();
    let mut seen = String::new();
    assert!(until_seen(&mut view, &mut seen, "data: ", 1).await, "the view's first frame");

    let mut half = TcpStream::connect(http).await.unwrap();
    half.write_all(b"GET / HTT").await.unwrap();
    assert!(closed_unread(&mut half).await, "half a request is closed after the idle time");

    // The view has now been quiet for longer than the idle time.
    fleet.update_map(common::update(robot.id, 1, 0.5, 0.5, vec![common::patch(0, 0, 5, 5, 0.1)])).await.unwrap();
    assert!(until_seen(&mut view, &mut seen, "data: ", 2).await, "the view is still open: {seen}");
    exec.stop().await;
}

/// The plaintext health listener holds at most its budget, and the health
/// service answers there and on the main port while it is full.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_health_listener_holds_at_most_its_budget() {
    let dir = tempfile::tempdir().unwrap();
    let grpc = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let health = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let (grpc_address, health_address) = (grpc.local_addr().unwrap(), health.local_addr().unwrap());
    let stop = CancellationToken::new();
    let listeners = coordinator::Listeners { grpc, http: None, health: Some(health) };
    let mut config = coordinator::Config::new(dir.path().join("health.db"));
    config.connections.drain_grace = Duration::from_millis(200);
    let grace = config.connections.drain_grace;
    let server = tokio::spawn(coordinator::run_with(listeners, stop.clone().cancelled_owned(), config));
    assert!(answers_a_probe(health_address).await, "the health listener answers");
    let mut held = silent(health_address, coordinator::HEALTH_CONNECTIONS).await;
    assert!(refused(health_address).await, "a connection beyond the budget is closed unread");
    assert_eq!(health_status(grpc_address).await.unwrap(), 1, "the main port serves");
    drop(held.pop());
    assert!(answers_a_probe(health_address).await, "a slot given back answers a probe");
    // Silent peers still connected do not hold the shutdown past the drain grace.
    let stopping = std::time::Instant::now();
    stop.cancel();
    server.await.unwrap().unwrap();
    assert!(stopping.elapsed() < grace + Duration::from_secs(5), "stopped in {:?}", stopping.elapsed());
    drop(held);
}

/// The executive's binary, logging to `dir`/log with `NO_COLOR` unset (a log
/// in a file is plain without it), once it serves; under `ulimit LIMIT`
/// when given (soft and hard with `-n`, soft alone with `-Sn`).
async fn logging_to_a_file(
    dir: &std::path::Path,
    limit: Option<&str>,
) -> (std::process::Child, SocketAddr, SocketAddr) {
    let (port, http_port) = (common::free_port(), common::free_port());
    let log = std::fs::File::create(dir.join("log")).unwrap();
    let ulimit = limit.map_or(String::new(), |limit| format!("ulimit {limit} && "));
    let coordinator = std::process::Command::new("sh")
        .arg("-c")
        .arg(format!(r#"{ulimit}exec "$0" "$@""#))
        .arg(common::binary("coordinator"))
        .args(["--listen", &format!("127.0.0.1:{port}"), "--health-listen", "127.0.0.1:0"])
        .args(["--http", &format!("127.0.0.1:{http_port}")])
        .arg("--db")
        .arg(dir.join("logged.db"))
        .env("RUST_LOG", "warn,coordinator=info")
        .env_remove("NO_COLOR")
        .stdout(log)
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    common::wait_until_serving(&format!("http://127.0.0.1:{port}"), Duration::from_secs(30)).await;
    let address = |port: u16| format!("127.0.0.1:{port}").parse().unwrap();
    (coordinator, address(port), address(http_port))
}

/// The executive's metrics, read from its HTTP listener at `address`.
async fn scraped(address: SocketAddr) -> String {
    let mut stream = TcpStream::connect(address).await.unwrap();
    stream.write_all(b"GET /metrics HTTP/1.1\r\nhost: x\r\nconnection: close\r\n\r\n").await.unwrap();
    let mut text = String::new();
    stream.read_to_string(&mut text).await.unwrap();
    text
}

/// A soft open-files limit of 64 (the usual soft limit is 1 024, a
/// thousand robots' connections) is raised to what the connection limits
/// need when the hard limit allows it: a hundred connections are held and
/// the next is answered.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_low_soft_open_files_limit_is_raised_for_the_connections_allowed() {
    let dir = tempfile::tempdir().unwrap();
    let (mut coordinator, address, _) = logging_to_a_file(dir.path(), Some("-Sn 64")).await;
    let held = silent(address, 100).await;
    let answered = answers_a_probe(address).await;
    drop(held);
    coordinator.kill().unwrap();
    coordinator.wait().unwrap();
    let said = std::fs::read_to_string(dir.path().join("log")).unwrap();
    assert!(said.contains("open-files limit raised") && said.contains("from=64"), "{said}");
    assert!(answered && !said.contains("cannot accept"), "{said}");
}

/// CPU time the process `pid` has used, in clock ticks (Linux).
fn cpu_ticks(pid: u32) -> u64 {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).unwrap();
    // The fields after the command's closing parenthesis; utime and stime
    // are the 14th and 15th of the whole line.
    let after = stat.rsplit_once(')').unwrap().1;
    let fields: Vec<&str> = after.split_whitespace().collect();
    fields[11].parse::<u64>().unwrap() + fields[12].parse::<u64>().unwrap()
}

/// Out of descriptors, accepting fails while connections wait in the
/// backlog, and tonic tries again at once: the executive spun a core (about
/// 100 ticks a second) without a word. It now pauses, says why once a
/// second, and takes connections again when descriptors are freed.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn out_of_descriptors_the_executive_waits_quietly_and_recovers() {
    let dir = tempfile::tempdir().unwrap();
    let (mut coordinator, address, http) = logging_to_a_file(dir.path(), Some("-n 64")).await;
    // More connections than the process has descriptors: the last ones
    // wait in the backlog.
    let mut held = silent(address, 100).await;
    tokio::time::sleep(Duration::from_millis(500)).await;
    let before = cpu_ticks(coordinator.id());
    tokio::time::sleep(Duration::from_secs(2)).await;
    let spent = cpu_ticks(coordinator.id()) - before;
    let said = std::fs::read_to_string(dir.path().join("log")).unwrap();
    assert!(said.contains("the open-files limit is below what the connections allowed need"), "{said}");
    held.clear();
    let recovered = tokio::time::timeout(Duration::from_secs(20), async {
        while !answers_a_probe(address).await {
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    })
    .await;
    let metrics = scraped(http).await;
    coordinator.kill().unwrap();
    coordinator.wait().unwrap();
    assert!(spent < 40, "{spent} ticks of CPU in 2 s while out of descriptors");
    // Operators see it in the metrics too.
    let failed = metrics
        .lines()
        .find(|l| l.starts_with(r#"coordinator_connections_refused_total{listener="gRPC",reason="accept error"}"#))
        .and_then(|l| l.rsplit(' ').next()?.parse::<u64>().ok());
    assert!(failed.is_some_and(|n| n > 0), "{metrics}");
    assert!(said.contains("cannot accept connections") && said.contains("Too many open files"), "{said}");
    assert!(recovered.is_ok(), "no answer after the connections were closed");
}

/// Logs written to a file (or a pipe, or journald) carry no terminal colour
/// codes, which would otherwise stand on every line; `NO_COLOR` is unset,
/// as it is on most machines.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn logs_written_to_a_file_carry_no_colour_codes() {
    let dir = tempfile::tempdir().unwrap();
    let (mut coordinator, _, _) = logging_to_a_file(dir.path(), None).await;
    coordinator.kill().unwrap();
    coordinator.wait().unwrap();
    let said = std::fs::read_to_string(dir.path().join("log")).unwrap();
    assert!(said.contains("executive serving"), "{said}");
    assert!(!said.contains('\u{1b}'), "escape codes in the log: {said:?}");
}
