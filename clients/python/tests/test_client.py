"""The package against a real coordinator, used the way an integrator would."""

from __future__ import annotations

import sqlite3
import subprocess
import sys
import threading
import urllib.request

import grpc
import numpy as np
import pytest
from conftest import REPOSITORY, TOKEN, Coordinator, follow_assignments, goto_from, wait_for

from exploration_executive import Executive, MapServerMap, patch_from_grid, pb, read_pgm, segment_labels

WAREHOUSE = REPOSITORY / "maps" / "nav2_warehouse.yaml"
EXAMPLES = REPOSITORY / "clients" / "python" / "examples"


def frame(width: int, height: int) -> pb.MapFrame:
    return pb.MapFrame(resolution=0.1, origin=pb.Point(x=0.0, y=0.0), width=width, height=height)


def test_a_token_is_required_and_robots_get_their_own(coordinator: Coordinator) -> None:
    with Executive(coordinator.address) as anonymous, pytest.raises(grpc.RpcError) as refused:
        anonymous.list_missions()
    assert refused.value.code() == grpc.StatusCode.UNAUTHENTICATED
    with Executive(coordinator.address, TOKEN) as operator:
        mission = operator.create_mission("tokens", frame(20, 10), policy="nearest")
        robot = operator.register_robot(mission.id, "r1", (0.5, 0.5, 0.0))
        assert robot.token and robot.token != TOKEN and robot.token.startswith("rbt_")
        # The robot's token may report as itself, not administer missions.
        robot.heartbeat((0.5, 0.5, 0.0), "idle")
        with Executive(coordinator.address, robot.token) as as_robot, pytest.raises(grpc.RpcError) as denied:
            as_robot.create_mission("not mine", frame(5, 5))
        assert denied.value.code() == grpc.StatusCode.PERMISSION_DENIED
        robot.close()
    # What gRPC would refuse on every call, or read wrongly, is refused at once.
    with pytest.raises(ValueError, match="printable ASCII"):
        Executive(coordinator.address, "two\nlines")
    with pytest.raises(ValueError, match="127.0.0.1:99999': expected host:port"):
        Executive("127.0.0.1:99999")


def test_numpy_grids_become_patches_of_the_fused_map(open_coordinator: Coordinator) -> None:
    with Executive(open_coordinator.address) as executive:
        mission = executive.create_mission("patches", frame(20, 10), policy="nearest")
        robot = executive.register_robot(mission.id, "r1", (0.25, 0.15, 0.0))
        grid = np.array([[0.05, 0.05, np.nan], [0.95, 0.05, 0.05]], dtype=np.float32)
        first = robot.update_map(grid, (2, 1), (0.25, 0.15, 0.0))
        # Log-odds, with an explicit unknown mask; the sequence number moves on by itself.
        log_odds = np.log(grid / (1 - np.nan_to_num(grid, nan=0.5)))
        mask = np.array([[False, True, True], [True, True, True]])
        second = robot.update_map(log_odds, (10, 5), (0.25, 0.15, 0.0), encoding="log_odds", unknown=mask)
        assert (first.applied_seq, second.applied_seq) == (1, 2)
        snapshot = executive.missions.GetMap(pb.GetMapRequest(mission_id=mission.id))
        cells = np.frombuffer(snapshot.cells, dtype=np.uint8).reshape(10, 20)
        # Row 0 of the grid is the bottom row: grid[0] landed on row 1.
        assert cells[1, 2] < 20 and cells[1, 3] < 20 and cells[1, 4] == 255, cells[1, :6]
        assert cells[2, 2] > 80 and cells[2, 3] < 20
        assert cells[5, 10] < 20 and cells[5, 11] == 255 and cells[6, 10] == 255
        assert int((cells != 255).sum()) == 6
        # A rectangle off the grid is the executive's to refuse, naming it.
        with pytest.raises(grpc.RpcError) as refused:
            robot.update_map(np.zeros((3, 3)), (19, 9), (0.25, 0.15, 0.0))
        assert refused.value.code() == grpc.StatusCode.INVALID_ARGUMENT
        assert "patch" in refused.value.details()
        robot.close()


