"""Builds the package with the gRPC code generated from the repository's
proto/ by grpcio-tools (no generated code is checked in)."""

from __future__ import annotations

import importlib.metadata
import importlib.resources
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py

HERE = Path(__file__).resolve().parent
PROTO_ROOT = HERE.parent.parent / "proto" / "proto"
PROTO = "exploration/v1/exploration.proto"


def generate(out: Path) -> None:
    """Writes exploration_pb2(.pyi) and exploration_pb2_grpc into `out`."""
    from grpc_tools import protoc

    if not (PROTO_ROOT / PROTO).is_file():
        raise RuntimeError(f"{PROTO_ROOT / PROTO} not found: build from the repository's clients/python")
    out.mkdir(parents=True, exist_ok=True)
    well_known = importlib.resources.files("grpc_tools") / "_proto"
    args = [
        "grpc_tools.protoc",
        f"-I{PROTO_ROOT}",
        f"-I{well_known}",
        f"--python_out={out}",
        f"--pyi_out={out}",
        f"--grpc_python_out={out}",
        PROTO,
    ]
    if protoc.main(args) != 0:
        raise RuntimeError(f"grpc_tools.protoc failed on {PROTO}")
    generated = out / "exploration" / "v1"
    # protoc writes absolute imports ("from exploration.v1 import ..."); the
    # generated modules live inside this package, so make them relative.
    stub = generated / "exploration_pb2_grpc.py"
    stub.write_text(stub.read_text().replace("from exploration.v1 import", "from . import"))
    for package in (out, out / "exploration", generated):
        (package / "__init__.py").touch()


class BuildWithProto(build_py):
    def run(self) -> None:
        super().run()
        generate(Path(self.build_lib) / "exploration_executive" / "_proto")


def dependencies() -> list[str]:
    """The runtime the generated code was made for, at least: a stub from
    grpcio-tools X refuses to load under a grpcio older than X (a venv kept
    with grpcio 1.85.3 failed so beside grpcio-tools 1.85.4), and protobuf's
    generated modules check their runtime likewise."""
    tools = importlib.metadata.version("grpcio-tools")
    protobuf = importlib.metadata.version("protobuf")
    return [f"grpcio>={tools}", f"protobuf>={protobuf}", "numpy>=1.24", "PyYAML>=6"]


setup(cmdclass={"build_py": BuildWithProto}, install_requires=dependencies())
