//! Tokens travel encrypted: the executive serves TLS with certificates made
//! in the test (rcgen), the project's clients verify it, and with a client
//! CA it admits only robots that present a certificate signed by it.

mod common;

use std::process::{Command, Stdio};
use std::time::Duration;

use common::{Pki, TestExecutive, bundled_map, wait_until_serving, wait_until_serving_tls};
use exploration_proto::client::{ClientTls, endpoint};
use exploration_proto::v1 as pb;
use exploration_proto::v1::missions_client::MissionsClient;

const TOKEN: &str = "tls-operator-token-0001";

/// `fleet-sim run --server https://… --tls-ca ca.pem` against
/// `coordinator --tls-cert … --tls-key …`: the issue's own command.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_fleet_explores_through_tls_with_the_real_binaries() {
    let dir = tempfile::tempdir().unwrap();
    let pki = Pki::new(dir.path());
    let (port, health_port) = (common::free_port(), common::free_port());
    let mut coordinator = Command::new(common::binary("coordinator"))
        .args(["--listen", &format!("127.0.0.1:{port}"), "--health-listen", &format!("127.0.0.1:{health_port}")])
        .arg("--db")
        .arg(dir.path().join("tls.db"))
        .arg("--tls-cert")
        .arg(&pki.server_cert)
        .arg("--tls-key")
        .arg(&pki.server_key)
        .args(["--operator-token", TOKEN])
        .env("RUST_LOG", "warn")
        .stdout(Stdio::null())
        .spawn()
        .unwrap();
    let url = format!("https://127.0.0.1:{port}");
    let tls = ClientTls::from_files(Some(&pki.ca), None, None).unwrap();
    wait_until_serving_tls(&url, &tls, Duration::from_secs(30)).await;
    // Probes that speak no TLS ask the plaintext health listener; the API
    // port speaks only TLS.
    wait_until_serving(&format!("http://127.0.0.1:{health_port}"), Duration::from_secs(5)).await;
    assert!(list(&format!("http://127.0.0.1:{port}"), None).await.is_err(), "the API answered in plaintext");

    let fleet = Command::new(common::binary("fleet-sim"))
        .args(["run", "--server", &url, "--tls-ca"])
        .arg(&pki.ca)
        .arg("--map")
        .arg(bundled_map("nav2_depot"))
        .args(["--robots", "2", "--policy", "nearest", "--cell-size", "0.4", "--json"])
        .env("COORDINATOR_OPERATOR_TOKEN", TOKEN)
        .env("RUST_LOG", "warn")
        .output();
    let fleet = tokio::task::spawn_blocking(move || fleet).await.unwrap().unwrap();
    coordinator.kill().unwrap();
    coordinator.wait().unwrap();
    assert!(fleet.status.success(), "fleet-sim failed: {}", String::from_utf8_lossy(&fleet.stderr));
    let stdout = String::from_utf8_lossy(&fleet.stdout);
    let report: serde_json::Value = serde_json::from_str(stdout.lines().last().unwrap()).unwrap();
    assert_eq!(report["completed"], true, "{report}");
    assert_eq!(report["coverage"], 1.0, "{report}");
}

async fn list(url: &str, tls: Option<&ClientTls>) -> Result<usize, String> {
    // A deadline, so that a connection neither answered nor closed fails
    // with its step named instead of hanging the test run (it did once, in
    // about a dozen CI runs).
    let deadline = Duration::from_secs(20);
    let endpoint = endpoint(url, tls).map_err(|e| e.to_string())?;
    let channel = tokio::time::timeout(deadline, endpoint.connect())
        .await
        .map_err(|_| format!("connecting to {url}: no answer in {deadline:?}"))?
        .map_err(|e| format!("{e:?}"))?;
    let bearer = exploration_proto::Bearer::new(Some(TOKEN)).unwrap();
    let mut missions = MissionsClient::with_interceptor(channel, bearer);
    let listed = tokio::time::timeout(deadline, missions.list_missions(pb::ListMissionsRequest::default()))
        .await
        .map_err(|_| format!("ListMissions on {url}: no answer in {deadline:?}"))?
        .map_err(|s| s.to_string())?;
    Ok(listed.into_inner().missions.len())
}

/// With a client CA, only clients presenting a certificate it signed get
/// in; and clients check the executive's certificate against their CA.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn mutual_tls_admits_only_certified_clients_and_clients_check_the_server() {
    let dir = tempfile::tempdir().unwrap();
    let pki = Pki::new(dir.path());
    let mut config = coordinator::Config::new(dir.path().join("mtls.db"));
    config.tls = Some(coordinator::TlsConfig::from_files(&pki.server_cert, &pki.server_key, Some(&pki.ca)).unwrap());
    config.operator_token = Some(TOKEN.into());
    let exec = TestExecutive::start_with(config).await;
    let url = format!("https://{}", exec.address);

    let certified = ClientTls::from_files(Some(&pki.ca), Some(&pki.client_cert), Some(&pki.client_key)).unwrap();
    assert_eq!(list(&url, Some(&certified)).await, Ok(0));
    let anonymous = ClientTls::from_files(Some(&pki.ca), None, None).unwrap();
    let refused = list(&url, Some(&anonymous)).await;
    eprintln!("without a client certificate: {refused:?}");
    assert!(refused.is_err(), "no client certificate, no entry");
    let wrong_trust =
        ClientTls::from_files(Some(&pki.other_ca), Some(&pki.client_cert), Some(&pki.client_key)).unwrap();
    assert!(list(&url, Some(&wrong_trust)).await.is_err(), "the client refuses a server its CA did not sign");
    let plaintext = format!("http://{}", exec.address);
    let refused = list(&plaintext, None).await;
    eprintln!("plaintext on the TLS port: {refused:?}");
    assert!(refused.is_err(), "no plaintext on a TLS port");
    exec.stop().await;
}

