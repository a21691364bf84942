//! `coordctl`: the operator's command line for the exploration executive.
//!
//! It only speaks the public gRPC API, so everything it does a fleet manager
//! or a script can do too. Exit codes: 0 done, 1 other failure, 2 bad usage,
//! 3 not found, 4 refused in the current state (precondition, invalid
//! argument, limits), 5 not authenticated or not allowed.

mod output;
mod picture;

use std::collections::HashMap;
use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context, anyhow, bail};
use clap::{Parser, Subcommand};
use exploration_proto::replicas::Replicas;
use tonic::Code;
use tonic::service::interceptor::InterceptedService;

use exploration_proto::Bearer;
use exploration_proto::v1 as pb;
use exploration_proto::v1::missions_client::MissionsClient;
use exploration_proto::v1::override_robot_request::{Action, Cancel, Hold, Home, Release};

#[derive(Debug, Parser)]
#[command(name = "coordctl", version, about = "Watch and steer robot fleets exploring through the executive")]
struct Cli {
    /// The executive's address; replicas sharing a database: their addresses, comma-separated.
    #[arg(long, global = true, env = "COORDINATOR_URL", default_value = "http://127.0.0.1:50051")]
    server: String,
    /// The operator token (see `coordinator --operator-token`).
    #[arg(long, global = true, env = "COORDINATOR_TOKEN", hide_env_values = true)]
    token: Option<String>,
    /// Your name, recorded with every change you make on an executive that
    /// runs open; one that checks tokens records the name of your token.
    #[arg(long = "as", global = true, env = "USER", default_value = "operator")]
    actor: String,
    /// PEM CA certificate(s) to trust for an `https://` executive (default:
    /// the system's roots).
    #[arg(long, global = true, env = "COORDINATOR_TLS_CA")]
    tls_ca: Option<std::path::PathBuf>,
    /// PEM client certificate, when the executive asks for one (mutual TLS).
    #[arg(long, global = true, env = "COORDINATOR_TLS_CLIENT_CERT", requires = "tls_key")]
    tls_cert: Option<std::path::PathBuf>,
    /// PEM key of --tls-cert.
    #[arg(long, global = true, env = "COORDINATOR_TLS_CLIENT_KEY", requires = "tls_cert")]
    tls_key: Option<std::path::PathBuf>,
    /// Print JSON instead of tables.
    #[arg(long, global = true)]
    json: bool,
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// List, show, create, pause or resume missions, or change a mission's
    /// policy (`missions` alone lists them).
    #[command(visible_alias = "mission")]
    Missions {
        #[command(subcommand)]
        command: Option<MissionCommand>,
    },
    /// List the policies the executive offers, with their parameters.
    Policies,
    /// List a mission's robots: state, task, pose, liveness.
    Robots { mission: u64 },
    /// A mission's or a robot's task timeline, newest first.
    #[command(visible_alias = "history")]
    Tasks {
        mission: u64,
        /// Only this robot's (id, or name).
        #[arg(long)]
        robot: Option<String>,
        /// Only tasks of this kind.
        #[arg(long, value_parser = ["explore", "goto", "hold", "home", "pin"])]
        kind: Option<String>,
        /// Only tasks that have not ended.
        #[arg(long)]
        open: bool,
        /// At most this many.
        #[arg(long, default_value_t = 50)]
        limit: u32,
        /// Every transition of every task, with who and why.
        #[arg(long)]
        history: bool,
    },
    /// The mission's events: policy changes, overrides, pauses, lost robots ...
    Events { mission: u64 },
    /// Give a robot an operator task, or hand it back to the policy.
    Override {
        mission: u64,
        /// The robot's name or id.
        robot: String,
        #[command(subcommand)]
        action: OverrideAction,
        /// Why, for the record.
        #[arg(long, global = true, default_value = "")]
        reason: String,
    },
    /// Pin the frontier at x,y to a robot: it explores it, the others keep
    /// away (the same as `override MISSION ROBOT pin X,Y`).
    Pin {
        mission: u64,
        robot: String,
        #[arg(value_parser = parse_point, allow_hyphen_values = true)]
        point: pb::Point,
        #[arg(long, default_value = "")]
        reason: String,
    },
    /// Forbid a rectangle (metres: x0,y0,x1,y1): no target is assigned inside.
    Forbid {
        mission: u64,
        #[arg(value_parser = parse_rect, allow_hyphen_values = true)]
        area: pb::Rect,
        #[arg(long, default_value = "")]
        reason: String,
    },
    /// Lift a forbidden region.
    Allow {
        mission: u64,
        region: u64,
        #[arg(long, default_value = "")]
        reason: String,
    },
    /// Follow a mission live: one line (or JSON object) per change.
    Watch {
        mission: u64,
        /// Stop after this many views.
        #[arg(long)]
        count: Option<usize>,
    },
    /// Give a mission its rooms and corridors (Wurm et al. 2008, §VI): the
    /// segmentation of the finished building's map at MAP (map_server YAML
    /// of the same area as the mission's map), which the `segmentation`
    /// policy then plans on; or `--online` to go back to segmenting the
    /// explored map as it grows.
    Rooms {
        mission: u64,
        #[arg(required_unless_present = "online", conflicts_with = "online")]
        map: Option<PathBuf>,
        #[arg(long)]
        online: bool,
        #[arg(long, default_value = "")]
        reason: String,
    },
    /// The fused map.
    #[command(subcommand)]
    Map(MapCommand),
    /// A consistent copy of the executive's whole database, taken while
    /// missions run, written to FILE (which must not exist); start a
    /// coordinator with `--db FILE` to resume from it.
    Backup { file: std::path::PathBuf },
}

