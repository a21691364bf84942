//! The executive a run starts for itself on loopback, when it is not given
//! one: simulated time for experiments, durable commits for load tests.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;

use tokio_util::sync::CancellationToken;

use super::SimError;

/// An executive on loopback, owned by the run; stopped when dropped.
pub(crate) struct EmbeddedExecutive {
    pub(crate) url: String,
    /// Its operator token.
    pub(crate) token: String,
    /// Its clock, moved on with the simulation's steps; `None`: the wall clock.
    pub(super) clock: Option<Arc<coordinator::ManualClock>>,
    stop: CancellationToken,
    task: Option<tokio::task::JoinHandle<Result<(), coordinator::ServeError>>>,
    /// Holds the database (unless one was given) and the view's tokens file.
    _dir: tempfile::TempDir,
}

impl Drop for EmbeddedExecutive {
    fn drop(&mut self) {
        // A run abandoned midway (a time limit) must not leave its executive serving.
        self.stop.cancel();
    }
}

impl EmbeddedExecutive {
    pub(super) async fn start(
        db: Option<PathBuf>,
        operator_token: String,
        view: Option<SocketAddr>,
    ) -> Result<Self, SimError> {
        // The fleet waits for every acknowledgement: a crash of this process
        // takes the fleet with it, so power-cut durability buys nothing here.
        // Its time is the simulation's: leases, stalls and replanning
        // intervals in simulated seconds, the same on any machine.
        Self::start_with(db, operator_token, coordinator::Durability::Normal, true, view).await
    }

    /// An executive as a deployment runs one (every commit survives a power
    /// cut), for load tests; with a random operator token unless given one.
    pub(crate) async fn start_durable(token: Option<String>) -> Result<Self, SimError> {
        let token = match token {
            Some(token) => token,
            None => coordinator::auth::random_operator_token().map_err(|e| SimError::Executive(e.to_string()))?,
        };
        Self::start_with(None, token, coordinator::Durability::Full, false, None).await
    }

    async fn start_with(
        db: Option<PathBuf>,
        operator_token: String,
        durability: coordinator::Durability,
        simulated_time: bool,
        view: Option<SocketAddr>,
    ) -> Result<Self, SimError> {
        let failed = |e: &dyn std::fmt::Display| SimError::Executive(e.to_string());
        let dir = tempfile::tempdir().map_err(|e| failed(&e))?;
        let path = db.unwrap_or_else(|| dir.path().join("coordinator.db"));
        let listener =
            tokio::net::TcpListener::bind("127.0.0.1:0").await.map_err(|e| SimError::Executive(e.to_string()))?;
        let address = listener.local_addr().map_err(|e| SimError::Executive(e.to_string()))?;
        let stop = CancellationToken::new();
        let shutdown = stop.clone().cancelled_owned();
        let mut config = coordinator::Config::new(path);
        config.operator_token = Some(operator_token.clone());
        config.durability = durability;
        let clock = simulated_time.then(|| {
            let (clock, handle) = coordinator::Clock::manual();
            config.executive.clock = clock;
            handle
        });
        let http = match view {
            Some(address) => {
                let http = tokio::net::TcpListener::bind(address).await.map_err(|e| failed(&e))?;
                let viewer = coordinator::auth::random_viewer_token().map_err(|e| failed(&e))?;
                let tokens = dir.path().join("tokens");
                let line = format!("viewer viewer {}\n", coordinator::auth::sha256_hex(&viewer));
                std::fs::write(&tokens, line).map_err(|e| failed(&e))?;
                config.operator_tokens_file = Some(tokens);
                let url = http.local_addr().map_err(|e| failed(&e))?;
                crate::errln!("live view: http://{url}/  (read-only token: {viewer})");
                if !url.ip().is_loopback() {
                    crate::errln!(
                        "warning: the view is served in plaintext on {}, so its token crosses the network \
                         unencrypted; bind it to 127.0.0.1 unless the network is yours",
                        url.ip()
                    );
                }
                Some(http)
            }
            None => None,
        };
        let listeners = coordinator::Listeners { grpc: listener, http, health: None };
        let task = tokio::spawn(coordinator::run_with(listeners, shutdown, config));
        Ok(Self { url: format!("http://{address}"), token: operator_token, clock, stop, task: Some(task), _dir: dir })
    }

    pub(crate) async fn stop(mut self) -> Result<(), SimError> {
        self.stop.cancel();
        let Some(task) = self.task.take() else { return Ok(()) };
        match task.await {
            Ok(Ok(())) => Ok(()),
            Ok(Err(e)) => Err(SimError::Executive(e.to_string())),
            Err(e) => Err(SimError::Executive(e.to_string())),
        }
    }
}