/// GET `path` over HTTPS, trusting `ca`: the status line and the body.
async fn https_get(address: std::net::SocketAddr, ca: &std::path::Path, path: &str, token: &str) -> (String, String) {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    use tokio_rustls::rustls::pki_types::pem::PemObject;
    use tokio_rustls::rustls::pki_types::{CertificateDer, ServerName};
    use tokio_rustls::rustls::{ClientConfig, RootCertStore};

    let mut roots = RootCertStore::empty();
    for cert in CertificateDer::pem_file_iter(ca).unwrap() {
        roots.add(cert.unwrap()).unwrap();
    }
    let provider = std::sync::Arc::new(tokio_rustls::rustls::crypto::ring::default_provider());
    let config = ClientConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .unwrap()
        .with_root_certificates(roots)
        .with_no_client_auth();
    let connector = tokio_rustls::TlsConnector::from(std::sync::Arc::new(config));
    let tcp = tokio::net::TcpStream::connect(address).await.unwrap();
    let mut tls = connector.connect(ServerName::try_from("127.0.0.1").unwrap(), tcp).await.unwrap();
    let request =
        format!("GET {path} HTTP/1.1\r\nHost: {address}\r\nAuthorization: Bearer {token}\r\nConnection: close\r\n\r\n");
    tls.write_all(request.as_bytes()).await.unwrap();
    let mut response = Vec::new();
    // A peer that closes without close_notify is fine here: the body is complete.
    let _ = tls.read_to_end(&mut response).await;
    let response = String::from_utf8_lossy(&response).into_owned();
    let (head, body) = response.split_once("\r\n\r\n").expect("an HTTP response");
    (head.lines().next().unwrap_or("").to_owned(), body.to_owned())
}

/// The view's listener carries tokens as gRPC does: where gRPC has TLS,
/// HTTP is HTTPS with the same certificate, and plaintext gets nothing.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_live_view_speaks_https_where_the_executive_has_tls() {
    let dir = tempfile::tempdir().unwrap();
    let pki = Pki::new(dir.path());
    let mut config = coordinator::Config::new(dir.path().join("https.db"));
    config.tls = Some(coordinator::TlsConfig::from_files(&pki.server_cert, &pki.server_key, None).unwrap());
    config.operator_token = Some(TOKEN.into());
    let exec = TestExecutive::start_with_http(config).await;
    let url = format!("https://{}", exec.address);
    let tls = ClientTls::from_files(Some(&pki.ca), None, None).unwrap();
    wait_until_serving_tls(&url, &tls, Duration::from_secs(30)).await;
    let http = exec.http.unwrap();

    let (status, body) = https_get(http, &pki.ca, "/api/missions", TOKEN).await;
    assert!(status.starts_with("HTTP/1.1 200"), "{status}");
    assert_eq!(body.trim(), "[]");
    let (status, _) = https_get(http, &pki.ca, "/api/missions", "not-the-token-at-all").await;
    assert!(status.starts_with("HTTP/1.1 401"), "{status}");

    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let mut plain = tokio::net::TcpStream::connect(http).await.unwrap();
    plain.write_all(b"GET /api/missions HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n").await.unwrap();
    let mut answer = Vec::new();
    let _ = tokio::time::timeout(Duration::from_secs(20), plain.read_to_end(&mut answer)).await;
    assert!(!String::from_utf8_lossy(&answer).contains("HTTP/1.1"), "no plaintext HTTP answer on the TLS port");
    exec.stop().await;
}

/// A user who mixes up TLS and plaintext, or trusts the wrong CA, is told
/// what to change, not only what the transport saw ("frame with invalid
/// size" is all h2 can say of a TLS record).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn coordctl_says_what_to_change_when_tls_and_plaintext_are_mixed_up() {
    let dir = tempfile::tempdir().unwrap();
    let pki = Pki::new(dir.path());
    let mut config = coordinator::Config::new(dir.path().join("tls.db"));
    config.tls = Some(coordinator::TlsConfig::from_files(&pki.server_cert, &pki.server_key, None).unwrap());
    config.operator_token = Some(TOKEN.into());
    let tls_exec = TestExecutive::start_with(config).await;
    let plain_exec = TestExecutive::start(dir.path().join("plain.db")).await;

    let coordctl = |url: String, ca: Option<&std::path::Path>| {
        let mut command = Command::new(common::binary("coordctl"));
        command.args(["--server", &url, "--token", TOKEN]);
        if let Some(ca) = ca {
            command.arg("--tls-ca").arg(ca);
        }
        let output = command.arg("missions").output();
        tokio::task::spawn_blocking(move || {
            let output = output.unwrap();
            assert!(!output.status.success());
            String::from_utf8_lossy(&output.stderr).into_owned()
        })
    };
    let plaintext_to_tls = coordctl(format!("http://{}", tls_exec.address), None).await.unwrap();
    assert!(plaintext_to_tls.contains("if the executive there serves TLS, use https://"), "{plaintext_to_tls}");
    let tls_to_plaintext = coordctl(format!("https://{}", plain_exec.address), Some(&pki.ca)).await.unwrap();
    assert!(tls_to_plaintext.contains("does not serve TLS: use http://"), "{tls_to_plaintext}");
    let wrong_ca = coordctl(format!("https://{}", tls_exec.address), Some(&pki.other_ca)).await.unwrap();
    assert!(wrong_ca.contains("not signed by the CA given with --tls-ca"), "{wrong_ca}");
    for said in [&plaintext_to_tls, &tls_to_plaintext, &wrong_ca] {
        assert_eq!(said.lines().count(), 1, "one line: {said}");
    }
    tls_exec.stop().await;
    plain_exec.stop().await;
}
