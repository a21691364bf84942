"""A thin layer over the executive's gRPC API.

:class:`Executive` is one connection: missions for operators, and robot
registration. :class:`Robot` is one registered robot speaking with its own
token: map patches from numpy grids with sequence numbers handled,
heartbeats, bids, and an iterator over its assignments that reconnects when
the executive restarts.

Either may be given several addresses: executive replicas sharing one
database. Calls follow each mission to the replica that holds it, and move
on to the next replica when one cannot be reached (see :mod:`.replicas`).

The raw stubs stay at hand (``executive.missions``, ``executive.fleet``) with
the messages in :mod:`exploration_executive.pb` for anything this layer does
not wrap.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import grpc
import numpy as np

from ._proto.exploration.v1 import exploration_pb2 as pb
from ._proto.exploration.v1 import exploration_pb2_grpc as rpc
from .maps import MapServerMap
from .patches import patch_from_grid
from .replicas import Replicas, addresses_of

#: Answers after which a stream or call is worth trying again: the executive
#: is restarting, draining, or shedding load.
RETRYABLE = {grpc.StatusCode.UNAVAILABLE, grpc.StatusCode.RESOURCE_EXHAUSTED}

#: The trailer in which an executive shedding load says how long to wait.
RETRY_PUSHBACK = "grpc-retry-pushback-ms"


def retry_pushback_s(error: grpc.RpcError) -> float | None:
    """How long the executive asked to wait before calling again, seconds
    (at most 10), if it did."""
    trailers = error.trailing_metadata() if hasattr(error, "trailing_metadata") else None
    for key, value in trailers or ():
        if key == RETRY_PUSHBACK:
            try:
                ms = int(value)
            except ValueError:
                return None
            return min(ms, 10_000) / 1000 if ms >= 0 else None
    return None


@dataclass(frozen=True)
class Bid:
    """A robot's estimate for one candidate target (Simmons et al. 2000)."""

    x: float
    y: float
    path_cost: float
    information_gain: float
    gain_region: tuple[float, float, float, float] | None = None


