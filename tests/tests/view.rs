//! The live mission view (`coordinator --http`): its API asks for the same
//! tokens as gRPC, its stream sends the whole map once and then only what
//! changed, and a person opening the page in a real browser (Chromium,
//! headless) sees the fleet explore.

mod browser;
mod common;

use std::net::SocketAddr;
use std::path::Path;
use std::time::Duration;

use browser::Browser;
use common::TestExecutive;
use exploration_proto::Bearer;
use exploration_proto::v1 as pb;
use exploration_proto::v1::fleet_client::FleetClient;
use exploration_proto::v1::missions_client::MissionsClient;
use serde_json::Value;
use tokio::io::{AsyncBufReadExt, AsyncReadExt, AsyncWriteExt, BufReader};

const OPERATOR: &str = "operator-token-for-the-view-tests";
const VIEWER: &str = "viewer-token-for-the-view-tests";

/// An HTTP/1.1 GET with an optional bearer token: the status and the
/// response, read as a stream of chunks when it is one.
struct Get {
    status: u16,
    reader: BufReader<tokio::net::TcpStream>,
    chunked: bool,
    buffered: String,
}

impl Get {
    async fn send(address: SocketAddr, path: &str, token: Option<&str>) -> Self {
        let mut stream = tokio::net::TcpStream::connect(address).await.unwrap();
        let auth = token.map(|t| format!("Authorization: Bearer {t}\r\n")).unwrap_or_default();
        let request = format!("GET {path} HTTP/1.1\r\nHost: {address}\r\n{auth}Connection: close\r\n\r\n");
        stream.write_all(request.as_bytes()).await.unwrap();
        let mut reader = BufReader::new(stream);
        let mut line = String::new();
        reader.read_line(&mut line).await.unwrap();
        let status = line.split_whitespace().nth(1).and_then(|s| s.parse().ok()).expect("an HTTP status line");
        let mut chunked = false;
        loop {
            line.clear();
            reader.read_line(&mut line).await.unwrap();
            if line.trim().is_empty() {
                break;
            }
            chunked |= line.to_ascii_lowercase().starts_with("transfer-encoding: chunked");
        }
        Self { status, reader, chunked, buffered: String::new() }
    }

    /// The whole body.
    async fn body(mut self) -> String {
        if !self.chunked {
            let mut body = String::new();
            self.reader.read_to_string(&mut body).await.unwrap();
            return body;
        }
        while self.chunk().await {}
        self.buffered
    }

    /// Reads one chunk into the buffer; false at the end.
    async fn chunk(&mut self) -> bool {
        let mut size = String::new();
        self.reader.read_line(&mut size).await.unwrap();
        let size = usize::from_str_radix(size.trim(), 16).unwrap_or(0);
        if size == 0 {
            return false;
        }
        let mut data = vec![0; size + 2];
        self.reader.read_exact(&mut data).await.unwrap();
        self.buffered.push_str(std::str::from_utf8(&data[..size]).unwrap());
        true
    }

    /// The next server-sent event's data, as JSON.
    async fn next_event(&mut self) -> Value {
        loop {
            if let Some(end) = self.buffered.find("\n\n") {
                let block: String = self.buffered.drain(..end + 2).collect();
                let data = block.lines().find_map(|l| l.strip_prefix("data: ")).expect("an event with data");
                return serde_json::from_str(data).unwrap();
            }
            let more = tokio::time::timeout(Duration::from_secs(20), self.chunk()).await.expect("an event within 20 s");
            assert!(more, "the stream ended");
        }
    }
}

fn token_line(name: &str, role: &str, token: &str) -> String {
    format!("{name} {role} {}\n", coordinator::auth::sha256_hex(token))
}

