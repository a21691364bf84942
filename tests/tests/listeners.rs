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

/// A connection to `address` is closed before it sends a byte.
async fn closed_unread(address: SocketAddr) -> bool {
    let mut extra = TcpStream::connect(address).await.unwrap();
    let mut byte = [0u8; 1];
    matches!(tokio::time::timeout(Duration::from_secs(20), extra.read(&mut byte)).await, Ok(Ok(0) | Err(_)))
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
        assert!(closed_unread(http).await, "a connection beyond the limit is closed unread");
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
    assert!(closed_unread(health_address).await, "a connection beyond the budget is closed unread");
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