def test_a_truncated_or_foreign_image_is_refused_not_read_for_ever(tmp_path) -> None:
    image = tmp_path / "map.pgm"
    # b"P5" alone looped for ever: the header scan never met the data's end.
    for data, problem in [
        (b"P5", "ends after 1 of its 4 fields"),
        (b"P5 4 # a comment without its line's end", "ends after 2 of its 4 fields"),
        (b"P6 2 2 255\n" + bytes(12), "found the header b'P6 2 2 255'"),
        (b"P5 x 2 255\n", "found the header"),
        (b"P5 4 4 255\n" + bytes(3), "4 × 4 pixels announced, 3 bytes follow"),
    ]:
        image.write_bytes(data)
        with pytest.raises(ValueError, match=problem):
            read_pgm(image)
    image.write_bytes(b"P5\n# made by hand\n2 1\n255\n" + bytes([0, 254]))
    assert read_pgm(image).tolist() == [[0, 254]]


def test_malformed_grids_are_refused_before_anything_is_sent() -> None:
    with pytest.raises(ValueError, match="2-D"):
        patch_from_grid(np.zeros(4), 0, 0)
    with pytest.raises(ValueError, match="mask"):
        patch_from_grid(np.zeros((2, 2)), 0, 0, unknown=np.zeros((3, 2), dtype=bool))
    with pytest.raises(ValueError, match="off the grid"):
        patch_from_grid(np.zeros((2, 2)), -1, 0)
    with pytest.raises(ValueError, match="off the grid"):
        patch_from_grid(np.zeros((2, 2)), 0, 2**40)
    with pytest.raises(ValueError, match="encoding"):
        patch_from_grid(np.zeros((2, 2)), 0, 0, encoding="percent")
    with pytest.raises(ValueError, match=r"cell \(1, 0\) holds 101"):
        patch_from_grid(np.array([[0, 100], [101, -1]], dtype=np.int16), 0, 0, encoding="occupancy_percent")
    with pytest.raises(ValueError, match="integer"):
        patch_from_grid(np.array([[0.5]]), 0, 0, encoding="occupancy_percent")


def test_the_map_of_a_large_mission_is_read_whole(open_coordinator: Coordinator) -> None:
    # 4.4 million cells: more than gRPC's default 4 MB a message.
    with Executive(open_coordinator.address) as executive:
        mission = executive.create_mission("large", frame(2100, 2100), policy="nearest")
        snapshot = executive.missions.GetMap(pb.GetMapRequest(mission_id=mission.id))
        assert len(snapshot.cells) == 2100 * 2100
        assert set(snapshot.cells) == {255}


def test_the_segments_of_every_cell_are_read_from_their_runs(open_coordinator: Coordinator) -> None:
    # Two rooms, a doorway between them, the right-hand third still unknown.
    grid = np.zeros((30, 60), dtype=np.uint8)
    grid[[0, -1], :] = 100
    grid[:, [0, 20]] = 100
    grid[12:18, 20] = 0
    grid[:, 40:] = 255
    grid[2, 1:20] = 100  # a wall near the bottom: row 0 of the answer is the bottom row
    with Executive(open_coordinator.address) as executive:
        mission = executive.create_mission("rooms", frame(60, 30), policy="segmentation", lockstep=True)
        never, no_labels = executive.segmentation(mission.id)
        assert not never.HasField("computed_at") and no_labels is None
        robot = executive.register_robot(mission.id, "r1", (1.0, 1.5, 0.0))
        robot.update_map(grid, (0, 0), (1.0, 1.5, 0.0), encoding="occupancy_percent")
        answer, labels = executive.segmentation(mission.id)
        assert answer.HasField("computed_at") and answer.label_runs and not answer.labels
        assert labels is not None and labels.shape == (30, 60)
        assert (labels[2, 1:20] == 0).all() and labels[5, 5] > 0 and labels[15, 30] > 0
        assert int((labels > 0).sum()) == sum(s.cells for s in answer.segments)
        # The same labels as the executive sends them cell by cell.
        request = pb.GetSegmentationRequest(mission_id=mission.id, include_labels=True)
        per_cell = executive.missions.GetSegmentation(request)
        assert per_cell.labels and not per_cell.label_runs
        assert (segment_labels(per_cell) == labels).all()
        assert len(answer.label_runs) * 2 < len(per_cell.labels)
        robot.close()