#[tokio::test]
async fn the_view_asks_for_a_token_and_lets_every_valid_one_read() {
    let dir = tempfile::tempdir().unwrap();
    let tokens = dir.path().join("tokens");
    std::fs::write(&tokens, token_line("alice", "operator", OPERATOR) + &token_line("kim", "viewer", VIEWER)).unwrap();
    let mut config = coordinator::Config::new(dir.path().join("view.db"));
    config.operator_tokens_file = Some(tokens);
    let exec = TestExecutive::start_with_http(config).await;
    let http = exec.http.unwrap();

    let mut missions = MissionsClient::with_interceptor(exec.channel(), Bearer::new(Some(OPERATOR)).unwrap());
    let request = pb::CreateMissionRequest {
        name: "watched".into(),
        frame: Some(common::frame(40, 20)),
        policy: Some(pb::PolicySpec { name: "nearest".into(), params: Default::default() }),
        lockstep: true,
        ..Default::default()
    };
    let mission = missions.create_mission(request).await.unwrap().into_inner();
    let mut fleet = FleetClient::with_interceptor(exec.channel(), Bearer::new(Some(OPERATOR)).unwrap());
    let robot_token =
        fleet.register_robot(common::registration(mission.id, "scout", 1.0, 1.0)).await.unwrap().into_inner().token;

    // The page itself holds no data and is open to all; the API is not.
    let page = Get::send(http, "/", None).await;
    assert_eq!(page.status, 200);
    assert!(page.body().await.contains("<canvas id=\"view\""));
    for token in [None, Some("not-a-token-of-this-executive")] {
        let refused = Get::send(http, "/api/missions", token).await;
        assert_eq!(refused.status, 401, "token {token:?}");
        let body: Value = serde_json::from_str(&refused.body().await).unwrap();
        assert!(body["error"].as_str().unwrap().contains("token"), "{body}");
        assert_eq!(Get::send(http, &format!("/api/missions/{}/live", mission.id), token).await.status, 401);
    }
    for token in [OPERATOR, VIEWER, robot_token.as_str()] {
        let listed = Get::send(http, "/api/missions", Some(token)).await;
        assert_eq!(listed.status, 200, "token {token}");
        let body: Value = serde_json::from_str(&listed.body().await).unwrap();
        assert_eq!(body[0]["id"], mission.id);
        assert_eq!(body[0]["name"], "watched");
        assert_eq!(body[0]["policy"], "nearest");
        assert_eq!(body[0]["robots"], 1);
    }
    let missing = Get::send(http, "/api/missions/999/live", Some(VIEWER)).await;
    assert_eq!(missing.status, 404);
    assert!(missing.body().await.contains("999"));
    // Every refusal of the API is the same JSON, a malformed id's too, and
    // what it repeats of the request is escaped.
    for (id, said) in
        [("abc", "\"abc\" is not a mission id"), ("%01x", "\"\\u{1}x\" is not"), ("18446744073709551616", "2^64")]
    {
        let malformed = Get::send(http, &format!("/api/missions/{id}/live"), Some(VIEWER)).await;
        assert_eq!(malformed.status, 400, "{id}");
        let body: Value = serde_json::from_str(&malformed.body().await).unwrap();
        assert!(body["error"].as_str().unwrap().contains(said), "{id}: {body}");
    }
    exec.stop().await;
}

