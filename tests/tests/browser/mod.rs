//! Headless Chromium driven over its DevTools protocol, for the browser
//! test: the test waits for what a person would wait for (the page says
//! it is live), instead of guessing how long a page load takes.
//!
//! `--dump-dom` and `--screenshot` with a virtual-time budget were tried
//! first: headless Chromium's page time runs ahead of the network, so a
//! load often ended before the first server-sent event arrived, and no
//! number of retries made that certain.

use std::io::{BufRead, BufReader};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use base64::Engine;
use serde_json::{Value, json};
use tungstenite::stream::MaybeTlsStream;
use tungstenite::{Message, WebSocket};

/// Chromium from `CHROMIUM`, or Debian's `chromium` on the path.
pub fn find_chromium() -> Option<PathBuf> {
    if let Some(path) = std::env::var_os("CHROMIUM") {
        return Some(PathBuf::from(path));
    }
    std::env::var_os("PATH").and_then(|paths| {
        std::env::split_paths(&paths)
            .flat_map(|dir| ["chromium", "chromium-browser"].map(|name| dir.join(name)))
            .find(|p| p.is_file())
    })
}

/// One headless Chromium with one page, killed when dropped. Blocking:
/// call it from `spawn_blocking`.
pub struct Browser {
    chromium: Child,
    socket: WebSocket<MaybeTlsStream<TcpStream>>,
    session: String,
    next_id: u64,
}

impl Browser {
    /// Starts Chromium with a 1280×800 window and attaches to its page.
    pub fn launch(chromium: &Path, profile: &Path) -> Self {
        let mut child = Command::new(chromium)
            .args([
                "--headless",
                "--no-sandbox",
                "--disable-gpu",
                "--hide-scrollbars",
                "--window-size=1280,800",
                "--remote-debugging-port=0",
                "--no-first-run",
            ])
            .arg(format!("--user-data-dir={}", profile.display()))
            .arg("about:blank")
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .expect("Chromium starts");
        let endpoint = devtools_endpoint(&mut child);
        let (socket, _) = tungstenite::connect(endpoint.as_str()).expect("the DevTools socket accepts us");
        // A Chromium that stops answering fails the test instead of hanging it.
        if let MaybeTlsStream::Plain(stream) = socket.get_ref() {
            stream.set_read_timeout(Some(Duration::from_secs(60))).expect("a read timeout");
        }
        let mut browser = Self { chromium: child, socket, session: String::new(), next_id: 0 };
        let targets = browser.call("Target.getTargets", json!({}));
        let page = targets["targetInfos"]
            .as_array()
            .and_then(|all| all.iter().find(|t| t["type"] == "page"))
            .and_then(|t| t["targetId"].as_str())
            .expect("Chromium opened a page")
            .to_owned();
        let attached = browser.call("Target.attachToTarget", json!({ "targetId": page, "flatten": true }));
        browser.session = attached["sessionId"].as_str().expect("a session id").to_owned();
        browser
    }

    /// Opens `url` in the page.
    pub fn open(&mut self, url: &str) {
        let navigated = self.call("Page.navigate", json!({ "url": url }));
        assert!(navigated.get("errorText").is_none(), "the page loads: {navigated}");
    }

    /// The value of a JavaScript expression in the page.
    pub fn evaluate(&mut self, expression: &str) -> Value {
        let result = self.call("Runtime.evaluate", json!({ "expression": expression, "returnByValue": true }));
        result["result"]["value"].clone()
    }

    /// Evaluates `condition` until it is true; false if `patience` runs out first.
    pub fn wait_for(&mut self, condition: &str, patience: Duration) -> bool {
        let deadline = Instant::now() + patience;
        while Instant::now() < deadline {
            if self.evaluate(condition) == Value::Bool(true) {
                return true;
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        false
    }

    /// The page as the browser shows it now, as a PNG file.
    pub fn screenshot(&mut self, png: &Path) {
        let shot = self.call("Page.captureScreenshot", json!({ "format": "png" }));
        let data = shot["data"].as_str().expect("the screenshot's data");
        let bytes = base64::engine::general_purpose::STANDARD.decode(data).expect("base64 from Chromium");
        std::fs::write(png, bytes).unwrap();
    }

    /// Sends one DevTools command and returns its result, skipping the
    /// events that arrive in between.
    fn call(&mut self, method: &str, params: Value) -> Value {
        self.next_id += 1;
        let id = self.next_id;
        let mut command = json!({ "id": id, "method": method, "params": params });
        if !self.session.is_empty() {
            command["sessionId"] = json!(self.session);
        }
        self.socket.send(Message::text(command.to_string())).expect("Chromium takes the command");
        loop {
            let message = self.socket.read().expect("Chromium answers");
            let Ok(text) = message.to_text() else { continue };
            let Ok(reply) = serde_json::from_str::<Value>(text) else { continue };
            if reply["id"] != json!(id) {
                continue;
            }
            assert!(reply.get("error").is_none(), "{method} failed: {}", reply["error"]);
            return reply["result"].clone();
        }
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        let _ = self.chromium.kill();
        let _ = self.chromium.wait();
    }
}

/// Reads Chromium's stderr up to the line that names its DevTools socket,
/// then keeps draining it so that Chromium never blocks on a full pipe.
fn devtools_endpoint(child: &mut Child) -> String {
    let mut lines = BufReader::new(child.stderr.take().expect("stderr is piped")).lines();
    let mut said = Vec::new();
    let endpoint = loop {
        let Some(Ok(line)) = lines.next() else {
            panic!("Chromium exited without a DevTools socket:\n{}", said.join("\n"));
        };
        if let Some(url) = line.strip_prefix("DevTools listening on ") {
            break url.trim().to_owned();
        }
        said.push(line);
    };
    std::thread::spawn(move || lines.for_each(drop));
    endpoint
}
