//! Shared helpers: a real executive on port 0 with a real SQLite file, gRPC
//! clients, the bundled maps and the binaries.

#![allow(dead_code)]

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::Duration;

use tokio_util::sync::CancellationToken;
use tonic::transport::Channel;

use exploration_proto::v1 as pb;
use exploration_proto::v1::fleet_client::FleetClient;
use exploration_proto::v1::missions_client::MissionsClient;

/// An executive served in this process, as `coordinator` serves it.
pub struct TestExecutive {
    pub address: SocketAddr,
    pub url: String,
    /// The HTTP listener's address, when it serves HTTP.
    pub http: Option<SocketAddr>,
    pub db: coordinator::Location,
    stop: CancellationToken,
    task: tokio::task::JoinHandle<Result<(), coordinator::ServeError>>,
}

impl TestExecutive {
    /// Serves on 127.0.0.1:0 with the database `db`.
    pub async fn start(db: impl Into<coordinator::Location>) -> Self {
        Self::start_with(coordinator::Config::new(db)).await
    }

    /// Serves on 127.0.0.1:0 with `config`.
    pub async fn start_with(config: coordinator::Config) -> Self {
        Self::start_listening(config, None).await
    }

    /// Serves gRPC and HTTP (`/metrics`) on ports of 127.0.0.1; the HTTP
    /// address is in `http`.
    pub async fn start_with_http(config: coordinator::Config) -> Self {
        let http = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        Self::start_listening(config, Some(http)).await
    }

    async fn start_listening(config: coordinator::Config, http: Option<tokio::net::TcpListener>) -> Self {
        let http_address = http.as_ref().map(|l| l.local_addr().unwrap());
        let db = config.db.clone();
        // A TLS executive is probed by its test, which holds the CA.
        let probe = config.tls.is_none();
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let address = listener.local_addr().unwrap();
        let stop = CancellationToken::new();
        let listeners = coordinator::Listeners { grpc: listener, http, health: None };
        let task = tokio::spawn(coordinator::run_with(listeners, stop.clone().cancelled_owned(), config));
        let mut exec = Self { address, url: format!("http://{address}"), http: http_address, db, stop, task };
        if probe {
            exec.until_serving().await;
        }
        exec
    }

