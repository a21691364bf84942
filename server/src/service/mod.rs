//! The gRPC handlers: thin adapters that check the caller's token
//! ([`crate::auth`]), convert a request into domain types ([`convert`]),
//! call the [`Executive`], and convert the answer back. Errors become
//! statuses in one place, `impl From<Error> for Status`.

use std::pin::Pin;
use std::sync::Arc;

use futures::{Stream, StreamExt};
use tokio_stream::wrappers::WatchStream;
use tokio_util::sync::CancellationToken;
use tonic::{Request, Response, Status};

use exploration::grid::UNKNOWN;
use exploration_proto::v1 as pb;
use exploration_proto::v1::fleet_server::{Fleet, FleetServer};
use exploration_proto::v1::missions_server::{Missions, MissionsServer};
use tonic::service::interceptor::InterceptedService;

use crate::auth::{AuthLayer, Authenticator, Caller};
use crate::domain::{Heartbeat, MapUpdate, MissionSpec, RobotSpec};
use crate::error::Error;
use crate::executive::{Executive, RobotSummary};
use crate::store::TaskFilter;

/// Most mission views a watcher gets per second.
const WATCH_MIN_INTERVAL: std::time::Duration = std::time::Duration::from_millis(250);
/// How many items a listing returns: `default` when the caller gives no
/// limit (0), and never more than `max`.
struct PageLimit {
    default: u32,
    max: u32,
}

impl PageLimit {
    fn of(&self, requested: u32) -> u32 {
        if requested == 0 { self.default } else { requested.min(self.max) }
    }
}

const TASKS_PAGE: PageLimit = PageLimit { default: 1000, max: 100_000 };
/// Events are at most ~1 KB each: 5 000 stay under gRPC's 4 MB client limit.
const EVENTS_PAGE: PageLimit = PageLimit { default: 1000, max: 5000 };

pub mod convert;

/// Both services of `exploration.v1` over one executive.
#[derive(Debug, Clone)]
pub struct ExplorationService {
    executive: Arc<Executive>,
    shutdown: CancellationToken,
}

/// The `Missions` server, every call authenticated first.
pub type MissionsService = InterceptedService<MissionsServer<ExplorationService>, AuthLayer>;
/// The `Fleet` server, every call authenticated first.
pub type FleetService = InterceptedService<FleetServer<ExplorationService>, AuthLayer>;

impl ExplorationService {
    /// Serves `executive`; streams end when `shutdown` is cancelled.
    pub fn new(executive: Arc<Executive>, shutdown: CancellationToken) -> Self {
        Self { executive, shutdown }
    }

    /// Both servers behind `auth`: the only way they are served, so that no
    /// handler runs for a caller that was not authenticated.
    pub fn into_servers(self, auth: Authenticator, max_message_bytes: usize) -> (MissionsService, FleetService) {
        let executive = Arc::clone(&self.executive);
        let layer = AuthLayer::new(auth, move |robot| executive.robot_token_hash(robot));
        let missions = MissionsServer::new(self.clone()).max_decoding_message_size(max_message_bytes);
        let fleet = FleetServer::new(self).max_decoding_message_size(max_message_bytes);
        (InterceptedService::new(missions, layer.clone()), InterceptedService::new(fleet, layer))
    }

    /// Who sent the request, as the authentication layer found.
    fn caller<T>(&self, request: &Request<T>) -> Result<Caller, Error> {
        request
            .extensions()
            .get::<Caller>()
            .cloned()
            .ok_or_else(|| Error::Internal("a request reached a handler without passing the auth layer".to_owned()))
    }

    /// The request must come from an operator; returns who.
    fn operator<T>(&self, request: &Request<T>, what: &str) -> Result<Caller, Error> {
        let caller = self.caller(request)?;
        caller.require_operator(what)?;
        Ok(caller)
    }

    /// The request must come from `robot` itself or an operator.
    fn as_robot<T>(&self, request: &Request<T>, robot: u64) -> Result<(), Error> {
        self.caller(request)?.require_robot(robot)
    }

