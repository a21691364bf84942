//! `coordctl`: the operator's command line for the exploration executive.
//!
//! It only speaks the public gRPC API, so everything it does a fleet manager
//! or a script can do too. Exit codes: 0 done, 1 other failure, 2 bad usage,
//! 3 not found, 4 refused in the current state (precondition, invalid
//! argument, limits), 5 not authenticated or not allowed; 0 too when the
//! reader of its output leaves early (`| head`).

mod cli;
mod output;
mod picture;

use cli::{Cli, Command, MapCommand, MissionCommand, OverrideAction};

use std::collections::HashMap;
use std::process::ExitCode;

use anyhow::{Context, anyhow, bail};
use clap::Parser;
use client_sim::console::{self, StdoutError};
use client_sim::errln;
use exploration_proto::replicas::Replicas;
use tonic::Code;
use tonic::service::interceptor::InterceptedService;

use exploration_proto::Bearer;
use exploration_proto::v1 as pb;
use exploration_proto::v1::missions_client::MissionsClient;
use exploration_proto::v1::override_robot_request::{Action, Cancel, Hold, Home, Release};

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
        // `coordctl tasks 1 | head`: the reader had what it wanted.
        Err(e) if StdoutError::is_reader_gone(&e) => ExitCode::SUCCESS,
        Err(e) => {
            match e.downcast_ref::<tonic::Status>() {
                Some(status) => errln!("coordctl: {}", exploration_proto::client::status_line(status)),
                None => errln!("coordctl: {}", console::report(e.as_ref())),
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
            errln!("warning: {warning}");
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
    let channel = Replicas::from_list(&cli.server, tls.as_ref()).map_err(|e| Usage(format!("--server: {e}")))?;
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
    if count == Some(0) {
        // It printed one view and stopped: neither none nor every one.
        return Err(Usage("--count must be at least 1 (leave it out to watch until stopped)".into()).into());
    }
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
                            out.view(&view)?;
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
            out.policies(&policies)?;
        }
        Command::Robots { mission } => {
            let robots = robots(&mut api, mission).await?;
            out.robots(&robots)?;
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
            out.tasks(&tasks, &names, history)?;
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
            out.events(&events)?;
        }
        Command::Pin { mission, robot, point, reason } => {
            let robot_id = robot_id(&mut api, mission, &robot).await?;
            let request =
                pb::OverrideRobotRequest { robot_id, action: Some(Action::PinFrontier(point)), actor, reason };
            let robot = api.override_robot(request).await?.into_inner();
            out.robots(std::slice::from_ref(&robot))?;
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
            out.robots(std::slice::from_ref(&robot))?;
        }
        Command::Forbid { mission, area, reason } => {
            let request = pb::ForbidRegionRequest { mission_id: mission, area: Some(area), actor, reason };
            let region = api.forbid_region(request).await?.into_inner();
            out.regions(std::slice::from_ref(&region))?;
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
            out.mission(&api.set_given_segmentation(request).await?.into_inner())?;
        }
        Command::Allow { mission, region, reason } => {
            let request = pb::AllowRegionRequest { mission_id: mission, region_id: region, actor, reason };
            let mission = api.allow_region(request).await?.into_inner();
            out.mission(&mission)?;
        }
        Command::Watch { mission, count } => watch(&mut api, mission, count, &out).await?,
        Command::Backup { file } => {
            let bytes = backup(&mut api, &file).await?;
            out.done(&format!("wrote {} ({bytes} bytes, checked)", file.display()))?;
        }
        Command::Map(MapCommand::Export { mission, png, px, segments }) => {
            let snapshot = api.get_map(pb::GetMapRequest { mission_id: mission }).await?.into_inner();
            let details = api.get_mission(pb::GetMissionRequest { mission_id: mission }).await?.into_inner();
            let labels = if segments { segment_labels(&mut api, mission, snapshot.cells.len()).await? } else { None };
            let picture = picture::render(&snapshot, &details.forbidden_regions, labels.as_deref(), px)?;
            picture.save(&png).with_context(|| format!("cannot write {}", png.display()))?;
            out.done(&format!("wrote {}", png.display()))?;
        }
    }
    Ok(())
}

/// The segment label of each of a mission's `cells`, asked for as runs, the
/// few kilobytes a building takes; per cell if its runs are too many to
/// send. `None` when the mission has no segmentation.
async fn segment_labels(api: &mut Missions, mission: u64, cells: usize) -> anyhow::Result<Option<Vec<u32>>> {
    let ask = |label_runs| pb::GetSegmentationRequest { mission_id: mission, include_labels: true, label_runs };
    let answer = match api.get_segmentation(ask(true)).await {
        Err(status) if status.code() == tonic::Code::ResourceExhausted => api.get_segmentation(ask(false)).await,
        answer => answer,
    }?;
    answer.into_inner().labels_per_cell(cells).map_err(|e| anyhow::anyhow!("the executive's segmentation: {e}"))
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
            let mut missions = Vec::new();
            let mut after_id = 0;
            loop {
                let page = api.list_missions(pb::ListMissionsRequest { after_id, limit: 0 }).await?.into_inner();
                missions.extend(page.missions);
                if page.next_after_id == 0 {
                    break;
                }
                anyhow::ensure!(page.next_after_id > after_id, "the executive's pages of missions do not move on");
                after_id = page.next_after_id;
            }
            out.missions(&missions)?;
        }
        MissionCommand::Show { mission } => {
            let mission = api.get_mission(pb::GetMissionRequest { mission_id: mission }).await?.into_inner();
            out.mission(&mission)?;
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
            out.mission(&mission)?;
        }
        MissionCommand::Pause { mission, reason } => {
            let request = pb::MissionControlRequest { mission_id: mission, actor, reason };
            out.mission(&api.pause_mission(request).await?.into_inner())?;
        }
        MissionCommand::Resume { mission, reason } => {
            let request = pb::MissionControlRequest { mission_id: mission, actor, reason };
            out.mission(&api.resume_mission(request).await?.into_inner())?;
        }
        MissionCommand::Delete { mission, reason } => {
            let request = pb::MissionControlRequest { mission_id: mission, actor, reason };
            api.delete_mission(request).await?;
            out.done(&format!("mission {mission} deleted"))?;
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
            out.policy(&mission)?;
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

#[cfg(test)]
mod tests {
    use super::*;

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
}