#[derive(Debug, Subcommand)]
enum MapCommand {
    /// Export the fused map as a PNG: occupancy, frontier, segments, robots,
    /// targets and forbidden regions.
    Export {
        mission: u64,
        #[arg(long)]
        png: PathBuf,
        /// Size of the longer side, pixels.
        #[arg(long, default_value_t = 1200)]
        px: u32,
        /// Tint the segmentation's segments.
        #[arg(long)]
        segments: bool,
    },
}

#[derive(Debug, Subcommand)]
enum MissionCommand {
    /// Every mission with its state and counters.
    List,
    /// Everything about one mission.
    Show { mission: u64 },
    /// Create a mission over the frame of a map_server YAML, or an explicit frame.
    Create {
        #[arg(long, default_value = "mission")]
        name: String,
        /// Take the frame (size, resolution, origin) from this map.
        #[arg(long, conflicts_with_all = ["width", "height"])]
        map: Option<PathBuf>,
        #[arg(long, requires = "height")]
        width: Option<u32>,
        #[arg(long, requires = "width")]
        height: Option<u32>,
        /// Metres per cell (with --map: defaults to the map's).
        #[arg(long)]
        resolution: Option<f64>,
        /// World position of cell (0, 0)'s lower-left corner, x,y.
        #[arg(long, value_parser = parse_point)]
        origin: Option<pb::Point>,
        #[arg(long, default_value = "burgard")]
        policy: String,
        /// A policy parameter, name=value; repeat for more.
        #[arg(long = "param", value_parser = parse_param)]
        params: Vec<(String, f64)>,
        /// Seconds without news after which a robot loses its task.
        #[arg(long)]
        lease: Option<f64>,
        /// Seconds without progress after which a task fails.
        #[arg(long)]
        stall: Option<f64>,
        /// Where robots meet when exploration is done, x,y.
        #[arg(long, value_parser = parse_point)]
        rendezvous: Option<pb::Point>,
    },
    /// Robots hold where they are until resumed.
    Pause {
        mission: u64,
        #[arg(long, default_value = "")]
        reason: String,
    },
    /// Robots get targets again.
    Resume {
        mission: u64,
        #[arg(long, default_value = "")]
        reason: String,
    },
    /// Show the policy, or switch to another one while the mission runs.
    Policy {
        mission: u64,
        name: Option<String>,
        #[arg(long = "param", value_parser = parse_param)]
        params: Vec<(String, f64)>,
        #[arg(long, default_value = "")]
        reason: String,
    },
}