    async fn mission_view(&self, mission_id: u64) -> Result<pb::MissionView, Error> {
        let mission = self.executive.mission(mission_id).await?;
        let robots = self.executive.robots(mission_id).await?;
        Ok(pb::MissionView { mission: Some((&mission).into()), robots: robots.iter().map(Into::into).collect() })
    }

    /// PauseMission (`pause`) and ResumeMission, once the caller is checked.
    async fn set_paused(
        &self,
        caller: &Caller,
        r: pb::MissionControlRequest,
        pause: bool,
    ) -> Result<Response<pb::Mission>, Status> {
        let id = required_id(r.mission_id, "mission_id")?;
        let note = convert::operator_note(caller, r.actor, r.reason)?;
        let mission = self.executive.pause_mission(id, pause, note).await?;
        Ok(Response::new((&mission).into()))
    }
}

fn required_id(id: u64, field: &str) -> Result<u64, Error> {
    if id == 0 { Err(Error::InvalidArgument(format!("{field} is required (identities start at 1)"))) } else { Ok(id) }
}

#[tonic::async_trait]
impl Missions for ExplorationService {
    #[tracing::instrument(skip_all, fields(name = %request.get_ref().name))]
    async fn create_mission(
        &self,
        request: Request<pb::CreateMissionRequest>,
    ) -> Result<Response<pb::Mission>, Status> {
        self.operator(&request, "creating a mission")?;
        let spec = MissionSpec::try_from(request.into_inner())?;
        let mission = self.executive.create_mission(spec).await?;
        Ok(Response::new((&mission).into()))
    }

    #[tracing::instrument(skip_all, fields(mission = request.get_ref().mission_id))]
    async fn get_mission(&self, request: Request<pb::GetMissionRequest>) -> Result<Response<pb::Mission>, Status> {
        self.caller(&request)?;
        let id = required_id(request.into_inner().mission_id, "mission_id")?;
        let mission = self.executive.mission(id).await?;
        Ok(Response::new((&mission).into()))
    }

    #[tracing::instrument(skip_all)]
    async fn list_missions(
        &self,
        request: Request<pb::ListMissionsRequest>,
    ) -> Result<Response<pb::ListMissionsResponse>, Status> {
        self.caller(&request)?;
        let request = request.into_inner();
        let mut page = convert::MissionPage::new(request.limit);
        let next = self.executive.missions_after(request.after_id, |mission| page.take(&mission)).await?;
        Ok(Response::new(page.finish(next)))
    }

    #[tracing::instrument(skip_all)]
    async fn list_policies(
        &self,
        request: Request<pb::ListPoliciesRequest>,
    ) -> Result<Response<pb::ListPoliciesResponse>, Status> {
        self.caller(&request)?;
        Ok(Response::new(convert::policies()))
    }

    #[tracing::instrument(skip_all, fields(mission = request.get_ref().mission_id))]
    async fn list_robots(
        &self,
        request: Request<pb::ListRobotsRequest>,
    ) -> Result<Response<pb::ListRobotsResponse>, Status> {
        self.caller(&request)?;
        let id = required_id(request.into_inner().mission_id, "mission_id")?;
        let robots = self.executive.robots(id).await?;
        Ok(Response::new(pb::ListRobotsResponse { robots: robots.iter().map(Into::into).collect() }))
    }

    #[tracing::instrument(skip_all, fields(mission = request.get_ref().mission_id, robot = request.get_ref().robot_id))]
    async fn list_tasks(
        &self,
        request: Request<pb::ListTasksRequest>,
    ) -> Result<Response<pb::ListTasksResponse>, Status> {
        self.caller(&request)?;
        let r = request.into_inner();
        let filter = TaskFilter {
            mission_id: required_id(r.mission_id, "mission_id")?,
            robot_id: (r.robot_id != 0).then_some(r.robot_id),
            kind: convert::task_kind_filter(r.kind)?,
            open_only: r.open_only,
            limit: TASKS_PAGE.of(r.limit),
        };
        let tasks = self.executive.tasks(filter).await?;
        Ok(Response::new(pb::ListTasksResponse { tasks: tasks.iter().map(Into::into).collect() }))
    }