    /// Waits until the executive answers, or says why it stopped instead.
    async fn until_serving(&mut self) {
        let deadline = tokio::time::Instant::now() + Duration::from_secs(60);
        loop {
            if self.task.is_finished() {
                let outcome = (&mut self.task).await;
                panic!("the executive stopped at start: {outcome:?}");
            }
            let channel = tonic::transport::Endpoint::from_shared(self.url.clone()).unwrap().connect_lazy();
            let mut health = tonic_health::pb::health_client::HealthClient::new(channel);
            if health.check(tonic_health::pb::HealthCheckRequest { service: String::new() }).await.is_ok() {
                return;
            }
            assert!(tokio::time::Instant::now() < deadline, "the executive at {} did not come up", self.url);
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
    }

    /// Starts on `config` and expects the start to fail; returns why.
    pub async fn start_fails(config: coordinator::Config) -> coordinator::ServeError {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let never = std::future::pending::<()>();
        match coordinator::run(listener, never, config).await {
            Err(e) => e,
            Ok(()) => panic!("the executive started"),
        }
    }

    /// Shuts down gracefully and waits until it has stopped.
    pub async fn stop(self) {
        self.stop.cancel();
        self.task.await.unwrap().unwrap();
    }

    pub fn channel(&self) -> Channel {
        tonic::transport::Endpoint::from_shared(self.url.clone()).unwrap().connect_lazy()
    }

    pub fn missions(&self) -> MissionsClient<Channel> {
        MissionsClient::new(self.channel())
    }

    pub fn fleet(&self) -> FleetClient<Channel> {
        FleetClient::new(self.channel())
    }
}

/// A bundled map shipped in `maps/`.
pub fn bundled_map(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../maps").join(format!("{name}.yaml"))
}

/// The shared map collection, when the setting `EXPLORATION_SHARED_MAPS`
/// points at it; `None` (and a line saying what is skipped) otherwise.
pub fn shared_maps(what: &str) -> Option<PathBuf> {
    match std::env::var_os("EXPLORATION_SHARED_MAPS") {
        Some(dir) if Path::new(&dir).join("README.md").exists() => Some(PathBuf::from(dir)),
        _ => {
            eprintln!(
                "SKIPPED {what}: set EXPLORATION_SHARED_MAPS to the folder of the shared maps \
                 (../shared/maps in the development workspace; .ci/run sets it) to run it"
            );
            None
        }
    }
}

/// A fresh PostgreSQL database named after `test`, where
/// `EXPLORATION_POSTGRES_URL` names a server (`.ci/run` starts one).
pub async fn postgres_database(test: &str) -> Option<String> {
    coordinator::store::postgres::test_database(&format!("e2e_{test}")).await
}

/// A binary of the workspace, built by the same cargo invocation as this test.
pub fn binary(name: &str) -> PathBuf {
    let mut dir = std::env::current_exe().unwrap();
    dir.pop();
    if dir.ends_with("deps") {
        dir.pop();
    }
    let path = dir.join(name);
    assert!(
        path.exists(),
        "{} is missing: build the workspace's binaries first (cargo build --workspace --bins)",
        path.display()
    );
    path
}

/// A mission frame of `width` × `height` cells of 0.1 m at the origin.
pub fn frame(width: u32, height: u32) -> pb::MapFrame {
    pb::MapFrame { resolution: 0.1, origin: Some(pb::Point { x: 0.0, y: 0.0 }), width, height }
}

pub async fn create_mission(
    missions: &mut MissionsClient<Channel>,
    width: u32,
    height: u32,
    policy: &str,
) -> pb::Mission {
    missions.create_mission(mission_request(width, height, policy)).await.unwrap().into_inner()
}

/// A request for a mission of `width` × `height` cells under `policy`.
pub fn mission_request(width: u32, height: u32, policy: &str) -> pb::CreateMissionRequest {
    pb::CreateMissionRequest {
        name: "test".into(),
        frame: Some(frame(width, height)),
        policy: Some(pb::PolicySpec { name: policy.into(), params: Default::default() }),
        replan: None,
        scoped_by_communication: false,
        // Each request is answered after the plan it makes due, so that
        // tests read it at once; tests/planner.rs covers the other mode.
        lockstep: true,
        ..Default::default()
    }
}

/// Registration of a point-sized robot with a 2 m sensor at (x, y).
pub fn registration(mission_id: u64, name: &str, x: f64, y: f64) -> pb::RegisterRobotRequest {
    pb::RegisterRobotRequest {
        mission_id,
        name: name.into(),
        capabilities: Some(pb::RobotCapabilities {
            sensor_range_m: 2.0,
            field_of_view_rad: std::f64::consts::TAU,
            speed_mps: 0.5,
            footprint_radius_m: 0.0,
        }),
        pose: Some(pb::Pose { x, y, theta: 0.0 }),
    }
}

pub async fn register(fleet: &mut FleetClient<Channel>, mission_id: u64, name: &str, x: f64, y: f64) -> pb::Robot {
    fleet.register_robot(registration(mission_id, name, x, y)).await.unwrap().into_inner().robot.unwrap()
}

/// A mission's events, oldest first (ListEvents' first page: at most 1 000).
pub async fn events(missions: &mut MissionsClient<Channel>, mission_id: u64) -> Vec<pb::MissionEvent> {
    let request = pb::ListEventsRequest { mission_id, ..Default::default() };
    missions.list_events(request).await.unwrap().into_inner().events
}

/// A probability patch with every cell at `p`.
pub fn patch(x: u32, y: u32, width: u32, height: u32, p: f32) -> pb::MapPatch {
    pb::MapPatch {
        x,
        y,
        width,
        height,
        encoding: pb::CellEncoding::Probability as i32,
        values: vec![p; (width * height) as usize],
        unknown: vec![],
        occupancy: vec![],
    }
}

/// Cell (x, y) of the fragmented map below (a map no building makes, and
/// the worst for anything sized by runs or by frontier cells): its class cycles unknown (0),
/// free (1), occupied (2) along the diagonals, so that no two neighbours in
/// a row share one.
pub fn fragmented_class(x: u32, y: u32) -> u8 {
    ((x + y) % 3) as u8
}

/// A patch of the whole `width` × `height` map in the pattern of
/// [`fragmented_class`].
pub fn fragmented_map(width: u32, height: u32) -> pb::MapPatch {
    let cells = (0..height).flat_map(|y| (0..width).map(move |x| fragmented_class(x, y)));
    let (values, unknown): (Vec<f32>, Vec<u8>) =
        cells.map(|class| ([0.5, 0.1, 0.9][usize::from(class)], u8::from(class == 0))).unzip();
    pb::MapPatch { width, height, values, unknown, ..patch(0, 0, width, height, 0.5) }
}

pub fn update(robot_id: u64, seq: u64, x: f64, y: f64, patches: Vec<pb::MapPatch>) -> pb::UpdateMapRequest {
    pb::UpdateMapRequest { robot_id, seq, pose: Some(pb::Pose { x, y, theta: 0.0 }), patches, ..Default::default() }
}

/// Waits until the executive at `url` answers health checks as SERVING.
pub async fn wait_until_serving(url: &str, within: Duration) {
    let deadline = tokio::time::Instant::now() + within;
    loop {
        let channel = tonic::transport::Endpoint::from_shared(url.to_owned()).unwrap().connect().await;
        if let Ok(channel) = channel {
            let mut health = tonic_health::pb::health_client::HealthClient::new(channel);
            let answer = health.check(tonic_health::pb::HealthCheckRequest { service: String::new() }).await;
            if answer.is_ok_and(|r| {
                r.into_inner().status == tonic_health::pb::health_check_response::ServingStatus::Serving as i32
            }) {
                return;
            }
        }
        assert!(tokio::time::Instant::now() < deadline, "the executive at {url} did not come up");
        tokio::task::yield_now().await;
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

/// A small tmpfs mounted for one test, to fill its disk for real; unmounted
/// when dropped. `None` (and a line saying what is skipped) where mounting
/// is not allowed (not root, no mount namespace).
pub struct Tmpfs {
    dir: tempfile::TempDir,
}

impl Tmpfs {
    pub fn mount(size: &str, what: &str) -> Option<Self> {
        let dir = tempfile::tempdir().unwrap();
        let status = std::process::Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size={size}"), "tmpfs"])
            .arg(dir.path())
            .stderr(std::process::Stdio::null())
            .status();
        if status.is_ok_and(|s| s.success()) {
            Some(Self { dir })
        } else {
            eprintln!("SKIPPED {what}: mounting a {size} tmpfs needs root (CI runs as root)");
            None
        }
    }

    pub fn path(&self) -> &Path {
        self.dir.path()
    }

    /// Fills the disk with a ballast file, then gives `leave` bytes back;
    /// returns the ballast's path (remove it to free the space).
    pub fn fill_leaving(&self, leave: u64) -> PathBuf {
        use std::io::Write;
        let path = self.path().join("ballast");
        let mut file = std::fs::File::create(&path).unwrap();
        let chunk = vec![0xa5u8; 64 * 1024];
        loop {
            if let Err(e) = file.write_all(&chunk) {
                assert_eq!(e.raw_os_error(), Some(28), "only a full disk stops the ballast: {e}");
                break;
            }
        }
        let _ = file.flush();
        let len = file.metadata().unwrap().len();
        file.set_len(len.saturating_sub(leave)).unwrap();
        file.sync_all().unwrap();
        path
    }
}

impl Drop for Tmpfs {
    fn drop(&mut self) {
        let _ = std::process::Command::new("umount").arg("-l").arg(self.dir.path()).status();
    }
}

/// Certificates made for one test: a CA, the executive's certificate for
/// 127.0.0.1 and localhost, and a client certificate, as PEM files in `dir`.
pub struct Pki {
    pub ca: PathBuf,
    pub server_cert: PathBuf,
    pub server_key: PathBuf,
    pub client_cert: PathBuf,
    pub client_key: PathBuf,
    /// A second CA that signed nothing here, to show that trust is checked.
    pub other_ca: PathBuf,
}

impl Pki {
    pub fn new(dir: &Path) -> Self {
        use rcgen::{BasicConstraints, CertificateParams, CertifiedIssuer, IsCa, KeyPair};
        let ca_params = || {
            let mut params = CertificateParams::new(Vec::<String>::new()).unwrap();
            params.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
            params
        };
        let ca = CertifiedIssuer::self_signed(ca_params(), KeyPair::generate().unwrap()).unwrap();
        let other = CertifiedIssuer::self_signed(ca_params(), KeyPair::generate().unwrap()).unwrap();
        let leaf = |names: Vec<String>| {
            let key = KeyPair::generate().unwrap();
            let mut params = CertificateParams::new(names.clone()).unwrap();
            // A subject of its own: OpenSSL (the Python client's gRPC) takes
            // a certificate named as its issuer for a self-signed one.
            params.distinguished_name.push(rcgen::DnType::CommonName, names[0].clone());
            let cert = params.signed_by(&key, &ca).unwrap();
            (cert.pem(), key.serialize_pem())
        };
        let (server_cert, server_key) = leaf(vec!["127.0.0.1".into(), "localhost".into()]);
        let (client_cert, client_key) = leaf(vec!["robot-0".into()]);
        let write = |name: &str, text: &str| {
            let path = dir.join(name);
            std::fs::write(&path, text).unwrap();
            path
        };
        Self {
            ca: write("ca.pem", &ca.pem()),
            server_cert: write("server.pem", &server_cert),
            server_key: write("server.key", &server_key),
            client_cert: write("client.pem", &client_cert),
            client_key: write("client.key", &client_key),
            other_ca: write("other-ca.pem", &other.pem()),
        }
    }
}

/// Waits until the TLS executive at `url` answers health checks as SERVING.
pub async fn wait_until_serving_tls(url: &str, tls: &exploration_proto::client::ClientTls, within: Duration) {
    let deadline = tokio::time::Instant::now() + within;
    loop {
        let channel = exploration_proto::client::endpoint(url, Some(tls)).unwrap().connect().await;
        if let Ok(channel) = channel {
            let mut health = tonic_health::pb::health_client::HealthClient::new(channel);
            let answer = health.check(tonic_health::pb::HealthCheckRequest { service: String::new() }).await;
            if answer.is_ok() {
                return;
            }
        }
        assert!(tokio::time::Instant::now() < deadline, "the executive at {url} did not come up");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

/// A port of 127.0.0.1 that nothing listens on, for a binary to be told to
/// listen on. It lies below Linux's ephemeral range (32 768 and up), from
/// which `bind(0)` picks and the kernel gives outgoing connections their
/// ports: a port from `bind(0)`, released for the binary, could be taken
/// by another test's client socket first (it was once in CI: "cannot listen
/// on 127.0.0.1:37297: Address already in use"). Each test process takes
/// its ports in turn from its own start in 20 000–32 000.
pub fn free_port() -> u16 {
    use std::sync::atomic::{AtomicU32, Ordering};
    const LOW: u32 = 20_000;
    const SPAN: u32 = 12_000;
    static NEXT: AtomicU32 = AtomicU32::new(0);
    let start = std::process::id().wrapping_mul(997);
    loop {
        let port = LOW + start.wrapping_add(NEXT.fetch_add(1, Ordering::Relaxed)) % SPAN;
        let port = u16::try_from(port).expect("below 32 000");
        if std::net::TcpListener::bind(("127.0.0.1", port)).is_ok() {
            return port;
        }
    }
}

/// The `coordinator` binary serving `db` on 127.0.0.1:`port`, logging at `log`.
pub fn spawn_coordinator(port: u16, db: &Path, log: &str) -> std::process::Child {
    std::process::Command::new(binary("coordinator"))
        .args(["--listen", &format!("127.0.0.1:{port}"), "--db"])
        .arg(db)
        .env("RUST_LOG", log)
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::inherit())
        .spawn()
        .expect("coordinator starts")
}

/// GET `path` from an HTTP/1.1 server; the body.
pub async fn http_get(address: SocketAddr, path: &str) -> String {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let mut stream = tokio::net::TcpStream::connect(address).await.unwrap();
    let request = format!("GET {path} HTTP/1.1\r\nHost: {address}\r\nConnection: close\r\n\r\n");
    stream.write_all(request.as_bytes()).await.unwrap();
    let mut response = String::new();
    stream.read_to_string(&mut response).await.unwrap();
    let (head, body) = response.split_once("\r\n\r\n").expect("an HTTP response");
    assert!(head.starts_with("HTTP/1.1 200"), "{head}");
    body.to_owned()
}

/// Runs the `coordinator` binary with `args` until it exits (it is killed
/// if it is still serving after a minute); returns its success and stderr.
pub fn coordinator_exits(args: &[&str], db: &std::path::Path) -> (bool, String) {
    let mut child = std::process::Command::new(binary("coordinator"))
        .args(["--listen", "127.0.0.1:0", "--db"])
        .arg(db)
        .args(args)
        .env("RUST_LOG", "warn")
        .env("RUST_BACKTRACE", "0")
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let deadline = std::time::Instant::now() + Duration::from_secs(60);
    while child.try_wait().unwrap().is_none() {
        if std::time::Instant::now() > deadline {
            child.kill().unwrap();
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    let output = child.wait_with_output().unwrap();
    (output.status.success(), String::from_utf8_lossy(&output.stderr).into_owned())
}
