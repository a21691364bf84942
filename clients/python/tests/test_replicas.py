"""Executive replicas sharing one PostgreSQL database: the client follows a
mission to the replica that holds it, and through that replica's death to
the one that takes the mission over.

Needs EXPLORATION_REPLICAS_DB, the URL of an empty PostgreSQL database (the
workspace's test `python_client.rs` makes one where EXPLORATION_POSTGRES_URL
names a server, as `.ci/run` does); skipped, saying so, elsewhere.
"""

from __future__ import annotations

import os
import subprocess
from collections.abc import Iterator
from pathlib import Path

import grpc
import numpy as np
import pytest
from conftest import coordinator_binary, follow_assignments, free_port, goto_from, wait_for
from exploration_executive import Executive, pb
from exploration_executive.replicas import Replicas, addresses_of
from test_client import frame

DATABASE = os.environ.get("EXPLORATION_REPLICAS_DB")


class Replica:
    """One `coordinator --replica-id` process on the shared database."""

    def __init__(self, name: str, folder: Path) -> None:
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        command = [str(coordinator_binary()), "--listen", f"127.0.0.1:{self.port}", "--db", str(DATABASE)]
        command += ["--replica-id", name, "--lease-period", "1", "--lease-grace", "0.25"]
        with (folder / f"{name}.log").open("ab") as log:
            self.process = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT)

    def kill(self) -> None:
        self.process.kill()
        self.process.wait()


@pytest.fixture
def replicas(tmp_path: Path) -> Iterator[tuple[Replica, Replica]]:
    if not DATABASE:
        pytest.skip("SKIPPED: replicas need EXPLORATION_REPLICAS_DB, an empty PostgreSQL database's URL")
    pair = (Replica("a", tmp_path), Replica("b", tmp_path))
    try:
        for replica in pair:
            wait_for(lambda r=replica: _serving(r.url), f"replica {replica.url} to serve")
        yield pair
    finally:
        for replica in pair:
            replica.kill()


def _serving(url: str) -> bool:
    with Executive(url, failover_s=0) as probe:
        try:
            probe.list_missions()
            return True
        except Exception:  # noqa: BLE001 - not up yet
            return False


def test_the_client_follows_the_mission_to_its_holder_and_through_its_death(replicas) -> None:  # noqa: ANN001
    a, b = replicas
    with Executive(a.url) as creator:
        mission = creator.create_mission("replicas", frame(60, 20), policy="nearest")  # held by a

    # Given only b, the client is pointed to a, which holds the mission.
    operator = Executive(b.url)
    robot = operator.register_robot(mission.id, "r1", (0.5, 0.5, 0.0))
    assert operator.address == a.url
    robot.update_map(np.full((10, 10), 0.05), (0, 0), (0.5, 0.5, 0.0))
    received, _ = follow_assignments(robot)

    # The holder dies; b claims the mission once a's lease has run out, and
    # the robot's next update, retried meanwhile, is applied there.
    a.kill()
    answer = robot.update_map(np.full((10, 10), 0.05), (10, 0), (1.5, 0.5, 0.0))
    assert answer.applied_seq == 2
    assert robot._session.address == b.url
    assert operator.mission(mission.id).map_updates == 2
    assert operator.address == b.url

    # The assignment stream reconnected to b: an override made there arrives.
    operator.override_robot(robot.id, goto=(5.0, 1.0), reason="after the failover")

    after = wait_for(goto_from(received), "the override, through the stream reconnected to the new holder")
    assert (after.target.x, after.target.y) == pytest.approx((5.0, 1.0), abs=0.1)
    robot.close()
    operator.close()


class _Unavailable(grpc.RpcError):
    """An UNAVAILABLE answer whose trailers name ``owner``."""

    def __init__(self, owner: str) -> None:
        self.owner = owner

    def code(self) -> grpc.StatusCode:
        return grpc.StatusCode.UNAVAILABLE

    def trailing_metadata(self) -> tuple[tuple[str, str], ...]:
        return (("exploration-owner", self.owner),)


def test_an_owner_that_is_no_address_is_taken_for_none() -> None:
    replicas = Replicas(addresses_of("a:1,http://b:2"), None, token_sent=False)
    assert replicas.current == "http://a:1"
    # Named holders are followed, even off the list; from there, the list again.
    assert replicas.follow(_Unavailable("http://c:3"))
    assert replicas.current == "http://c:3"
    assert not replicas.follow(_Unavailable("http://c:3")), "the holder named is the one asked"
    assert replicas.current == "http://a:1"
    # Whatever the trailer holds that is no address: the next replica, no error.
    for garbage in ["", "\x00\n", "ftp://x:1", "http://no-port", "x" * 100_000, "http://[::1"]:
        before = replicas.current
        assert not replicas.follow(_Unavailable(garbage)), garbage[:20]
        assert replicas.current != before
    replicas.close()