    #[tracing::instrument(skip_all, fields(mission = request.get_ref().mission_id))]
    async fn get_map(&self, request: Request<pb::GetMapRequest>) -> Result<Response<pb::MapSnapshot>, Status> {
        self.caller(&request)?;
        let id = required_id(request.into_inner().mission_id, "mission_id")?;
        let map = self.executive.map(id).await?;
        let frame = *map.grid.frame();
        Ok(Response::new(pb::MapSnapshot {
            mission_id: id,
            frame: Some(convert::frame_to_proto(&frame)),
            cells: map.grid.cells().iter().map(|&v| if v == UNKNOWN { 255 } else { v }).collect(),
            frontier: map.frontier.iter().map(|p| pb::Point { x: p.x, y: p.y }).collect(),
            robots: map.robots.iter().map(|r: &RobotSummary| r.into()).collect(),
            frontier_mask: map.frontier_mask,
        }))
    }

    #[tracing::instrument(skip_all, fields(mission = request.get_ref().mission_id))]
    async fn set_policy(&self, request: Request<pb::SetPolicyRequest>) -> Result<Response<pb::Mission>, Status> {
        let caller = self.operator(&request, "changing a mission's policy")?;
        let r = request.into_inner();
        let id = required_id(r.mission_id, "mission_id")?;
        let policy =
            convert::policy(Some(r.policy.ok_or_else(|| Error::InvalidArgument("policy is required".into()))?))?;
        let note = convert::operator_note(&caller, r.actor, r.reason)?;
        let mission = self.executive.set_policy(id, policy, &note.actor, &note.reason).await?;
        Ok(Response::new((&mission).into()))
    }

    #[tracing::instrument(skip_all, fields(mission = request.get_ref().mission_id))]
    async fn list_events(
        &self,
        request: Request<pb::ListEventsRequest>,
    ) -> Result<Response<pb::ListEventsResponse>, Status> {
        self.caller(&request)?;
        let r = request.into_inner();
        let id = required_id(r.mission_id, "mission_id")?;
        let limit = EVENTS_PAGE.of(r.limit);
        let events = self.executive.events(id, r.after_id, limit).await?;
        // A short page is the last; a full one may have more behind it.
        let next_after_id = match events.last() {
            Some(last) if events.len() == limit as usize => last.id,
            _ => 0,
        };
        Ok(Response::new(pb::ListEventsResponse { events: events.iter().map(convert::event).collect(), next_after_id }))
    }

    #[tracing::instrument(skip_all, fields(mission = request.get_ref().mission_id))]
    async fn get_segmentation(
        &self,
        request: Request<pb::GetSegmentationRequest>,
    ) -> Result<Response<pb::Segmentation>, Status> {
        self.caller(&request)?;
        let r = request.into_inner();
        let id = required_id(r.mission_id, "mission_id")?;
        let frame = self.executive.mission(id).await?.record.spec.frame;
        let stored = self.executive.segmentation(id).await?;
        let form = convert::LabelForm::asked_by(&r);
        Ok(Response::new(convert::segmentation(id, &frame, stored.as_ref(), form)?))
    }

    type WatchMissionStream = MissionViewStream;

    #[tracing::instrument(skip_all, fields(mission = request.get_ref().mission_id))]
    async fn watch_mission(
        &self,
        request: Request<pb::WatchMissionRequest>,
    ) -> Result<Response<Self::WatchMissionStream>, Status> {
        self.caller(&request)?;
        let id = required_id(request.into_inner().mission_id, "mission_id")?;
        let changes = self.executive.subscribe(id).await?;
        let service = self.clone();
        let shutdown = self.shutdown.clone().cancelled_owned();
        // The current view at once, then one per change, at most every WATCH_MIN_INTERVAL.
        let stream = futures::stream::unfold((changes, true), move |(mut changes, first)| {
            let service = service.clone();
            async move {
                if !first {
                    tokio::time::sleep(WATCH_MIN_INTERVAL).await;
                    changes.changed().await.ok()?;
                }
                changes.borrow_and_update();
                let view = service.mission_view(id).await.map_err(Status::from);
                Some((view, (changes, false)))
            }
        })
        .take_until(shutdown);
        Ok(Response::new(Box::pin(stream)))
    }