#[derive(Debug, Clone, Subcommand)]
enum OverrideAction {
    /// Go to a point x,y (metres); done on arrival.
    Goto {
        #[arg(value_parser = parse_point, allow_hyphen_values = true)]
        point: pb::Point,
    },
    /// Explore a rectangle x0,y0,x1,y1; done when no reachable frontier is left inside.
    Region {
        #[arg(value_parser = parse_rect, allow_hyphen_values = true)]
        area: pb::Rect,
    },
    /// Explore the frontier at x,y; other robots stay away from it meanwhile.
    Pin {
        #[arg(value_parser = parse_point, allow_hyphen_values = true)]
        point: pb::Point,
    },
    /// Stay put until released.
    Hold,
    /// Go to its start pose (or the rendezvous).
    Home,
    /// End its current task and hand it back to the policy.
    Release,
    /// Cancel its override and hand it back to the policy.
    Cancel,
}

type Missions = MissionsClient<InterceptedService<Replicas, Bearer>>;

#[tokio::main(flavor = "current_thread")]
async fn main() -> ExitCode {
    let cli = match Cli::try_parse() {
        Ok(cli) => cli,
        Err(e) => {
            let _ = e.print();
            return ExitCode::from(if e.use_stderr() { 2 } else { 0 });
        }
    };
    match run(cli).await {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            match e.downcast_ref::<tonic::Status>() {
                Some(status) => eprintln!("coordctl: {:?}: {}", status.code(), status.message()),
                None => eprintln!("coordctl: {e:#}"),
            }
            ExitCode::from(exit_code(&e))
        }
    }
}

/// Sorts failures into the exit codes the module documents.
fn exit_code(error: &anyhow::Error) -> u8 {
    match error.downcast_ref::<tonic::Status>().map(tonic::Status::code) {
        Some(Code::NotFound) => 3,
        Some(Code::InvalidArgument | Code::FailedPrecondition | Code::ResourceExhausted | Code::OutOfRange) => 4,
        Some(Code::Unauthenticated | Code::PermissionDenied) => 5,
        _ if error.downcast_ref::<Usage>().is_some() => 2,
        _ => 1,
    }
}

/// A mistake in the command line that clap cannot see.
#[derive(Debug)]
struct Usage(String);