class Executive:
    """A connection to one executive (or its replicas), for operators and
    for registering robots.

    ``address`` is ``host:port``, ``http(s)://host:port``, or several of
    them (a sequence, or comma-separated) for executive replicas sharing one
    database. ``token`` is sent as ``authorization: Bearer`` on every call;
    the executive runs open (no token) only on loopback and in tests. Use
    ``https://`` addresses (with ``root_certificates``, the CA's PEM, for a
    private CA) whenever the token crosses a network.

    A call answered UNAVAILABLE is tried again, for up to ``failover_s``
    seconds, at the replica that answer named as the mission's holder or
    else at the next address: a replica that died is replaced by another
    once its lease on the mission has run out, and a lone executive that
    restarts answers again. ``create_mission`` is not tried again after an
    UNAVAILABLE that named no holder (it may have been carried out); the
    next call goes to the next address. A call refused RESOURCE_EXHAUSTED
    with a retry hint (an executive shedding load) was not carried out: it
    is tried again once the hint has passed, within the same
    ``failover_s``, so that an overloaded executive gets fewer calls.
    """

    def __init__(
        self,
        address: str | Sequence[str],
        token: str | None = None,
        *,
        root_certificates: bytes | None = None,
        timeout_s: float = 10.0,
        failover_s: float = 30.0,
        _current: str | None = None,
    ) -> None:
        # Checked here: gRPC would refuse it on every call with a bare
        # INTERNAL "Invalid metadata", after logging from C++.
        if token is not None and not all("!" <= c <= "~" for c in token):
            raise ValueError("token: a token is printable ASCII without spaces, as an HTTP header carries it")
        self._addresses = addresses_of(address)
        self._replicas = Replicas(self._addresses, root_certificates, token_sent=bool(token), current=_current)
        self._root_certificates = root_certificates
        self.token = token
        self.timeout_s = timeout_s
        self.failover_s = failover_s
        self.closed = False

    @property
    def missions(self) -> rpc.MissionsStub:
        """The raw Missions stub of the replica the calls go to now."""
        return self._replicas.missions

    @property
    def fleet(self) -> rpc.FleetStub:
        """The raw Fleet stub of the replica the calls go to now."""
        return self._replicas.fleet

    @property
    def address(self) -> str:
        """The replica the calls go to now."""
        return self._replicas.current

    @property
    def metadata(self) -> tuple[tuple[str, str], ...]:
        return (("authorization", f"Bearer {self.token}"),) if self.token else ()

    def close(self) -> None:
        self.closed = True
        self._replicas.close()

    def __enter__(self) -> "Executive":
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    def _call(self, service: str, method: str, request, *, idempotent: bool = True):  # noqa: ANN001, ANN202
        """``service.method(request)`` at the replica the calls go to now,
        tried again elsewhere as the class says."""
        deadline = time.monotonic() + self.failover_s
        backoff, followed = 0.05, set()
        while True:
            stub = getattr(self._replicas.missions if service == "missions" else self._replicas.fleet, method)
            try:
                return stub(request, metadata=self.metadata, timeout=self.timeout_s)
            except grpc.RpcError as error:
                if self.closed:
                    raise
                if error.code() == grpc.StatusCode.RESOURCE_EXHAUSTED:
                    hint = retry_pushback_s(error)
                    # Never sooner than the growing pause: a hint of 0 from
                    # the network must not turn this into a busy loop.
                    wait = None if hint is None else max(hint, backoff)
                    if wait is None or time.monotonic() + wait >= deadline:
                        raise
                    time.sleep(wait)
                    backoff = min(1.0, backoff * 2)
                    continue
                if error.code() != grpc.StatusCode.UNAVAILABLE:
                    raise
                misconfigured = self._replicas.misconfigured(error)
                if misconfigured is not None:
                    raise misconfigured
                explained = self._replicas.explained(error)
                named = self._replicas.follow(error)
                if (not named and not idempotent) or time.monotonic() >= deadline:
                    raise explained
                # A holder named for the first time is asked at once; a dead
                # holder the others still name (its lease has not run out)
                # and an executive that does not answer are asked again
                # after a pause.
                if named and self._replicas.current not in followed:
                    followed.add(self._replicas.current)
                    continue
                time.sleep(backoff)
                backoff = min(1.0, backoff * 2)

    # Missions -----------------------------------------------------------

    def create_mission(
        self,
        name: str,
        area: MapServerMap | pb.MapFrame,
        *,
        policy: str = "minpos",
        params: dict[str, float] | None = None,
        lockstep: bool = False,
    ) -> pb.Mission:
        """A mission over ``area``: a map_server map (its frame only: the
        building is what the robots explore) or an explicit frame."""
        frame = area.frame() if isinstance(area, MapServerMap) else area
        request = pb.CreateMissionRequest(
            name=name,
            frame=frame,
            policy=pb.PolicySpec(name=policy, params=params or {}),
            lockstep=lockstep,
        )
        return self._call("missions", "CreateMission", request, idempotent=False)

    def mission(self, mission_id: int) -> pb.Mission:
        return self._call("missions", "GetMission", pb.GetMissionRequest(mission_id=mission_id))

    def list_missions(self, *, page_size: int = 0) -> list[pb.Mission]:
        """Every mission, lowest id first, read a page at a time (at most
        ``page_size`` missions; 0 lets the executive choose, up to 1000 and
        4 MB a page)."""
        missions: list[pb.Mission] = []
        after_id = 0
        while True:
            request = pb.ListMissionsRequest(limit=page_size, after_id=after_id)
            page = self._call("missions", "ListMissions", request)
            missions.extend(page.missions)
            if page.next_after_id == 0:
                return missions
            if page.next_after_id <= after_id:
                raise RuntimeError("the executive's pages of missions do not move on")
            after_id = page.next_after_id

    def robots(self, mission_id: int) -> list[pb.Robot]:
        return list(self._call("missions", "ListRobots", pb.ListRobotsRequest(mission_id=mission_id)).robots)

    def segmentation(self, mission_id: int) -> tuple[pb.Segmentation, np.ndarray | None]:
        """The mission's rooms and corridors, and the segment of every cell:
        ``labels[row, column]``, row 0 the bottom row, 0 outside the free
        space; ``None`` when the mission was never segmented. The labels
        travel as runs, a few kilobytes for a building, and cell by cell
        only when the executive says their runs are too many to send."""

        def ask(runs: bool) -> pb.Segmentation:
            request = pb.GetSegmentationRequest(mission_id=mission_id, include_labels=True, label_runs=runs)
            return self._call("missions", "GetSegmentation", request)

        try:
            answer = ask(True)
        except grpc.RpcError as error:
            if error.code() != grpc.StatusCode.RESOURCE_EXHAUSTED:
                raise
            answer = ask(False)
        return answer, segment_labels(answer)

    def events(self, mission_id: int, *, page_size: int = 0) -> Iterator[pb.MissionEvent]:
        """Every event of the mission, oldest first, read a page at a time
        (``page_size`` events; 0 lets the executive choose, 1000)."""
        after_id = 0
        while True:
            request = pb.ListEventsRequest(mission_id=mission_id, limit=page_size, after_id=after_id)
            page = self._call("missions", "ListEvents", request)
            yield from page.events
            if page.next_after_id == 0:
                return
            if page.next_after_id <= after_id:
                raise RuntimeError("the executive's pages of events do not move on")
            after_id = page.next_after_id

    def watch_mission(self, mission_id: int) -> Iterator[pb.MissionView]:
        """The mission and its robots each time they change (until cancelled)."""
        request = pb.WatchMissionRequest(mission_id=mission_id)
        try:
            yield from self.missions.WatchMission(request, metadata=self.metadata)
        except grpc.RpcError as error:
            raise self._replicas.explained(error)

    def override_robot(
        self,
        robot_id: int,
        *,
        goto: tuple[float, float] | None = None,
        hold: bool = False,
        home: bool = False,
        release: bool = False,
        cancel: bool = False,
        actor: str = "",
        reason: str = "",
    ) -> pb.Robot:
        """Steps in for one robot: exactly one of ``goto``, ``hold``,
        ``home``, ``release`` or ``cancel``. An executive that checks tokens
        records the token's name as the actor."""
        chosen = [goto is not None, hold, home, release, cancel]
        if sum(chosen) != 1:
            raise ValueError("give exactly one of goto, hold, home, release, cancel")
        request = pb.OverrideRobotRequest(robot_id=robot_id, actor=actor, reason=reason)
        if goto is not None:
            request.goto.CopyFrom(pb.Point(x=goto[0], y=goto[1]))
        elif hold:
            request.hold.SetInParent()
        elif home:
            request.home.SetInParent()
        elif release:
            request.release.SetInParent()
        else:
            request.cancel.SetInParent()
        return self._call("missions", "OverrideRobot", request)

    def pause_mission(self, mission_id: int, *, actor: str = "", reason: str = "") -> pb.Mission:
        """Every robot holds where it is until :meth:`resume_mission`."""
        request = pb.MissionControlRequest(mission_id=mission_id, actor=actor, reason=reason)
        return self._call("missions", "PauseMission", request, idempotent=False)

    def resume_mission(self, mission_id: int, *, actor: str = "", reason: str = "") -> pb.Mission:
        """Robots get targets again."""
        request = pb.MissionControlRequest(mission_id=mission_id, actor=actor, reason=reason)
        return self._call("missions", "ResumeMission", request, idempotent=False)

    def delete_mission(self, mission_id: int, *, actor: str = "", reason: str = "") -> None:
        """Deletes a completed or paused mission with its robots, tasks, map
        and history (FAILED_PRECONDITION while it runs), freeing its place
        among the executive's missions."""
        request = pb.MissionControlRequest(mission_id=mission_id, actor=actor, reason=reason)
        self._call("missions", "DeleteMission", request, idempotent=False)

    # Robots ---------------------------------------------------------------

    def register_robot(
        self,
        mission_id: int,
        name: str,
        pose: tuple[float, float, float],
        *,
        sensor_range_m: float = 4.0,
        field_of_view_rad: float = 2 * math.pi,
        speed_mps: float = 0.5,
        footprint_radius_m: float = 0.0,
    ) -> "Robot":
        """Registers (or re-registers) a robot; it speaks with its own token from then on."""
        request = pb.RegisterRobotRequest(
            mission_id=mission_id,
            name=name,
            capabilities=pb.RobotCapabilities(
                sensor_range_m=sensor_range_m,
                field_of_view_rad=field_of_view_rad,
                speed_mps=speed_mps,
                footprint_radius_m=footprint_radius_m,
            ),
            pose=pb.Pose(x=pose[0], y=pose[1], theta=pose[2]),
        )
        response = self._call("fleet", "RegisterRobot", request)
        # An executive that runs open issues no tokens: the robot speaks as
        # the connection does.
        session = Executive(
            self._addresses,
            response.token or self.token,
            root_certificates=self._root_certificates,
            timeout_s=self.timeout_s,
            failover_s=self.failover_s,
            _current=self._replicas.current,
        )
        return Robot(session, response.robot)


