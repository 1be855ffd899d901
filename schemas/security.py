"""Security shared by the server, workers and robot agents (docs/security.md).

One module on purpose: both ends of a signed push must build the very same bytes, and every
zenoh client (worker, agent) adds the same authentication keys. It depends on the standard
library alone; the Ed25519 code itself lives in server/signing.py (sign) and
robot_agent/verify.py (verify), which import `cryptography`.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

# ------------------------------------------------------------------ limits (docs/security.md)

MAX_BODY_BYTES = 1 << 20
"""REST request bodies (the largest legitimate one, a RunConfig with a 4 KiB maze, is ~6 KiB)."""
MAX_POPULATION_WEIGHTS = 8_000_000
"""population x weights of one run: its genomes are 64 MB of float64 (paper: 100 x 7104)."""
MAX_GENERATION_STEPS = 50_000_000
"""population x trials x steps: robot steps of one generation (paper: 100 x 3 x 40 = 12,000)."""
MAX_ZENOH_MESSAGE = 128 << 20
"""zenoh messages the server's router accepts (transport/link/rx/max_message_size)."""
MAX_ROBOT_MESSAGE = 32 << 20
"""A robot control message as bytes (a push of a 1M-weight controller document is ~20 MB)."""
MAX_TRACE_BYTES = 4 << 20
"""A trace batch as bytes (600 samples are ~25 KB)."""
MAX_TRACE_SAMPLES = 10_000
"""Samples in one trace batch (the agent sends at most 600)."""

# ------------------------------------------------------------------ zenoh authentication and TLS


def _json5(value: object) -> str:
    return json.dumps(value)


@dataclass(frozen=True)
class ZenohClientAuth:
    """What a zenoh client (worker, agent) adds to its config: user/password and a TLS root CA."""

    user: str | None = None
    password: str | None = None
    root_ca: Path | None = None
    """PEM of the CA that signed the router's certificate (for tls/ endpoints)."""

    def __post_init__(self) -> None:
        if (self.user is None) != (self.password is None):
            raise ValueError("zenoh user and password go together: give both or neither")
        if self.user is not None and (":" in self.user or not self.user):
            raise ValueError(f"zenoh user must be non-empty without ':', got {self.user!r}")

    def entries(self) -> list[tuple[str, str]]:
        """(key, json5 value) pairs for `zenoh.Config.insert_json5`."""
        out: list[tuple[str, str]] = []
        if self.user is not None:
            out.append(
                ("transport/auth/usrpwd", _json5({"user": self.user, "password": self.password}))
            )
        if self.root_ca is not None:
            out.append(("transport/link/tls/root_ca_certificate", _json5(str(self.root_ca))))
        return out


@dataclass(frozen=True)
class ZenohRouterAuth:
    """What the server's router adds: a user:password dictionary file, TLS certificate and key."""

    dictionary_file: Path | None = None
    """One `user:password` line per client; with it, clients without a valid pair are refused."""
    certificate: Path | None = None
    private_key: Path | None = None
    root_ca: Path | None = None
    """For a router that itself connects to a lab zenohd over tls/."""
    user: str | None = None
    password: str | None = None
    """Credentials the router presents when it connects to a lab zenohd with usrpwd."""
    max_message_size: int = MAX_ZENOH_MESSAGE

    def __post_init__(self) -> None:
        if (self.certificate is None) != (self.private_key is None):
            raise ValueError("a TLS certificate and its private key go together")
        if (self.user is None) != (self.password is None):
            raise ValueError("zenoh user and password go together: give both or neither")
        if self.max_message_size < 1 << 16:
            raise ValueError(f"max_message_size must be >= 65536, got {self.max_message_size}")

    def entries(self) -> list[tuple[str, str]]:
        """(key, json5 value) pairs for `zenoh.Config.insert_json5`."""
        out = [("transport/link/rx/max_message_size", str(self.max_message_size))]
        usrpwd: dict[str, str] = {}
        if self.dictionary_file is not None:
            usrpwd["dictionary_file"] = str(self.dictionary_file)
        if self.user is not None and self.password is not None:
            usrpwd.update(user=self.user, password=self.password)
        if usrpwd:
            out.append(("transport/auth/usrpwd", _json5(usrpwd)))
        tls: dict[str, str] = {}
        if self.certificate is not None and self.private_key is not None:
            tls.update(listen_certificate=str(self.certificate))
            tls.update(listen_private_key=str(self.private_key))
        if self.root_ca is not None:
            tls["root_ca_certificate"] = str(self.root_ca)
        if tls:
            out.append(("transport/link/tls", _json5(tls)))
        return out


# ------------------------------------------------------------------ signed controller pushes

SIGNING_CONTEXT = b"evocolony-signed-command-v1"


def signed_bytes(*, kind: str, robot: str, push_id: str, seq: int, document: str | None) -> bytes:
    """The exact bytes the server signs for one command to one robot.

    context, kind (push, stop, replacement), robot id, push id, sequence number and the sha256
    of the document's UTF-8 bytes (empty for a stop), newline-separated: a signature binds the
    document to this robot and this sequence number, so it cannot be replayed to another robot
    or, since agents keep the highest sequence seen, to the same robot later.
    """
    if seq < 0:
        raise ValueError(f"seq must be >= 0, got {seq}")
    digest = hashlib.sha256(document.encode()).hexdigest() if document is not None else ""
    fields = (kind, robot, push_id, str(seq), digest)
    if any("\n" in f for f in fields):
        raise ValueError("signed fields must not contain newlines")
    return SIGNING_CONTEXT + b"\n" + "\n".join(fields).encode()
