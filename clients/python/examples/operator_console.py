"""An operator's view of a running executive, written against the package.
(Not named operator.py: Python puts a script's folder first on the import
path, and a file of that name would hide the standard library's `operator`
from every script run here.)

    python examples/operator_console.py --server 127.0.0.1:50051 list
    python examples/operator_console.py --server 127.0.0.1:50051 watch 1
    python examples/operator_console.py --server 127.0.0.1:50051 override 3 --goto 2.5,-1.0 --reason "check the door"

`watch` prints a line whenever the mission changes, until it completes (or
--views lines). `override` sends one robot somewhere (or holds, homes,
releases it, or cancels its override) and prints its new target.
"""

from __future__ import annotations

import argparse

import grpc
from exploration_executive import Executive, pb


def show(mission: pb.Mission) -> str:
    state = pb.MissionState.Name(mission.state).removeprefix("MISSION_STATE_").lower()
    coverage = 100.0 * mission.known_cells / max(1, mission.frame.width * mission.frame.height)
    return (
        f"mission {mission.id} {mission.name!r}: {state}, {mission.policy.name}, {mission.robots} robots, "
        f"{coverage:.1f} % known, {mission.frontier_cells} frontier cells"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--server", default="127.0.0.1:50051")
    parser.add_argument("--token", default=None, help="operator token (a viewer's may list and watch)")
    commands = parser.add_subparsers(dest="command", required=True)
    commands.add_parser("list")
    watch = commands.add_parser("watch")
    watch.add_argument("mission", type=int)
    watch.add_argument("--views", type=int, default=0, help="stop after this many (0: until completed)")
    override = commands.add_parser("override")
    override.add_argument("robot", type=int)
    action = override.add_mutually_exclusive_group(required=True)
    action.add_argument("--goto", help="x,y in metres")
    for flag in ("hold", "home", "release", "cancel"):
        action.add_argument(f"--{flag}", action="store_true")
    override.add_argument("--reason", default="")
    args = parser.parse_args()

    with Executive(args.server, args.token) as executive:
        if args.command == "list":
            for mission in executive.list_missions():
                print(show(mission))
        elif args.command == "watch":
            for count, view in enumerate(executive.watch_mission(args.mission), start=1):
                moving = sum(1 for r in view.robots if r.state == pb.ROBOT_STATE_MOVING)
                print(f"{show(view.mission)}; {moving} moving")
                if view.mission.state == pb.MISSION_STATE_COMPLETED or count == args.views:
                    break
        else:
            goto = tuple(float(v) for v in args.goto.split(",")) if args.goto else None
            if goto is not None and len(goto) != 2:
                parser.error("--goto takes x,y")
            robot = executive.override_robot(
                args.robot,
                goto=goto,
                hold=args.hold,
                home=args.home,
                release=args.release,
                cancel=args.cancel,
                actor="operator.py",
                reason=args.reason,
            )
            kind = pb.TaskKind.Name(robot.task_kind).removeprefix("TASK_KIND_").lower()
            print(f"robot {robot.id} {robot.name!r}: {kind} to ({robot.target.x:.2f}, {robot.target.y:.2f})")


if __name__ == "__main__":
    try:
        main()
    except grpc.RpcError as refused:
        # The executive's answer says what was wrong; a traceback would bury it.
        raise SystemExit(f"{refused.code().name}: {refused.details()}") from None