#[tokio::test]
async fn the_stream_sends_the_whole_map_first_then_only_the_cells_that_changed() {
    let dir = tempfile::tempdir().unwrap();
    let exec = TestExecutive::start_with_http(coordinator::Config::new(dir.path().join("view.db"))).await;
    let mut missions = exec.missions();
    let mut fleet = exec.fleet();
    let mission = common::create_mission(&mut missions, 100, 60, "nearest").await;
    let robot = common::register(&mut fleet, mission.id, "scout", 0.5, 0.5).await;
    fleet.update_map(common::update(robot.id, 1, 0.5, 0.5, vec![common::patch(0, 0, 20, 10, 0.1)])).await.unwrap();

    let mut stream = Get::send(exec.http.unwrap(), &format!("/api/missions/{}/live", mission.id), None).await;
    assert_eq!(stream.status, 200);
    let first = stream.next_event().await;
    assert_eq!(first["mission"]["known_cells"], 200);
    assert_eq!(first["robots"][0]["name"], "scout");
    assert_eq!(first["map"]["full"], true);
    let patches = first["map"]["patches"].as_array().unwrap();
    assert_eq!(patches.len(), 1);
    assert_eq!((patches[0]["width"].as_u64(), patches[0]["height"].as_u64()), (Some(100), Some(60)));
    let runs: Vec<u64> = patches[0]["runs"].as_array().unwrap().iter().map(|v| v.as_u64().unwrap()).collect();
    assert_eq!(runs.chunks(2).map(|r| r[1]).sum::<u64>(), 6000, "every cell once");
    // Row 0: 20 free cells (class 1), then 80 unknown (class 0).
    assert_eq!(&runs[..4], &[1, 20, 0, 80]);

    // A wall seen far away: the next update carries that rectangle alone.
    let wall = common::patch(50, 30, 5, 4, 0.9);
    fleet.update_map(common::update(robot.id, 2, 0.5, 0.5, vec![wall])).await.unwrap();
    let changed = loop {
        let event = stream.next_event().await;
        if !event["map"]["patches"].as_array().unwrap().is_empty() {
            break event;
        }
    };
    assert_eq!(changed["map"]["full"], false);
    let expected = serde_json::json!([{ "x": 50, "y": 30, "width": 5, "height": 4, "runs": [2, 20] }]);
    assert_eq!(changed["map"]["patches"], expected);
    assert!(changed["map"]["version"].as_u64() > first["map"]["version"].as_u64());
    exec.stop().await;
}

/// An executive with its live view, and the id of its one mission, whose
/// robot has written [`common::fragmented_map`] over all of it.
async fn with_a_fragmented_map(dir: &Path, width: u32, height: u32) -> (TestExecutive, u64) {
    let exec = TestExecutive::start_with_http(coordinator::Config::new(dir.join("view.db"))).await;
    let (mut missions, mut fleet) = (exec.missions(), exec.fleet());
    let mission = common::create_mission(&mut missions, width, height, "nearest").await;
    let robot = common::register(&mut fleet, mission.id, "scout", 0.15, 0.05).await;
    let map = common::update(robot.id, 1, 0.15, 0.05, vec![common::fragmented_map(width, height)]);
    fleet.update_map(map).await.unwrap();
    (exec, mission.id)
}

/// A map a robot wrote with a class that changes at every cell goes to a
/// viewer in two bits a cell, not as runs of one: the first event of every
/// viewer carries the whole map, and as runs the largest mission's would
/// be about 100 MB of JSON (64 viewers at once: more memory than this
/// machine has).
#[tokio::test]
async fn a_fragmented_map_goes_to_a_viewer_in_a_third_of_a_byte_a_cell() {
    let dir = tempfile::tempdir().unwrap();
    let (width, height) = (600, 400);
    let (exec, mission) = with_a_fragmented_map(dir.path(), width, height).await;
    let mut stream = Get::send(exec.http.unwrap(), &format!("/api/missions/{mission}/live"), None).await;
    assert_eq!(stream.status, 200);
    let first = stream.next_event().await;
    let patch = &first["map"]["patches"][0];
    assert!(patch.get("runs").is_none(), "sent as runs: {}", &patch.to_string()[..200]);
    let packed = patch["packed"].as_str().expect("the cells packed");
    let cells = (width * height) as usize;
    assert!(first.to_string().len() < cells / 3 + 4_096, "{} bytes for {cells} cells", first.to_string().len());
    use base64::Engine as _;
    let bytes = base64::engine::general_purpose::STANDARD.decode(packed).unwrap();
    for (k, (x, y)) in (0..height).flat_map(|y| (0..width).map(move |x| (x, y))).enumerate() {
        let sent = (bytes[k / 4] >> (2 * (k % 4))) & 3;
        assert_eq!(sent, common::fragmented_class(x, y), "cell ({x}, {y})");
    }
    exec.stop().await;
}