    #[tracing::instrument(skip_all, fields(robot = request.get_ref().robot_id))]
    async fn override_robot(&self, request: Request<pb::OverrideRobotRequest>) -> Result<Response<pb::Robot>, Status> {
        let caller = self.operator(&request, "overriding a robot")?;
        let r = request.into_inner();
        let robot = required_id(r.robot_id, "robot_id")?;
        let action = convert::OverrideInput::try_from(r.action)?.0;
        let note = convert::operator_note(&caller, r.actor, r.reason)?;
        let summary = self.executive.override_robot(robot, action, note).await?;
        Ok(Response::new((&summary).into()))
    }

    #[tracing::instrument(skip_all, fields(mission = request.get_ref().mission_id))]
    async fn pause_mission(
        &self,
        request: Request<pb::MissionControlRequest>,
    ) -> Result<Response<pb::Mission>, Status> {
        let caller = self.operator(&request, "pausing a mission")?;
        self.set_paused(&caller, request.into_inner(), true).await
    }

    #[tracing::instrument(skip_all, fields(mission = request.get_ref().mission_id))]
    async fn delete_mission(
        &self,
        request: Request<pb::MissionControlRequest>,
    ) -> Result<Response<pb::DeleteMissionResponse>, Status> {
        let caller = self.operator(&request, "deleting a mission")?;
        let r = request.into_inner();
        let id = required_id(r.mission_id, "mission_id")?;
        let note = convert::operator_note(&caller, r.actor, r.reason)?;
        self.executive.delete_mission(id, note).await?;
        Ok(Response::new(pb::DeleteMissionResponse {}))
    }

    #[tracing::instrument(skip_all, fields(mission = request.get_ref().mission_id))]
    async fn resume_mission(
        &self,
        request: Request<pb::MissionControlRequest>,
    ) -> Result<Response<pb::Mission>, Status> {
        let caller = self.operator(&request, "resuming a mission")?;
        self.set_paused(&caller, request.into_inner(), false).await
    }

    #[tracing::instrument(skip_all, fields(mission = request.get_ref().mission_id))]
    async fn forbid_region(&self, request: Request<pb::ForbidRegionRequest>) -> Result<Response<pb::Region>, Status> {
        let caller = self.operator(&request, "forbidding a region")?;
        let r = request.into_inner();
        let id = required_id(r.mission_id, "mission_id")?;
        let (min, max) = convert::area(r.area, "area")?;
        let note = convert::operator_note(&caller, r.actor, r.reason)?;
        let region = self.executive.forbid_region(id, min, max, note).await?;
        Ok(Response::new(convert::region(&region)))
    }

    #[tracing::instrument(skip_all, fields(mission = request.get_ref().mission_id))]
    async fn set_given_segmentation(
        &self,
        request: Request<pb::SetGivenSegmentationRequest>,
    ) -> Result<Response<pb::Mission>, Status> {
        let caller = self.operator(&request, "giving a mission its rooms")?;
        let r = request.into_inner();
        let id = required_id(r.mission_id, "mission_id")?;
        let note = convert::operator_note(&caller, r.actor, r.reason)?;
        let mission = self.executive.set_given_segmentation(id, &r.label_runs, note).await?;
        Ok(Response::new(pb::Mission::from(&mission)))
    }

