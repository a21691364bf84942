"""Connections that fail because of how they were configured, told as what
to change: TLS and plaintext mixed up, a CA that did not sign the
executive's certificate, a certificate for another host.

gRPC reports them all as UNAVAILABLE, the code of an executive that is
restarting, so without this a client would wait out its failover time and
end with "Socket closed". This is the Python side of ``mismatch_hint`` in
``proto/src/client.rs``, which coordctl and fleet-sim use.
"""

from __future__ import annotations

import grpc

PLAINTEXT_TO_TLS = "if the executive there serves TLS, use https://"
TLS_TO_PLAINTEXT = "the executive there does not serve TLS: use http://"
NOT_OUR_CA = "the executive's certificate is not signed by the CA given as root_certificates"
NOT_ITS_NAME = "the executive's certificate does not name the host of the address"

# gRPC core's words for each failure, as it writes them in the details of a
# call that found no connection.
_TLS_HANDSHAKE_FAILURES = (
    # A plaintext executive answered the ClientHello with an HTTP/2 frame.
    ("WRONG_VERSION_NUMBER", TLS_TO_PLAINTEXT),
    ("CERTIFICATE_VERIFY_FAILED", NOT_OUR_CA),
    # A CA of the issuer's name, but another key.
    ("certificate signature failure", NOT_OUR_CA),
    ("Hostname Verification Check failed", NOT_ITS_NAME),
)


class Misconfigured(grpc.RpcError):
    """A failed call with what to change: the original error's code and
    trailers, its details followed by the hint. Raised from the original
    (its ``__cause__``), and caught by ``except grpc.RpcError`` as it was."""

    def __init__(self, error: grpc.RpcError, hint: str) -> None:
        super().__init__(error)
        self.error = error
        self.hint = hint
        self.__cause__ = error

    def code(self) -> grpc.StatusCode:
        return self.error.code()

    def details(self) -> str:
        return f"{self.error.details()} ({self.hint})"

    def __getattr__(self, name: str):  # noqa: ANN204
        # The rest of the call's face (trailing_metadata, debug_error_string
        # ...) is the original's.
        if name == "error":
            raise AttributeError(name)
        return getattr(self.error, name)

    def __str__(self) -> str:
        return f"{self.code().name}: {self.details()}"


def hint_for(error: grpc.RpcError, tls: bool) -> tuple[str, bool] | None:
    """What to change after ``error`` on a channel that speaks TLS or not,
    and whether the failure is certain to repeat (a TLS handshake that
    failed) rather than possibly passing (a socket closed at once may also
    be an executive at its connection limit)."""
    if not hasattr(error, "code") or error.code() != grpc.StatusCode.UNAVAILABLE:
        return None
    details = error.details() or ""
    if tls:
        return next(((hint, True) for words, hint in _TLS_HANDSHAKE_FAILURES if words in details), None)
    # A TLS executive closes on a plaintext HTTP/2 preface.
    if "Socket closed" in details:
        return PLAINTEXT_TO_TLS, False
    return None


def explained(error: grpc.RpcError, tls: bool) -> grpc.RpcError:
    """``error`` with what to change, where it was a mismatch; else itself."""
    found = hint_for(error, tls)
    return Misconfigured(error, found[0]) if found else error