impl std::fmt::Display for Usage {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for Usage {}

async fn connect(cli: &Cli) -> anyhow::Result<Missions> {
    for replica in cli.server.split(',') {
        if let Some(warning) = exploration_proto::client::plaintext_token_warning(replica.trim(), cli.token.as_deref())
        {
            eprintln!("warning: {warning}");
        }
    }
    let tls = match (&cli.tls_ca, &cli.tls_cert) {
        (None, None) => None,
        _ => Some(
            exploration_proto::client::ClientTls::from_files(
                cli.tls_ca.as_deref(),
                cli.tls_cert.as_deref(),
                cli.tls_key.as_deref(),
            )
            .map_err(|e| Usage(format!("TLS files: {e}")))?,
        ),
    };
    let channel =
        Replicas::from_list(&cli.server, tls.as_ref()).map_err(|e| Usage(format!("--server {}: {e}", cli.server)))?;
    let bearer = Bearer::new(cli.token.as_deref()).map_err(|_| Usage("the token holds invalid characters".into()))?;
    // A whole map of a big mission is larger than gRPC's default 4 MiB.
    Ok(MissionsClient::with_interceptor(channel, bearer)
        .max_decoding_message_size(exploration_proto::MAX_MESSAGE_BYTES))
}

/// How long `watch` waits for an executive (or the replica that holds the
/// mission) to answer again before it gives up.
const WATCH_PATIENCE: std::time::Duration = std::time::Duration::from_secs(60);

/// Shows each change of a mission an operator would see, until `count`
/// views: through a restart of the executive, or the mission passing to
/// another replica, it watches again (where the channel now points).
async fn watch(api: &mut Missions, mission: u64, count: Option<usize>, out: &output::Output) -> anyhow::Result<()> {
    let (mut seen, mut last) = (0, None);
    let mut heard = std::time::Instant::now();
    loop {
        let ended = match api.watch_mission(pb::WatchMissionRequest { mission_id: mission }).await {
            Ok(views) => {
                let mut views = views.into_inner();
                loop {
                    match views.message().await {
                        Ok(Some(view)) => {
                            heard = std::time::Instant::now();
                            // The executive pushes every change, heartbeats
                            // included; show only what changes what an operator sees.
                            let key = view.mission.as_ref().map(|m| {
                                let robots: Vec<_> = view.robots.iter().map(|r| (r.task_id, r.lost, r.state)).collect();
                                (m.state, m.frontier_cells, m.replans, m.robots, robots)
                            });
                            if key == last {
                                continue;
                            }
                            last = key;
                            out.view(&view);
                            seen += 1;
                            if count.is_some_and(|count| seen >= count) {
                                return Ok(());
                            }
                        }
                        Ok(None) => break tonic::Status::unavailable("the stream ended"),
                        Err(status) => break status,
                    }
                }
            }
            Err(status) => status,
        };
        if ended.code() != tonic::Code::Unavailable || heard.elapsed() > WATCH_PATIENCE {
            return Err(ended.into());
        }
        tokio::time::sleep(std::time::Duration::from_millis(250)).await;
    }
}

/// Receives a backup into `file`: written beside it first, checked against
/// the size and SHA-256 the executive sent, synced, then renamed into place.
async fn backup(api: &mut Missions, file: &std::path::Path) -> anyhow::Result<u64> {
    use sha2::Digest;
    use std::io::Write;
    if file.exists() {
        return Err(Usage(format!("{} exists; give a new file", file.display())).into());
    }
    let partial = file.with_extension("partial");
    let mut out = std::fs::File::create(&partial).with_context(|| format!("cannot create {}", partial.display()))?;
    let mut chunks = api.backup(pb::BackupRequest {}).await?.into_inner();
    let (mut written, mut hash, mut expected) = (0u64, sha2::Sha256::new(), None);
    while let Some(chunk) = chunks.message().await? {
        anyhow::ensure!(chunk.offset == written, "the backup arrived out of order");
        out.write_all(&chunk.data)?;
        hash.update(&chunk.data);
        written += chunk.data.len() as u64;
        if !chunk.sha256.is_empty() {
            expected = Some((chunk.total_bytes, chunk.sha256));
        }
    }
    let digest: String = hash.finalize().iter().map(|b| format!("{b:02x}")).collect();
    let Some((total, sha256)) = expected else {
        let _ = std::fs::remove_file(&partial);
        anyhow::bail!("the backup stream ended early ({written} bytes)");
    };
    if (total, sha256.as_str()) != (written, digest.as_str()) {
        let _ = std::fs::remove_file(&partial);
        anyhow::bail!("the backup is damaged: {written} bytes with SHA-256 {digest}, sent {total} with {sha256}");
    }
    out.sync_all()?;
    std::fs::rename(&partial, file).with_context(|| format!("cannot move the backup to {}", file.display()))?;
    Ok(written)
}

async fn run(cli: Cli) -> anyhow::Result<()> {
    let mut api = connect(&cli).await?;
    let out = output::Output { json: cli.json };
    let actor = cli.actor.clone();
    match cli.command {
        Command::Missions { command } => {
            mission_command(&mut api, out, &actor, command.unwrap_or(MissionCommand::List)).await?
        }
        Command::Policies => {
            let policies = api.list_policies(pb::ListPoliciesRequest {}).await?.into_inner().policies;
            out.policies(&policies);
        }
        Command::Robots { mission } => {
            let robots = robots(&mut api, mission).await?;
            out.robots(&robots);
        }
        Command::Tasks { mission, robot, kind, open, limit, history } => {
            let robot_id = match robot {
                Some(robot) => robot_id(&mut api, mission, &robot).await?,
                None => 0,
            };
            let request = pb::ListTasksRequest {
                mission_id: mission,
                robot_id,
                limit,
                kind: kind.as_deref().map_or(pb::TaskKind::Unspecified, task_kind) as i32,
                open_only: open,
            };
            let tasks = api.list_tasks(request).await?.into_inner().tasks;
            let names = robot_names(&mut api, mission).await?;
            out.tasks(&tasks, &names, history);
        }
        Command::Events { mission } => {
            let mut events = Vec::new();
            let mut after_id = 0;
            loop {
                let request = pb::ListEventsRequest { mission_id: mission, after_id, ..Default::default() };
                let page = api.list_events(request).await?.into_inner();
                events.extend(page.events);
                if page.next_after_id == 0 {
                    break;
                }
                anyhow::ensure!(page.next_after_id > after_id, "the executive's pages of events do not move on");
                after_id = page.next_after_id;
            }
            out.events(&events);
        }
        Command::Pin { mission, robot, point, reason } => {
            let robot_id = robot_id(&mut api, mission, &robot).await?;
            let request =
                pb::OverrideRobotRequest { robot_id, action: Some(Action::PinFrontier(point)), actor, reason };
            let robot = api.override_robot(request).await?.into_inner();
            out.robots(std::slice::from_ref(&robot));
        }
        Command::Override { mission, robot, action, reason } => {
            let robot_id = robot_id(&mut api, mission, &robot).await?;
            let action = match action {
                OverrideAction::Goto { point } => Action::Goto(point),
                OverrideAction::Region { area } => Action::ExploreRegion(area),
                OverrideAction::Pin { point } => Action::PinFrontier(point),
                OverrideAction::Hold => Action::Hold(Hold {}),
                OverrideAction::Home => Action::Home(Home {}),
                OverrideAction::Release => Action::Release(Release {}),
                OverrideAction::Cancel => Action::Cancel(Cancel {}),
            };
            let request = pb::OverrideRobotRequest { robot_id, action: Some(action), actor, reason };
            let robot = api.override_robot(request).await?.into_inner();
            out.robots(std::slice::from_ref(&robot));
        }
        Command::Forbid { mission, area, reason } => {
            let request = pb::ForbidRegionRequest { mission_id: mission, area: Some(area), actor, reason };
            let region = api.forbid_region(request).await?.into_inner();
            out.regions(std::slice::from_ref(&region));
        }
        Command::Rooms { mission, map, online: _, reason } => {
            let label_runs = match map {
                Some(map) => {
                    let frame = api
                        .get_mission(pb::GetMissionRequest { mission_id: mission })
                        .await?
                        .into_inner()
                        .frame
                        .context("the executive sent a mission without a frame")?;
                    exploration_proto::label_runs::encode(&rooms_of(&map, &frame)?)
                }
                None => Vec::new(),
            };
            let request = pb::SetGivenSegmentationRequest { mission_id: mission, label_runs, actor, reason };
            out.mission(&api.set_given_segmentation(request).await?.into_inner());
        }
        Command::Allow { mission, region, reason } => {
            let request = pb::AllowRegionRequest { mission_id: mission, region_id: region, actor, reason };
            let mission = api.allow_region(request).await?.into_inner();
            out.mission(&mission);
        }
        Command::Watch { mission, count } => watch(&mut api, mission, count, &out).await?,
        Command::Backup { file } => {
            let bytes = backup(&mut api, &file).await?;
            out.done(&format!("wrote {} ({bytes} bytes, checked)", file.display()));
        }
        Command::Map(MapCommand::Export { mission, png, px, segments }) => {
            let snapshot = api.get_map(pb::GetMapRequest { mission_id: mission }).await?.into_inner();
            let details = api.get_mission(pb::GetMissionRequest { mission_id: mission }).await?.into_inner();
            let labels = if segments {
                let request = pb::GetSegmentationRequest { mission_id: mission, include_labels: true };
                Some(api.get_segmentation(request).await?.into_inner().labels)
            } else {
                None
            };
            let picture = picture::render(&snapshot, &details.forbidden_regions, labels.as_deref(), px)?;
            picture.save(&png).with_context(|| format!("cannot write {}", png.display()))?;
            out.done(&format!("wrote {}", png.display()));
        }
    }
    Ok(())
}

async fn mission_command(
    api: &mut Missions,
    out: output::Output,
    actor: &str,
    command: MissionCommand,
) -> anyhow::Result<()> {
    let actor = actor.to_owned();
    match command {
        MissionCommand::List => {
            let missions = api.list_missions(pb::ListMissionsRequest {}).await?.into_inner().missions;
            out.missions(&missions);
        }
        MissionCommand::Show { mission } => {
            let mission = api.get_mission(pb::GetMissionRequest { mission_id: mission }).await?.into_inner();
            out.mission(&mission);
        }
        MissionCommand::Create {
            name,
            map,
            width,
            height,
            resolution,
            origin,
            policy,
            params,
            lease,
            stall,
            rendezvous,
        } => {
            let frame = match (map, width, height) {
                (Some(map), _, _) => frame_of_map(&map, resolution, origin)?,
                (None, Some(width), Some(height)) => pb::MapFrame {
                    resolution: resolution.unwrap_or(0.05),
                    origin: Some(origin.unwrap_or_default()),
                    width,
                    height,
                },
                _ => bail!(Usage("give --map, or --width and --height".into())),
            };
            let request = pb::CreateMissionRequest {
                name,
                frame: Some(frame),
                policy: Some(pb::PolicySpec { name: policy, params: params.into_iter().collect() }),
                lifecycle: Some(pb::LifecycleSettings {
                    lease_s: lease.unwrap_or(0.0),
                    stall_s: stall.unwrap_or(0.0),
                    rendezvous,
                }),
                ..Default::default()
            };
            let mission = api.create_mission(request).await?.into_inner();
            out.mission(&mission);
        }
        MissionCommand::Pause { mission, reason } => {
            let request = pb::MissionControlRequest { mission_id: mission, actor, reason };
            out.mission(&api.pause_mission(request).await?.into_inner());
        }
        MissionCommand::Resume { mission, reason } => {
            let request = pb::MissionControlRequest { mission_id: mission, actor, reason };
            out.mission(&api.resume_mission(request).await?.into_inner());
        }
        MissionCommand::Policy { mission, name, params, reason } => {
            let mission = match name {
                Some(name) => {
                    let policy = pb::PolicySpec { name, params: params.into_iter().collect() };
                    let request = pb::SetPolicyRequest { mission_id: mission, policy: Some(policy), actor, reason };
                    api.set_policy(request).await?.into_inner()
                }
                None if params.is_empty() => {
                    api.get_mission(pb::GetMissionRequest { mission_id: mission }).await?.into_inner()
                }
                None => bail!(Usage("--param needs the policy's name".into())),
            };
            out.policy(&mission);
        }
    }
    Ok(())
}

/// The frame of a map_server map: its image's size at its resolution, or
/// coarser cells covering the same area.
fn frame_of_map(
    map: &std::path::Path,
    resolution: Option<f64>,
    origin: Option<pb::Point>,
) -> anyhow::Result<pb::MapFrame> {
    let description = client_sim::world::MapDescription::load(map)?;
    let (pixels_x, pixels_y) = image::image_dimensions(&description.image)
        .with_context(|| format!("cannot read {}", description.image.display()))?;
    let resolution = resolution.unwrap_or(description.resolution);
    let cells = |pixels: u32| ((f64::from(pixels) * description.resolution / resolution).ceil() as u32).max(1);
    Ok(pb::MapFrame {
        resolution,
        origin: Some(origin.unwrap_or(pb::Point { x: description.origin.x, y: description.origin.y })),
        width: cells(pixels_x),
        height: cells(pixels_y),
    })
}

async fn robots(api: &mut Missions, mission: u64) -> anyhow::Result<Vec<pb::Robot>> {
    Ok(api.list_robots(pb::ListRobotsRequest { mission_id: mission }).await?.into_inner().robots)
}

async fn robot_names(api: &mut Missions, mission: u64) -> anyhow::Result<HashMap<u64, String>> {
    Ok(robots(api, mission).await?.into_iter().map(|r| (r.id, r.name)).collect())
}

/// A robot named by id or by name within `mission`.
async fn robot_id(api: &mut Missions, mission: u64, robot: &str) -> anyhow::Result<u64> {
    let robots = robots(api, mission).await?;
    if let Some(found) = robots.iter().find(|r| r.name == robot) {
        return Ok(found.id);
    }
    match robot.parse::<u64>() {
        Ok(id) if robots.iter().any(|r| r.id == id) => Ok(id),
        _ => {
            let known: Vec<&str> = robots.iter().map(|r| r.name.as_str()).collect();
            Err(anyhow!(tonic::Status::not_found(format!(
                "mission {mission} has no robot `{robot}` (its robots: {})",
                if known.is_empty() { "none".to_owned() } else { known.join(", ") }
            ))))
        }
    }
}

fn task_kind(name: &str) -> pb::TaskKind {
    match name {
        "explore" => pb::TaskKind::Explore,
        "goto" => pb::TaskKind::Goto,
        "hold" => pb::TaskKind::Hold,
        "home" => pb::TaskKind::Home,
        "pin" => pb::TaskKind::Pin,
        _ => pb::TaskKind::Unspecified,
    }
}

fn numbers<const N: usize>(text: &str, what: &str) -> Result<[f64; N], String> {
    let values: Vec<f64> = text
        .split(',')
        .map(|part| part.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|_| format!("`{text}` is not {what}"))?;
    values.try_into().map_err(|_| format!("`{text}` is not {what}"))
}

fn parse_point(text: &str) -> Result<pb::Point, String> {
    let [x, y] = numbers::<2>(text, "x,y in metres")?;
    Ok(pb::Point { x, y })
}

/// The rooms of the finished map at `yaml`, cell by cell over the mission's
/// frame; refused unless the map covers the same cells.
fn rooms_of(yaml: &std::path::Path, frame: &pb::MapFrame) -> anyhow::Result<Vec<u32>> {
    use client_sim::world::{StartChoice, World};
    let world = World::load(yaml, Some(frame.resolution), StartChoice::Auto, 0)
        .with_context(|| format!("loading {}", yaml.display()))?;
    let origin = frame.origin.unwrap_or_default();
    let (w, o) = (world.frame, world.frame.origin);
    let same_origin =
        (o.x - origin.x).abs() < frame.resolution / 2.0 && (o.y - origin.y).abs() < frame.resolution / 2.0;
    if w.width != frame.width || w.height != frame.height || !same_origin {
        bail!(
            "{} at {} m is {}×{} cells from ({:.2}, {:.2}); the mission's map is {}×{} from ({:.2}, {:.2})",
            yaml.display(),
            frame.resolution,
            w.width,
            w.height,
            o.x,
            o.y,
            frame.width,
            frame.height,
            origin.x,
            origin.y
        );
    }
    Ok(world.given_rooms())
}

fn parse_rect(text: &str) -> Result<pb::Rect, String> {
    let [x0, y0, x1, y1] = numbers::<4>(text, "x0,y0,x1,y1 in metres")?;
    Ok(pb::Rect { min_x: x0.min(x1), min_y: y0.min(y1), max_x: x0.max(x1), max_y: y0.max(y1) })
}

fn parse_param(text: &str) -> Result<(String, f64), String> {
    let (name, value) = text.split_once('=').ok_or_else(|| format!("`{text}` is not name=value"))?;
    let value = value.trim().parse().map_err(|_| format!("`{value}` in `{text}` is not a number"))?;
    Ok((name.trim().to_owned(), value))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn points_and_rectangles_parse_and_rectangles_are_normalized() {
        let p = parse_point("1.5,-2").unwrap();
        assert_eq!((p.x, p.y), (1.5, -2.0));
        let r = parse_rect("4,3,1,-1").unwrap();
        assert_eq!((r.min_x, r.min_y, r.max_x, r.max_y), (1.0, -1.0, 4.0, 3.0));
        assert!(parse_point("1,2,3").is_err());
        assert!(parse_rect("a,b,c,d").is_err());
        assert_eq!(parse_param("beta=2").unwrap(), ("beta".into(), 2.0));
        assert!(parse_param("beta").is_err());
    }

    #[test]
    fn statuses_map_to_documented_exit_codes() {
        let code = |status: tonic::Status| exit_code(&anyhow::Error::new(status));
        assert_eq!(code(tonic::Status::not_found("x")), 3);
        assert_eq!(code(tonic::Status::failed_precondition("x")), 4);
        assert_eq!(code(tonic::Status::permission_denied("x")), 5);
        assert_eq!(code(tonic::Status::unauthenticated("x")), 5);
        assert_eq!(code(tonic::Status::internal("x")), 1);
        assert_eq!(exit_code(&anyhow::Error::new(Usage("x".into()))), 2);
    }

    #[test]
    fn the_command_line_is_consistent() {
        use clap::CommandFactory;
        Cli::command().debug_assert();
    }
}