def test_a_ros_occupancy_grid_is_sent_as_it_is(open_coordinator: Coordinator) -> None:
    with Executive(open_coordinator.address) as executive:
        mission = executive.create_mission("ros grid", frame(20, 10), policy="nearest")
        robot = executive.register_robot(mission.id, "r1", (0.25, 0.15, 0.0))
        # nav_msgs/OccupancyGrid.data, int8, row 0 the bottom row; -1 unknown.
        data = np.array([[0, 0, -1], [100, 5, 0]], dtype=np.int8)
        patch = patch_from_grid(data, 2, 1, encoding="occupancy_percent")
        assert patch.occupancy == bytes([0, 0, 255, 100, 5, 0]) and not patch.values
        # The same bytes unsigned make the same patch.
        assert patch_from_grid(data.view(np.uint8), 2, 1, encoding="occupancy_percent") == patch
        assert robot.update_map(data, (2, 1), (0.25, 0.15, 0.0), encoding="occupancy_percent").applied_seq == 1
        snapshot = executive.missions.GetMap(pb.GetMapRequest(mission_id=mission.id))
        cells = np.frombuffer(snapshot.cells, dtype=np.uint8).reshape(10, 20)
        # Fused as the probabilities they name (and clamped as every patch is).
        assert cells[1, 2] < 20 and cells[1, 3] < 20 and cells[1, 4] == 255, cells[1, :6]
        assert cells[2, 2] > 80 and cells[2, 3] < 20 and cells[2, 4] < 20, cells[2, :6]
        assert int((cells != 255).sum()) == 5
        robot.close()


def test_the_assignment_iterator_survives_an_executive_killed_and_restarted(coordinator: Coordinator) -> None:
    operator = Executive(coordinator.address, TOKEN)
    mission = operator.create_mission("restart", frame(60, 20), policy="nearest")
    robot = operator.register_robot(mission.id, "r1", (0.5, 0.5, 0.0))
    # Free cells with unknown beyond: a frontier for the robot to explore.
    robot.update_map(np.full((10, 10), 0.05), (0, 0), (0.5, 0.5, 0.0))
    received, first = follow_assignments(robot)
    assert first.kind == pb.TASK_KIND_EXPLORE

    coordinator.kill()
    coordinator.start()
    operator.close()
    operator = Executive(coordinator.address, TOKEN)
    operator.override_robot(robot.id, goto=(5.0, 1.0), reason="after the restart")

    after = wait_for(goto_from(received), "the override, through the reconnected stream")
    assert (after.target.x, after.target.y) == pytest.approx((5.0, 1.0), abs=0.1)
    robot.close()
    operator.close()