    #[tracing::instrument(skip_all, fields(mission = request.get_ref().mission_id, region = request.get_ref().region_id))]
    async fn allow_region(&self, request: Request<pb::AllowRegionRequest>) -> Result<Response<pb::Mission>, Status> {
        let caller = self.operator(&request, "allowing a region")?;
        let r = request.into_inner();
        let id = required_id(r.mission_id, "mission_id")?;
        let region = required_id(r.region_id, "region_id")?;
        let note = convert::operator_note(&caller, r.actor, r.reason)?;
        let mission = self.executive.allow_region(id, region, note).await?;
        Ok(Response::new((&mission).into()))
    }

    type BackupStream = BackupStream;

    #[tracing::instrument(skip_all)]
    async fn backup(&self, request: Request<pb::BackupRequest>) -> Result<Response<Self::BackupStream>, Status> {
        let caller = self.operator(&request, "taking a backup")?;
        let copy = self.executive.backup().await?;
        let file = tokio::fs::File::open(copy.path())
            .await
            .map_err(|e| Error::Internal(format!("opening the backup copy: {e}")))?;
        let total = file.metadata().await.map_err(|e| Error::Internal(format!("sizing the backup copy: {e}")))?.len();
        tracing::info!(actor = %caller.actor("operator"), bytes = total, "backup taken");
        Ok(Response::new(backup_chunks(copy, file, total)))
    }
}

type AssignmentStream = Pin<Box<dyn Stream<Item = Result<pb::Assignment, Status>> + Send>>;
type BackupStream = Pin<Box<dyn Stream<Item = Result<pb::BackupChunk, Status>> + Send>>;

/// Bytes per backup chunk.
const BACKUP_CHUNK: usize = 1 << 20;

/// Streams a backup copy in chunks, the last one carrying the file's SHA-256;
/// the copy is removed once the stream ends or is dropped.
fn backup_chunks(copy: crate::executive::BackupFile, file: tokio::fs::File, total: u64) -> BackupStream {
    use sha2::Digest;
    use tokio::io::AsyncReadExt;
    struct State {
        _copy: crate::executive::BackupFile,
        file: tokio::fs::File,
        offset: u64,
        hash: sha2::Sha256,
        done: bool,
    }
    let state = State { _copy: copy, file, offset: 0, hash: sha2::Sha256::new(), done: false };
    Box::pin(futures::stream::unfold(state, move |mut state| async move {
        if state.done {
            return None;
        }
        let mut data = vec![0; BACKUP_CHUNK];
        let mut filled = 0;
        while filled < data.len() {
            match state.file.read(&mut data[filled..]).await {
                Ok(0) => break,
                Ok(n) => filled += n,
                Err(e) => {
                    state.done = true;
                    let status = Status::from(Error::Internal(format!("reading the backup copy: {e}")));
                    return Some((Err(status), state));
                }
            }
        }
        data.truncate(filled);
        state.hash.update(&data);
        let offset = state.offset;
        state.offset += filled as u64;
        state.done = state.offset >= total || filled == 0;
        let sha256 = if state.done {
            state.hash.clone().finalize().iter().map(|b| format!("{b:02x}")).collect()
        } else {
            String::new()
        };
        Some((Ok(pb::BackupChunk { offset, data, total_bytes: total, sha256 }), state))
    }))
}
type MissionViewStream = Pin<Box<dyn Stream<Item = Result<pb::MissionView, Status>> + Send>>;

#[tonic::async_trait]
impl Fleet for ExplorationService {
    #[tracing::instrument(skip_all, fields(mission = request.get_ref().mission_id, name = %request.get_ref().name))]
    async fn register_robot(
        &self,
        request: Request<pb::RegisterRobotRequest>,
    ) -> Result<Response<pb::RegisterRobotResponse>, Status> {
        let caller = self.caller(&request)?;
        let r = request.into_inner();
        let mission_id = required_id(r.mission_id, "mission_id")?;
        if let Caller::Robot(id) = caller {
            // A robot may re-register itself (after a restart), nothing else.
            if self.executive.robot_named(mission_id, r.name.trim()).await? != Some(id) {
                return Err(Error::PermissionDenied(format!(
                    "the token of robot {id} may only re-register robot {id}; registering new robots needs the \
                     operator token"
                ))
                .into());
            }
        }
        let spec = RobotSpec::try_from(r)?;
        let (record, token, resumed) = self.executive.register_robot(mission_id, spec).await?;
        let summary = RobotSummary { record, target: None, task_kind: None, blacklisted: 0 };
        Ok(Response::new(pb::RegisterRobotResponse { robot: Some((&summary).into()), resumed, token }))
    }

