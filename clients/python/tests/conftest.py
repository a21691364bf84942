"""A real coordinator for the tests: the workspace's binary (COORDINATOR_BIN,
or target/debug/coordinator of this repository) on a free loopback port,
with its database in the test's temporary folder."""

from __future__ import annotations

import itertools
import os
import queue
import signal
import socket
import subprocess
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import grpc
import pytest

REPOSITORY = Path(__file__).resolve().parents[3]
TOKEN = "python-client-tests-operator-token"


def coordinator_binary() -> Path:
    path = Path(os.environ.get("COORDINATOR_BIN", REPOSITORY / "target" / "debug" / "coordinator"))
    if not path.is_file():
        pytest.skip(f"SKIPPED: no coordinator binary at {path} (cargo build -p coordinator, or set COORDINATOR_BIN)")
    return path


_next_port = itertools.count((os.getpid() * 997) % 12_000)


def free_port() -> int:
    """A port nothing listens on, for the coordinator to be told to listen on.

    Below Linux's ephemeral range (32768 and up), from which bind(0) picks and
    the kernel gives outgoing connections their ports: a port from bind(0),
    released for the coordinator, could be taken by a client socket first.
    """
    while True:
        port = 20_000 + next(_next_port) % 12_000
        with socket.socket() as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
            return port


@dataclass(frozen=True)
class TlsFiles:
    """Certificates made by the Rust test that runs these (rcgen): a CA, the
    executive's certificate for 127.0.0.1 signed by it, and a second CA that
    signed nothing here."""

    ca: Path
    server_cert: Path
    server_key: Path
    other_ca: Path

    @staticmethod
    def given() -> TlsFiles:
        folder = os.environ.get("EXPLORATION_TLS_DIR")
        if not folder:
            pytest.skip("SKIPPED: the TLS tests need EXPLORATION_TLS_DIR (tests/tests/python_client.rs makes one)")
        path = Path(folder)
        return TlsFiles(path / "ca.pem", path / "server.pem", path / "server.key", path / "other-ca.pem")


class Coordinator:
    """One coordinator process; restartable on the same port and database."""

    def __init__(
        self, folder: Path, token: str | None, flags: Sequence[str] = (), *, tls: TlsFiles | None = None
    ) -> None:
        self.binary = coordinator_binary()
        self.port = free_port()
        self.db = folder / "coordinator.db"
        self.log = folder / "coordinator.log"
        self.token = token
        self.flags = list(flags)
        self.tls = tls
        if tls is not None:
            self.flags += ["--tls-cert", str(tls.server_cert), "--tls-key", str(tls.server_key)]
        self.metrics_url: str | None = None
        self.process: subprocess.Popen[bytes] | None = None

    @property
    def address(self) -> str:
        return f"127.0.0.1:{self.port}"

    @property
    def url(self) -> str:
        return f"{'https' if self.tls else 'http'}://{self.address}"

    def start(self) -> None:
        command = [str(self.binary), "--listen", self.address, "--db", str(self.db)]
        if self.token:
            command += ["--operator-token", self.token]
        command += self.flags
        with self.log.open("ab") as log:
            self.process = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT)
        self._wait_until_accepting(deadline=time.monotonic() + 30)
        # A subchannel of its own: gRPC shares subchannels between channels of
        # one address, and one the tests' clients left in reconnect backoff
        # (after a kill) must not decide when this probe sees the server.
        options = [("grpc.use_local_subchannel_pool", 1)]
        if self.tls is None:
            channel = grpc.insecure_channel(self.address, options=options)
        else:
            credentials = grpc.ssl_channel_credentials(root_certificates=self.tls.ca.read_bytes())
            channel = grpc.secure_channel(self.address, credentials, options=options)
        try:
            grpc.channel_ready_future(channel).result(timeout=30)
        finally:
            channel.close()

    def _wait_until_accepting(self, deadline: float) -> None:
        while True:
            if self.process is not None and self.process.poll() is not None:
                raise RuntimeError(f"the coordinator exited with {self.process.returncode}; see {self.log}")
            try:
                socket.create_connection(("127.0.0.1", self.port), timeout=1).close()
                return
            except OSError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.05)

    def kill(self) -> None:
        """SIGKILL: no goodbye to anyone."""
        if self.process is not None:
            self.process.send_signal(signal.SIGKILL)
            self.process.wait()
            self.process = None

    def stop(self) -> None:
        if self.process is not None:
            self.process.terminate()
            try:
                self.process.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.kill()
            self.process = None


def serve(
    folder: Path, token: str | None, flags: Sequence[str] = (), *, tls: TlsFiles | None = None
) -> Iterator[Coordinator]:
    c = Coordinator(folder, token, flags, tls=tls)
    c.start()
    try:
        yield c
    finally:
        c.stop()


@pytest.fixture
def coordinator(tmp_path: Path) -> Iterator[Coordinator]:
    """An executive that checks tokens (operator token: TOKEN)."""
    yield from serve(tmp_path, TOKEN)


@pytest.fixture
def tls_coordinator(tmp_path: Path) -> Iterator[Coordinator]:
    """An executive that checks tokens and serves TLS only (see :class:`TlsFiles`)."""
    folder = tmp_path / "tls"  # beside another fixture's executive
    folder.mkdir()
    yield from serve(folder, TOKEN, tls=TlsFiles.given())


@pytest.fixture
def open_coordinator(tmp_path: Path) -> Iterator[Coordinator]:
    """An executive that runs open, as on a developer's loopback."""
    yield from serve(tmp_path, None)


@pytest.fixture
def shedding_coordinator(tmp_path: Path) -> Iterator[Coordinator]:
    """An open executive that refuses robots' calls once a queue of their
    kind has stood 5 ms (a target and interval of 1 ms: a retry hint of
    10 ms), with its metrics at ``metrics_url``."""
    http = free_port()
    flags = ["--shed-target-ms", "1", "--shed-interval-ms", "1", "--http", f"127.0.0.1:{http}"]
    for c in serve(tmp_path, None, flags):
        c.metrics_url = f"http://127.0.0.1:{http}/metrics"
        yield c


def wait_for(predicate, what: str, within_s: float = 30.0):  # noqa: ANN001, ANN201
    deadline = time.monotonic() + within_s
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError(f"timed out waiting for {what}")


def follow_assignments(robot) -> tuple[queue.Queue, object]:  # noqa: ANN001
    """Follows ``robot.assignments()`` on a thread into a queue; returns the
    queue and the first assignment with a task."""
    received: queue.Queue = queue.Queue()

    def follow() -> None:
        for assignment in robot.assignments(max_backoff_s=0.5):
            received.put(assignment)

    threading.Thread(target=follow, daemon=True).start()
    first = wait_for(lambda: next((a for a in iter(received.get, None) if a.task_id), None), "a first task")
    return received, first


def goto_from(received: queue.Queue) -> Callable[[], object]:
    """A predicate for :func:`wait_for`: the next GOTO assignment taken from
    ``received`` (a queue an assignment iterator fills), or ``None``."""
    from exploration_executive import pb

    def goto_arrived():  # noqa: ANN202
        try:
            a = received.get(timeout=1)
        except queue.Empty:
            return None
        return a if a.kind == pb.TASK_KIND_GOTO else None

    return goto_arrived