def segment_labels(segmentation: pb.Segmentation) -> np.ndarray | None:
    """The labels of a ``GetSegmentation`` answer as a (height, width) grid,
    from ``label_runs`` or ``labels``, whichever it holds; ``None`` for neither."""
    width, height = segmentation.frame.width, segmentation.frame.height
    if segmentation.label_runs:
        if len(segmentation.label_runs) % 8:
            raise ValueError(f"label_runs hold {len(segmentation.label_runs)} bytes, not pairs of 8")
        pairs = np.frombuffer(segmentation.label_runs, dtype="<u4").reshape(-1, 2)
        covered = int(pairs[:, 1].sum(dtype=np.uint64))
        if covered != width * height:
            raise ValueError(f"label_runs cover {covered} cells, not the map's {width} x {height}")
        labels = np.repeat(pairs[:, 0], pairs[:, 1])
    elif segmentation.labels:
        if len(segmentation.labels) != 4 * width * height:
            raise ValueError(f"labels hold {len(segmentation.labels)} bytes for a {width} x {height} map")
        labels = np.frombuffer(segmentation.labels, dtype="<u4")
    else:
        return None
    return labels.reshape(height, width)


class Robot:
    """One registered robot, speaking with its own token."""

    def __init__(self, session: Executive, record: pb.Robot) -> None:
        self._session = session
        self.record = record
        self.id = record.id
        self.mission_id = record.mission_id
        self._seq = record.last_map_seq

    @property
    def token(self) -> str | None:
        return self._session.token

    def close(self) -> None:
        self._session.close()

    def update_map(
        self,
        grid: np.ndarray,
        origin: tuple[int, int],
        pose: tuple[float, float, float],
        *,
        encoding: str = "probability",
        unknown: np.ndarray | None = None,
    ) -> pb.UpdateMapResponse:
        """Sends a rectangle of this robot's grid whose lower-left cell is
        ``origin`` in the mission grid (see :func:`patch_from_grid`), with
        the next sequence number. A resend of an update the executive had
        already applied (its answer was lost) counts as applied."""
        patch = patch_from_grid(grid, origin[0], origin[1], encoding=encoding, unknown=unknown)
        self._seq += 1
        request = pb.UpdateMapRequest(
            robot_id=self.id, seq=self._seq, pose=pb.Pose(x=pose[0], y=pose[1], theta=pose[2]), patches=[patch]
        )
        try:
            return self._session._call("fleet", "UpdateMap", request)
        except grpc.RpcError as error:
            if error.code() == grpc.StatusCode.ALREADY_EXISTS:
                assignment = self.assignment()
                return pb.UpdateMapResponse(applied_seq=self._seq, assignment=assignment)
            raise

    def heartbeat(
        self,
        pose: tuple[float, float, float],
        state: str = "moving",
        *,
        task_id: int = 0,
        reason: str = "",
    ) -> pb.Assignment:
        """Reports the pose and state (``idle``, ``moving``, ``arrived`` or
        ``failed``, the last two about ``task_id``); returns the assignment."""
        states = {
            "idle": pb.ROBOT_STATE_IDLE,
            "moving": pb.ROBOT_STATE_MOVING,
            "arrived": pb.ROBOT_STATE_ARRIVED,
            "failed": pb.ROBOT_STATE_FAILED,
        }
        if state not in states:
            raise ValueError(f"state {state!r}: expected one of {sorted(states)}")
        request = pb.HeartbeatRequest(
            robot_id=self.id,
            pose=pb.Pose(x=pose[0], y=pose[1], theta=pose[2]),
            state=states[state],
            task_id=task_id,
            reason=reason,
        )
        return self._session._call("fleet", "Heartbeat", request).assignment

    def submit_bids(self, bids: Sequence[Bid]) -> pb.SubmitBidsResponse:
        """Replaces this robot's bids (for bidding policies such as ``simmons``)."""
        messages = []
        for bid in bids:
            message = pb.Bid(
                target=pb.Point(x=bid.x, y=bid.y), path_cost=bid.path_cost, information_gain=bid.information_gain
            )
            if bid.gain_region is not None:
                x0, y0, x1, y1 = bid.gain_region
                message.gain_region.CopyFrom(pb.Rect(min_x=x0, min_y=y0, max_x=x1, max_y=y1))
            messages.append(message)
        request = pb.SubmitBidsRequest(robot_id=self.id, bids=messages)
        return self._session._call("fleet", "SubmitBids", request)

    def assignment(self) -> pb.Assignment:
        """The current assignment."""
        return self._session._call("fleet", "GetAssignment", pb.GetAssignmentRequest(robot_id=self.id))

    def assignments(self, *, max_backoff_s: float = 5.0) -> Iterator[pb.Assignment]:
        """Every assignment from now on, the current one first.

        When the stream ends or breaks because the executive stopped,
        restarted or shed load, it waits (0.1 s, doubling up to
        ``max_backoff_s``) and reconnects, to the next replica given if
        there are several; when its replica names another as the mission's
        holder, it reconnects there at once. The current assignment is sent
        again on reconnection, so a change made meanwhile is not missed. It
        ends when the robot is closed; other errors are raised.
        """
        backoff = 0.1
        while True:
            stream = self._session.fleet.WatchAssignment(
                pb.WatchAssignmentRequest(robot_id=self.id), metadata=self._session.metadata
            )
            try:
                for assignment in stream:
                    backoff = 0.1
                    yield assignment
                # The executive ended the stream (it is shutting down): reconnect.
            except grpc.RpcError as error:
                if self._session.closed:
                    return
                if error.code() not in RETRYABLE:
                    raise
                misconfigured = self._session._replicas.misconfigured(error)
                if misconfigured is not None:
                    raise misconfigured
                if self._session._replicas.follow(error):
                    continue  # another replica holds the mission: ask it at once
            finally:
                stream.cancel()
            time.sleep(backoff)
            backoff = min(max_backoff_s, backoff * 2)