    #[tracing::instrument(skip_all, fields(robot = request.get_ref().robot_id, state = request.get_ref().state))]
    async fn heartbeat(
        &self,
        request: Request<pb::HeartbeatRequest>,
    ) -> Result<Response<pb::HeartbeatResponse>, Status> {
        let robot = required_id(request.get_ref().robot_id, "robot_id")?;
        self.as_robot(&request, robot)?;
        let heartbeat = Heartbeat::try_from(request.into_inner())?;
        let assignment = self.executive.heartbeat(robot, heartbeat).await?;
        Ok(Response::new(pb::HeartbeatResponse { assignment: Some((&assignment).into()) }))
    }

    #[tracing::instrument(skip_all, fields(robot = request.get_ref().robot_id, seq = request.get_ref().seq))]
    async fn update_map(
        &self,
        request: Request<pb::UpdateMapRequest>,
    ) -> Result<Response<pb::UpdateMapResponse>, Status> {
        let robot = required_id(request.get_ref().robot_id, "robot_id")?;
        self.as_robot(&request, robot)?;
        let update = MapUpdate::try_from(request.into_inner())?;
        let outcome = self.executive.update_map(robot, update).await?;
        Ok(Response::new(pb::UpdateMapResponse {
            applied_seq: outcome.applied_seq,
            assignment: Some((&outcome.assignment).into()),
            frontier_cells: outcome.frontier_cells,
            mission_state: pb::Assignment::from(&outcome.assignment).mission_state,
        }))
    }

    #[tracing::instrument(skip_all, fields(robot = request.get_ref().robot_id, bids = request.get_ref().bids.len()))]
    async fn submit_bids(
        &self,
        request: Request<pb::SubmitBidsRequest>,
    ) -> Result<Response<pb::SubmitBidsResponse>, Status> {
        let robot = required_id(request.get_ref().robot_id, "robot_id")?;
        self.as_robot(&request, robot)?;
        let bids = convert::bids(request.into_inner().bids)?;
        let (accepted, assignment) = self.executive.submit_bids(robot, bids).await?;
        Ok(Response::new(pb::SubmitBidsResponse { accepted: accepted as u32, assignment: Some((&assignment).into()) }))
    }

    #[tracing::instrument(skip_all, fields(robot = request.get_ref().robot_id))]
    async fn get_assignment(
        &self,
        request: Request<pb::GetAssignmentRequest>,
    ) -> Result<Response<pb::Assignment>, Status> {
        let robot = required_id(request.get_ref().robot_id, "robot_id")?;
        self.as_robot(&request, robot)?;
        let assignment = self.executive.assignment(robot).await?;
        Ok(Response::new((&assignment).into()))
    }

    type WatchAssignmentStream = AssignmentStream;

    #[tracing::instrument(skip_all, fields(robot = request.get_ref().robot_id))]
    async fn watch_assignment(
        &self,
        request: Request<pb::WatchAssignmentRequest>,
    ) -> Result<Response<Self::WatchAssignmentStream>, Status> {
        let robot = required_id(request.get_ref().robot_id, "robot_id")?;
        self.as_robot(&request, robot)?;
        let receiver = self.executive.watch(robot).await?;
        let shutdown = self.shutdown.clone().cancelled_owned();
        // The stream yields the current assignment, then each change, and ends
        // at shutdown so that a graceful stop is not held up by watchers.
        let stream = WatchStream::new(receiver).map(|a| Ok(pb::Assignment::from(&a))).take_until(shutdown);
        Ok(Response::new(Box::pin(stream)))
    }
}