/// The page decodes the packed cells into the classes the executive holds.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_page_draws_a_fragmented_map_cell_for_cell() {
    let Some(chromium) = browser::find_chromium() else {
        eprintln!("SKIPPED: no Chromium to load the page in (install Debian's chromium, or set CHROMIUM)");
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let (width, height) = (90, 70);
    let (exec, mission) = with_a_fragmented_map(dir.path(), width, height).await;
    let url = format!("http://{}/#mission={mission}", exec.http.unwrap());
    let shown = tokio::task::block_in_place(|| {
        let mut browser = Browser::launch(&chromium, &dir.path().join("profile"));
        browser.open(&url);
        let live = "state.classes !== null && document.getElementById('status').textContent.includes(' updates')";
        assert!(browser.wait_for(live, Duration::from_secs(60)), "the page went live");
        browser.evaluate("Array.from(state.classes).join('')").as_str().unwrap_or_default().to_owned()
    });
    let expected: String =
        (0..height).flat_map(|y| (0..width).map(move |x| char::from(b'0' + common::fragmented_class(x, y)))).collect();
    assert_eq!(shown, expected);
    exec.stop().await;
}

/// Screenshots of the live page until `done` holds for one; false if
/// none did within 30 s. The page draws on animation frames after each
/// event, so the picture can trail the stream by a frame or two.
fn screenshot_until(browser: &mut Browser, png: &Path, done: impl Fn(&[[u8; 3]]) -> bool) -> bool {
    let deadline = std::time::Instant::now() + Duration::from_secs(30);
    while std::time::Instant::now() < deadline {
        browser.screenshot(png);
        if done(&canvas_pixels(png)) {
            return true;
        }
        std::thread::sleep(Duration::from_millis(200));
    }
    false
}

/// The mission's known cells, from the executive.
async fn known_cells(missions: &mut MissionsClient<tonic::transport::Channel>) -> u64 {
    let listed = missions.list_missions(pb::ListMissionsRequest::default()).await.unwrap().into_inner();
    listed.missions.first().map_or(0, |m| m.known_cells)
}