def test_the_example_robot_explores_the_bundled_warehouse(open_coordinator: Coordinator) -> None:
    command = [sys.executable, str(EXAMPLES / "robot.py"), "--server", open_coordinator.address, "--map", str(WAREHOUSE)]
    done = subprocess.run(command + ["--cell-size", "0.3"], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    assert "MISSION_STATE_COMPLETED" in done.stdout, done.stdout
    known_percent = float(done.stdout.split("(")[1].split(" %")[0])
    area = MapServerMap.load(WAREHOUSE).coarsened(0.3)
    free_percent = 100.0 * float((area.cells == 0).sum()) / area.cells.size
    assert known_percent > free_percent, f"it explored {known_percent} % of the map, {free_percent} % is free"


def test_the_example_operator_lists_watches_and_overrides(open_coordinator: Coordinator) -> None:
    with Executive(open_coordinator.address) as executive:
        mission = executive.create_mission("watched", frame(40, 20), policy="nearest")
        robot = executive.register_robot(mission.id, "r1", (0.5, 0.5, 0.0))

    def run(*args: str) -> str:
        command = [sys.executable, str(EXAMPLES / "operator_console.py"), "--server", open_coordinator.address, *args]
        done = subprocess.run(command, capture_output=True, text=True, timeout=60)
        assert done.returncode == 0, done.stderr
        return done.stdout

    assert "mission 1 'watched': active, nearest, 1 robots" in run("list")
    assert "1 robots" in run("watch", str(mission.id), "--views", "1")
    # The target is the centre of the cell holding the point.
    assert "goto to (2.05, 1.05)" in run("override", str(robot.id), "--goto", "2,1", "--reason", "look")
    # A refusal is the executive's status and message, not a traceback.
    command = [sys.executable, str(EXAMPLES / "operator_console.py"), "--server", open_coordinator.address]
    refused = subprocess.run(command + ["override", "999", "--hold"], capture_output=True, text=True, timeout=60)
    assert refused.returncode == 1, refused.stderr
    assert refused.stderr.startswith("NOT_FOUND: ") and "999" in refused.stderr, refused.stderr
    assert "Traceback" not in refused.stderr, refused.stderr


def test_events_are_read_page_by_page_oldest_first(open_coordinator: Coordinator) -> None:
    with Executive(open_coordinator.address) as executive:
        mission = executive.create_mission("logged", frame(20, 10), policy="nearest")
        control = pb.MissionControlRequest(mission_id=mission.id, actor="carol", reason="drill")
        for _ in range(3):
            executive.missions.PauseMission(control, metadata=executive.metadata)
            executive.missions.ResumeMission(control, metadata=executive.metadata)
        whole = list(executive.events(mission.id))
        paged = list(executive.events(mission.id, page_size=2))
        assert [e.kind for e in paged].count("mission_paused") == 3
        assert paged == whole
        assert [e.id for e in paged] == sorted({e.id for e in paged}), "oldest first, none twice"


def test_missions_are_read_page_by_page_lowest_id_first(open_coordinator: Coordinator) -> None:
    with Executive(open_coordinator.address) as executive:
        created = [executive.create_mission(f"listed {i}", frame(20, 10), policy="nearest").id for i in range(3)]
        whole = executive.list_missions()
        paged = executive.list_missions(page_size=1)
        assert paged == whole
        assert [m.id for m in paged][-3:] == created
        first = executive.missions.ListMissions(pb.ListMissionsRequest(limit=1), metadata=executive.metadata)
        assert len(first.missions) == 1 and first.next_after_id == first.missions[0].id


def test_a_mission_is_paused_then_deleted_with_its_robots(open_coordinator: Coordinator) -> None:
    with Executive(open_coordinator.address) as executive:
        mission = executive.create_mission("short-lived", frame(20, 10), policy="nearest")
        robot = executive.register_robot(mission.id, "r1", (0.5, 0.5, 0.0))
        with pytest.raises(grpc.RpcError) as running:
            executive.delete_mission(mission.id, reason="too soon")
        assert running.value.code() == grpc.StatusCode.FAILED_PRECONDITION
        assert executive.pause_mission(mission.id, reason="done").state == pb.MISSION_STATE_PAUSED
        executive.delete_mission(mission.id, reason="done")
        assert mission.id not in [m.id for m in executive.list_missions()]
        with pytest.raises(grpc.RpcError) as gone:
            executive.mission(mission.id)
        assert gone.value.code() == grpc.StatusCode.NOT_FOUND
        with pytest.raises(grpc.RpcError) as refused:
            robot.heartbeat((0.5, 0.5, 0.0), "idle")
        # This executive checks no token: the robot is simply gone.
        assert refused.value.code() == grpc.StatusCode.NOT_FOUND
        robot.close()


def shed_by_standing_queue(metrics_url: str) -> float:
    with urllib.request.urlopen(metrics_url, timeout=5) as page:
        for line in page.read().decode().splitlines():
            if line.startswith('coordinator_shed_total{name="standing queue"}'):
                return float(line.split()[-1])
    return 0.0


def test_a_robot_refused_by_an_executive_shedding_load_waits_the_hint_and_is_answered(
    shedding_coordinator: Coordinator,
) -> None:
    c = shedding_coordinator
    assert c.metrics_url is not None
    pose = (0.5, 0.5, 0.0)
    grid = np.full((5, 5), 0.05)
    with Executive(c.address) as executive:
        mission = executive.create_mission("shedding", frame(20, 10), policy="nearest")
        stuck, robot, probe = (executive.register_robot(mission.id, name, pose) for name in ("stuck", "r", "probe"))
        stuck.update_map(grid, (0, 0), pose)
        # Another program holds SQLite's write lock: the next update is
        # applied but stays in flight until it is durable, and a queue of
        # map updates stands.
        lock = sqlite3.connect(c.db, isolation_level=None)
        lock.execute("BEGIN IMMEDIATE")
        results: dict[str, object] = {}

        def send(name: str, sender) -> None:  # noqa: ANN001
            results[name] = sender.update_map(grid, (5, 0), pose)

        stuck_sender = threading.Thread(target=send, args=("stuck", stuck))
        sender = threading.Thread(target=send, args=("robot", robot))
        try:
            stuck_sender.start()
            # Raw calls (no retries) until one is refused: the queue stands.
            # One that arrives before the queue has stood 5 ms is admitted and
            # waits behind the lock too, until its deadline gives up on it.
            seq = 0
            while True:
                seq += 1
                request = pb.UpdateMapRequest(
                    robot_id=probe.id, seq=seq, pose=pb.Pose(x=0.5, y=0.5), patches=[patch_from_grid(grid, 10, 0)]
                )
                try:
                    executive.fleet.UpdateMap(request, timeout=0.2)
                except grpc.RpcError as error:
                    if error.code() == grpc.StatusCode.RESOURCE_EXHAUSTED:
                        hint = dict(error.trailing_metadata())["grpc-retry-pushback-ms"]
                        assert hint == "10", "ten intervals"
                        break
                    # grpcio reports a deadline passed in flight as either.
                    assert error.code() in (grpc.StatusCode.DEADLINE_EXCEEDED, grpc.StatusCode.CANCELLED), error
            refused = shed_by_standing_queue(c.metrics_url)
            sender.start()
            # The client is refused too, waits the hint and asks again, for as
            # long as the lock is held; without the retry its call would fail.
            wait_for(lambda: shed_by_standing_queue(c.metrics_url) >= refused + 2, "the client refused twice")
            assert "robot" not in results, "answered while the queue stood"
        finally:
            lock.execute("ROLLBACK")
            lock.close()
            for thread in (stuck_sender, sender):
                if thread.is_alive():
                    thread.join(timeout=30)
        answered = results.get("robot")
        assert isinstance(answered, pb.UpdateMapResponse) and answered.applied_seq == 1, results
        assert "stuck" in results, "the stuck update is answered once the lock is released"


class _Refused(grpc.RpcError):
    """An answer as grpcio raises it, with the trailers given."""

    def __init__(self, *trailers: tuple[str, str]) -> None:
        self._trailers = trailers

    def trailing_metadata(self) -> tuple[tuple[str, str], ...]:
        return self._trailers


def test_the_retry_hint_is_read_at_its_worst_values() -> None:
    from exploration_executive.client import retry_pushback_s

    hint = "grpc-retry-pushback-ms"
    assert retry_pushback_s(_Refused()) is None, "no trailer, no hint"
    assert retry_pushback_s(_Refused(("other", "5"))) is None
    assert retry_pushback_s(_Refused((hint, "250"))) == 0.25
    assert retry_pushback_s(_Refused((hint, "0"))) == 0.0
    for garbage in ("-1", "", "soon", "1e3", "\x00", "12ms"):
        assert retry_pushback_s(_Refused((hint, garbage))) is None, repr(garbage)
    assert retry_pushback_s(_Refused((hint, "9" * 40))) == 10.0, "held to 10 s"
    assert retry_pushback_s(grpc.RpcError()) is None, "an error without trailers"
