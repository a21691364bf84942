"""A simulated robot, written against the package, exploring a map_server map
with a running executive.

    python examples/robot.py --server 127.0.0.1:50051 --map ../../maps/nav2_warehouse.yaml

It stands on a free cell of the map, sees what a 360° range sensor would
(ray casting on the true map), sends what it saw as a map patch, and drives
one cell per step along a breadth-first path over the cells it knows to be
free towards the target the executive gives it, until the mission is done.
With nothing to do it waits on its assignment stream for the next task, as
a real robot would, instead of spending steps asking for it.
"""

from __future__ import annotations

import argparse
import math
import queue
import threading
import time
from collections import deque

import grpc
import numpy as np

from exploration_executive import FREE, OCCUPIED, Executive, MapServerMap, pb


def sense(truth: MapServerMap, at: tuple[int, int], range_cells: int) -> tuple[np.ndarray, int, int]:
    """What the sensor sees from `at`: a probability grid (NaN: not seen) and its lower-left cell."""
    x0, y0 = max(0, at[0] - range_cells), max(0, at[1] - range_cells)
    x1, y1 = min(truth.width, at[0] + range_cells + 1), min(truth.height, at[1] + range_cells + 1)
    seen = np.full((y1 - y0, x1 - x0), np.nan, dtype=np.float32)
    rim = [(x, y) for x in (x0, x1 - 1) for y in range(y0, y1)] + [(x, y) for y in (y0, y1 - 1) for x in range(x0, x1)]
    for ex, ey in rim:
        steps = max(abs(ex - at[0]), abs(ey - at[1]), 1)
        for k in range(steps + 1):
            x, y = round(at[0] + (ex - at[0]) * k / steps), round(at[1] + (ey - at[1]) * k / steps)
            if math.hypot(x - at[0], y - at[1]) > range_cells:
                break
            value = truth.cells[y, x]
            seen[y - y0, x - x0] = 0.95 if value == OCCUPIED else 0.05 if value == FREE else np.nan
            if value != FREE:
                break
    return seen, x0, y0


def path(known_free: np.ndarray, start: tuple[int, int], goal: tuple[int, int]) -> list[tuple[int, int]] | None:
    """A shortest 8-connected path over known free cells (the goal may be any known cell)."""
    parent = {start: start}
    queue = deque([start])
    while queue:
        here = queue.popleft()
        if here == goal:
            steps = [here]
            while steps[-1] != start:
                steps.append(parent[steps[-1]])
            return steps[::-1][1:]
        for dx, dy in ((1, 0), (-1, 0), (0, 1), (0, -1), (1, 1), (-1, 1), (1, -1), (-1, -1)):
            n = (here[0] + dx, here[1] + dy)
            inside = 0 <= n[0] < known_free.shape[1] and 0 <= n[1] < known_free.shape[0]
            if inside and n not in parent and (known_free[n[1], n[0]] or n == goal):
                parent[n] = here
                queue.append(n)
    return None


def wait_for_another_task(assignments: queue.Queue[pb.Assignment], task: int, patience_s: float = 1.0) -> None:
    """Waits (at most ``patience_s``) until the stream brings a task other
    than ``task``, or the end of the mission. The executive plans off the
    request path, so an arrival's next task comes a planning later."""
    deadline = time.monotonic() + patience_s
    while (left := deadline - time.monotonic()) > 0:
        try:
            assignment = assignments.get(timeout=left)
        except queue.Empty:
            return
        if assignment.task_id != task or assignment.mission_state == pb.MISSION_STATE_COMPLETED:
            return


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--server", default="127.0.0.1:50051")
    parser.add_argument("--token", default=None)
    parser.add_argument("--map", required=True, help="map_server YAML of the building")
    parser.add_argument("--cell-size", type=float, default=0.15)
    parser.add_argument("--policy", default="nearest")
    parser.add_argument("--sensor-range", type=float, default=4.0)
    parser.add_argument("--max-steps", type=int, default=20_000)
    args = parser.parse_args()

    truth = MapServerMap.load(args.map).coarsened(args.cell_size)
    free = np.argwhere(truth.cells == FREE)
    centre = free.mean(axis=0)
    y, x = (int(v) for v in free[np.argmin(((free - centre) ** 2).sum(axis=1))])

    executive = Executive(args.server, args.token)
    mission = executive.create_mission("robot.py", truth, policy=args.policy)
    robot = executive.register_robot(mission.id, "py-robot", truth.world(x, y) + (0.0,), sensor_range_m=args.sensor_range)
    assignments: queue.Queue[pb.Assignment] = queue.Queue()
    threading.Thread(target=lambda: [assignments.put(a) for a in robot.assignments()], daemon=True).start()
    known_free = np.zeros(truth.cells.shape, dtype=bool)
    range_cells = int(args.sensor_range / truth.resolution)
    route: list[tuple[int, int]] = []
    task = 0
    for step in range(1, args.max_steps + 1):
        seen, x0, y0 = sense(truth, (x, y), range_cells)
        known_free[y0 : y0 + seen.shape[0], x0 : x0 + seen.shape[1]] |= seen == 0.05
        pose = truth.world(x, y) + (0.0,)
        assignment = robot.update_map(seen, (x0, y0), pose).assignment
        if assignment.mission_state == pb.MISSION_STATE_COMPLETED:
            break
        if assignment.task_id != task:
            task = assignment.task_id
            goal = truth.cell(assignment.target.x, assignment.target.y)
            route = (path(known_free, (x, y), goal) or []) if task else []
            if task and not route:
                robot.heartbeat(pose, "failed", task_id=task, reason="no known path")
                continue
        if route:
            x, y = route.pop(0)
            robot.heartbeat(truth.world(x, y) + (0.0,), "arrived" if not route else "moving", task_id=task)
        else:
            robot.heartbeat(pose, "idle")
            wait_for_another_task(assignments, task)
    mission = executive.mission(mission.id)
    known = 100.0 * mission.known_cells / (truth.width * truth.height)
    state = pb.MissionState.Name(mission.state)
    print(f"mission {mission.id}: {state} after {step} steps, {mission.known_cells} cells known ({known:.1f} % of the map)")


if __name__ == "__main__":
    try:
        main()
    except grpc.RpcError as refused:
        # The executive's answer says what was wrong; a traceback would bury it.
        raise SystemExit(f"{refused.code().name}: {refused.details()}") from None