/// Waits (at most 60 s) until the fleet's mission knows more than `cells` cells.
async fn until_known_beyond(missions: &mut MissionsClient<tonic::transport::Channel>, cells: u64) -> u64 {
    let deadline = tokio::time::Instant::now() + Duration::from_secs(60);
    loop {
        let known = known_cells(missions).await;
        if known > cells {
            return known;
        }
        assert!(tokio::time::Instant::now() < deadline, "the fleet did not get past {cells} known cells");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

const FREE_RGB: [u8; 3] = [255, 255, 255];
const WALL_RGB: [u8; 3] = [31, 41, 55];
const EXPLORING_ROBOT_RGB: [u8; 3] = [37, 99, 235];

/// The map canvas of a screenshot: left of the side panel, below the header.
fn canvas_pixels(png: &Path) -> Vec<[u8; 3]> {
    let image = image::open(png).unwrap().to_rgb8();
    let (width, height) = image.dimensions();
    let mut pixels = Vec::new();
    for y in 40..height {
        for x in 0..width.saturating_sub(450) {
            pixels.push(image.get_pixel(x, y).0);
        }
    }
    pixels
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_person_opening_the_page_sees_the_fleet_explore() {
    let Some(chromium) = browser::find_chromium() else {
        eprintln!("SKIPPED: no Chromium to load the page in (install Debian's chromium, or set CHROMIUM)");
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let exec = TestExecutive::start_with_http(coordinator::Config::new(dir.path().join("view.db"))).await;
    let url = format!("http://{}/", exec.http.unwrap());
    let mut missions = exec.missions();

    // A fleet of three on the bundled warehouse, driving the executive over gRPC.
    let mut run = client_sim::RunConfig::new(common::bundled_map("nav2_warehouse"), 3, "burgard");
    run.server = Some(exec.url.clone());
    run.pace = Some(Duration::from_millis(20));
    run.progress = false;
    let fleet = tokio::spawn(async move { client_sim::run(&run).await });

    let artefacts = Path::new(env!("CARGO_TARGET_TMPDIR")).join("view");
    std::fs::create_dir_all(&artefacts).unwrap();
    let (before, after) = (artefacts.join("fleet-before.png"), artefacts.join("fleet-after.png"));
    let known = until_known_beyond(&mut missions, 6_000).await;

    // A person opens the page and waits until it says it is live.
    let (mut browser, dom) = tokio::task::block_in_place(|| {
        let mut browser = Browser::launch(&chromium, &dir.path().join("profile"));
        browser.open(&url);
        let live = "document.getElementById('status').textContent.includes(' updates') \
                    && ['robot-0', 'robot-1', 'robot-2'].every((r) => document.body.innerText.includes(r))";
        let status = "document.getElementById('status').textContent";
        let became_live = browser.wait_for(live, Duration::from_secs(60));
        assert!(became_live, "the page went live and named the fleet; it says {}", browser.evaluate(status));
        let dom = browser.evaluate("document.documentElement.outerHTML").as_str().unwrap_or_default().to_owned();
        (browser, dom)
    });
    for robot in ["robot-0", "robot-1", "robot-2"] {
        assert!(dom.contains(robot), "{robot} is named on the page");
    }
    let coverage = dom.split("id=\"coverage\">").nth(1).and_then(|s| s.split('<').next()).unwrap_or("");
    let percent: f64 = coverage.trim_end_matches('%').trim().parse().unwrap_or(0.0);
    assert!(percent > 0.0, "the coverage figure is shown: {coverage:?}");

    tokio::task::block_in_place(|| {
        screenshot_until(&mut browser, &before, |pixels| pixels.contains(&EXPLORING_ROBOT_RGB));
    });
    let pixels = canvas_pixels(&before);
    for (colour, what) in [(FREE_RGB, "free space"), (WALL_RGB, "walls"), (EXPLORING_ROBOT_RGB, "exploring robots")] {
        let count = pixels.iter().filter(|p| **p == colour).count();
        assert!(count > 10, "the map shows {what} ({count} pixels of {colour:?}); screenshot {}", before.display());
    }

    // The same page, left open while the fleet maps 3 000 more cells.
    until_known_beyond(&mut missions, known + 3_000).await;
    let differs = |now: &[[u8; 3]]| now.iter().zip(&pixels).filter(|(a, b)| a != b).count();
    tokio::task::block_in_place(|| screenshot_until(&mut browser, &after, |now| differs(now) > 1_000));
    let changed = differs(&canvas_pixels(&after));
    assert!(changed > 1_000, "the picture changed as the fleet moved ({changed} pixels); {}", after.display());
    eprintln!("screenshots: {} and {}", before.display(), after.display());

    fleet.abort();
    exec.stop().await;
}

/// Live views are bounded: past the limit a viewer is refused at once with
/// 503 and a Retry-After, and a view that closes makes room for the next.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn live_views_beyond_the_limit_are_refused_until_one_closes() {
    let dir = tempfile::tempdir().unwrap();
    let exec = TestExecutive::start_with_http(coordinator::Config::new(dir.path().join("views.db"))).await;
    let mut missions = exec.missions();
    let mission = common::create_mission(&mut missions, 20, 10, "nearest").await;
    let (http, path) = (exec.http.unwrap(), format!("/api/missions/{}/live", mission.id));
    let mut open = Vec::new();
    for _ in 0..64 {
        let mut stream = Get::send(http, &path, None).await;
        assert_eq!(stream.status, 200);
        stream.next_event().await;
        open.push(stream);
    }
    let refused = Get::send(http, &path, None).await;
    assert_eq!(refused.status, 503);
    let body: Value = serde_json::from_str(&refused.body().await).unwrap();
    assert!(body["error"].as_str().unwrap().contains("64 live views are open"), "{body}");
    drop(open.pop());
    // The closed view's stream ends when the executive next writes to it:
    // change the mission until a view is admitted again.
    let mut fleet = exec.fleet();
    let robot = common::register(&mut fleet, mission.id, "nudge", 0.5, 0.5).await;
    let mut admitted = false;
    for seq in 1..=200 {
        let x = (seq % 15) as u32;
        fleet.update_map(common::update(robot.id, seq, 0.5, 0.5, vec![common::patch(x, 0, 5, 5, 0.1)])).await.unwrap();
        if Get::send(http, &path, None).await.status == 200 {
            admitted = true;
            break;
        }
    }
    assert!(admitted, "a closed view gives its place back");
    exec.stop().await;
}
