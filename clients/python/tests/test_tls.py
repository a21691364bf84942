"""The package against an executive that serves TLS: what a fleet whose
tokens cross a network runs, and the mistakes made setting it up."""

from __future__ import annotations

import time

import grpc
import numpy as np
import pytest
from conftest import TOKEN, Coordinator, follow_assignments

from exploration_executive import Executive, Robot, pb
from exploration_executive.mismatch import NOT_OUR_CA, PLAINTEXT_TO_TLS, TLS_TO_PLAINTEXT, Misconfigured

# Long enough that a client which waited it out could not pass for one that
# gave up at once.
PATIENT_S = 120.0


def frame(width: int, height: int) -> pb.MapFrame:
    return pb.MapFrame(resolution=0.1, origin=pb.Point(x=0.0, y=0.0), width=width, height=height)


def test_a_robot_registers_maps_and_is_assigned_over_tls(tls_coordinator: Coordinator) -> None:
    ca = tls_coordinator.tls.ca.read_bytes()
    with Executive(tls_coordinator.url, TOKEN, root_certificates=ca) as operator:
        mission = operator.create_mission("tls", frame(20, 10), policy="nearest")
        robot = operator.register_robot(mission.id, "r1", (0.55, 0.55, 0.0))
        # The robot speaks with its own token, over TLS as well.
        assert robot.token and robot.token != TOKEN
        applied = robot.update_map(np.full((5, 5), 0.05, dtype=np.float32), (3, 3), (0.55, 0.55, 0.0))
        assert applied.applied_seq == 1
        _, first = follow_assignments(robot)
        assert first.kind == pb.TASK_KIND_EXPLORE
        robot.close()


def test_tls_and_plaintext_mixed_up_are_told_what_to_change(
    tls_coordinator: Coordinator, coordinator: Coordinator
) -> None:
    files = tls_coordinator.tls
    ca, other_ca = files.ca.read_bytes(), files.other_ca.read_bytes()

    def refusal(address: str, root_certificates: bytes | None, failover_s: float) -> tuple[grpc.RpcError, float]:
        started = time.monotonic()
        with Executive(address, TOKEN, root_certificates=root_certificates, failover_s=failover_s) as executive:
            with pytest.raises(grpc.RpcError) as refused:
                executive.list_missions()
        return refused.value, time.monotonic() - started

    # A TLS handshake that failed fails again: said at once, not after the
    # failover time meant for an executive that restarts.
    for address, roots, hint in [
        (f"https://{coordinator.address}", ca, TLS_TO_PLAINTEXT),
        (tls_coordinator.url, other_ca, NOT_OUR_CA),
    ]:
        error, waited = refusal(address, roots, PATIENT_S)
        assert isinstance(error, Misconfigured) and error.code() == grpc.StatusCode.UNAVAILABLE
        assert error.details().endswith(f"({hint})") and hint in str(error), error
        assert waited < PATIENT_S / 2, f"{address}: waited {waited:.1f} s for a handshake that cannot pass"
    # A socket closed at once may also be an executive at its connection
    # limit: tried again for the failover time, then said with the hint.
    error, _ = refusal(f"http://{tls_coordinator.address}", None, 0.5)
    assert isinstance(error, Misconfigured) and error.code() == grpc.StatusCode.UNAVAILABLE
    assert error.details().endswith(f"({PLAINTEXT_TO_TLS})"), error
    # A robot following its assignments with the wrong CA is told, not
    # left reconnecting for ever.
    with Executive(tls_coordinator.url, TOKEN, root_certificates=ca) as operator:
        mission = operator.create_mission("tls", frame(20, 10), policy="nearest")
        record = operator.register_robot(mission.id, "r1", (0.55, 0.55, 0.0)).record
    wrong = Robot(Executive(tls_coordinator.url, TOKEN, root_certificates=other_ca, failover_s=PATIENT_S), record)
    with pytest.raises(Misconfigured, match="not signed by the CA"):
        next(wrong.assignments())
    wrong.close()
