"""Channels to one executive, or to replicas sharing one database, that
follow each mission to the replica holding it.

A replica that does not hold a request's mission answers UNAVAILABLE and
names the holder's address in the ``exploration-owner`` metadata; the call
was not carried out, so it is sent on there at once. A replica that cannot be
reached, or answers UNAVAILABLE without naming another, is left for the next
address of the list. This is the Python side of ``proto/src/replicas.rs``,
which ``fleet-sim`` and ``coordctl`` use.
"""

from __future__ import annotations

import ipaddress
import warnings
from collections.abc import Sequence
from urllib.parse import urlparse

import grpc

from ._proto.exploration.v1 import exploration_pb2_grpc as rpc
from .mismatch import Misconfigured, explained, hint_for

#: The largest message read, as the project's Rust clients read
#: (``exploration_proto::MAX_MESSAGE_BYTES``): gRPC's default of 4 MB would
#: refuse the map of a mission over 4 million cells (2 100 × 2 100).
MAX_MESSAGE_BYTES = 64 * 1024 * 1024

#: The response metadata naming the replica that holds a mission.
OWNER_METADATA = "exploration-owner"


def addresses_of(address: str | Sequence[str]) -> list[str]:
    """The URLs of ``host:port``, a URL, a comma-separated list of them, or
    a sequence (``host:port`` is ``http://host:port``, as replicas name
    each other)."""
    given = address.split(",") if isinstance(address, str) else list(address)
    addresses = [_url(a.strip()) for a in given if a.strip()]
    if not addresses:
        raise ValueError("address: give at least one host:port or URL")
    return addresses


def _url(address: str) -> str:
    return address if "://" in address else f"http://{address}"


def owner_named_by(error: grpc.RpcError) -> str | None:
    """The holder's address an UNAVAILABLE answer names, if any."""
    if error.code() != grpc.StatusCode.UNAVAILABLE:
        return None
    trailing = getattr(error, "trailing_metadata", None)
    for key, value in (trailing() if trailing else None) or ():
        if key == OWNER_METADATA and value:
            return value if isinstance(value, str) else value.decode()
    return None


def _target(address: str) -> tuple[str, str, bool]:
    """``(host:port, host, tls)`` of ``host:port``, ``http://…`` or ``https://…``."""
    parsed = urlparse(_url(address))
    try:
        port = parsed.port
    except ValueError:  # "Port out of range 0-65535", without the address
        port = None
    if parsed.scheme not in ("http", "https") or not parsed.hostname or not port:
        raise ValueError(f"address {address!r}: expected host:port, http://host:port or https://host:port")
    return f"{parsed.hostname}:{port}", parsed.hostname, parsed.scheme == "https"


def _is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


class Replicas:
    """Channels to the addresses given (opened when first used), calls going
    to the one that answered last or that was named as a mission's holder."""

    def __init__(
        self,
        addresses: Sequence[str],
        root_certificates: bytes | None,
        *,
        token_sent: bool,
        current: str | None = None,
    ) -> None:
        self.given = list(addresses)
        self.root_certificates = root_certificates
        self.token_sent = token_sent
        for address in self.given:
            self._check(address)
        self.current = current or self.given[0]
        self._channels: dict[str, tuple[grpc.Channel, rpc.MissionsStub, rpc.FleetStub]] = {}

    def _check(self, address: str) -> None:
        _, host, tls = _target(address)
        if self.token_sent and not tls and not _is_loopback(host):
            warnings.warn(f"the token crosses the network to {host} in plaintext: use https://", stacklevel=4)

    def _open(self, address: str) -> tuple[grpc.Channel, rpc.MissionsStub, rpc.FleetStub]:
        if address not in self._channels:
            target, _, tls = _target(address)
            options = [("grpc.max_receive_message_length", MAX_MESSAGE_BYTES)]
            if tls:
                credentials = grpc.ssl_channel_credentials(root_certificates=self.root_certificates)
                channel = grpc.secure_channel(target, credentials, options=options)
            else:
                channel = grpc.insecure_channel(target, options=options)
            self._channels[address] = (channel, rpc.MissionsStub(channel), rpc.FleetStub(channel))
        return self._channels[address]

    @property
    def missions(self) -> rpc.MissionsStub:
        return self._open(self.current)[1]

    @property
    def fleet(self) -> rpc.FleetStub:
        return self._open(self.current)[2]

    @property
    def tls(self) -> bool:
        """Whether the replica the calls go to now is spoken to over TLS."""
        return _target(self.current)[2]

    def explained(self, error: grpc.RpcError) -> grpc.RpcError:
        """``error`` with what to change, where it came of TLS and plaintext
        mixed up or of a certificate that does not fit (see :mod:`.mismatch`)."""
        return explained(error, self.tls)

    def misconfigured(self, error: grpc.RpcError) -> Misconfigured | None:
        """``error`` explained, when it is a TLS handshake that failed and no
        other address was given: asking again cannot help, so the caller
        should not wait out its failover time."""
        found = hint_for(error, self.tls)
        if found is None or not found[1] or len(self.given) > 1:
            return None
        return Misconfigured(error, found[0])

    def follow(self, error: grpc.RpcError) -> bool:
        """After an UNAVAILABLE answer: ``True`` when it named a holder other
        than the replica asked, which the next calls go to; otherwise the
        next address of the list is tried from now on."""
        owner = owner_named_by(error)
        if owner is not None and _url(owner) != self.current:
            try:
                self._check(_url(owner))
            except ValueError:
                owner = None  # not an address: the answer names no holder
        if owner is not None and _url(owner) != self.current:
            self.current = _url(owner)
            return True
        if error.code() == grpc.StatusCode.UNAVAILABLE:
            self.advance()
        return False

    def advance(self) -> None:
        """The next address given after the current one (the first, after
        an owner that was not in the list)."""
        position = self.given.index(self.current) + 1 if self.current in self.given else 0
        self.current = self.given[position % len(self.given)]

    def close(self) -> None:
        for channel, _, _ in self._channels.values():
            channel.close()
        self._channels.clear()
