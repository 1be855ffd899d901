"""The server's Ed25519 key: created on first start (file mode 600), signs robot commands.

Robot agents hold the public key (robot_agent/verify.py) and refuse a push, stop or
replacement whose signature over schemas.security.signed_bytes does not verify, or whose
sequence number is not above the last one they accepted. A sequence number is the server's Unix
time in nanoseconds or one more than the last one signed, whichever is larger, and the last one
is written durably beside the key before the signed command leaves: sequence numbers increase
strictly across restarts whatever the clock does, so a clock that ran ahead and was corrected
cannot make robots refuse the server's commands as replayed (docs/security.md).
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable
from pathlib import Path

from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
from fastapi import APIRouter, HTTPException, Request
from fastapi.responses import PlainTextResponse

from schemas.api import ErrorOut
from schemas.security import signed_bytes
from server.core.keys import load_or_create_key, public_pem


def seq_path(key_path: Path) -> Path:
    """Where the last signed sequence number of the key at `key_path` is kept."""
    return key_path.with_name(key_path.name + ".seq")


def read_seq(path: Path) -> int:
    """The sequence number stored at `path`, 0 if absent; ValueError if unreadable."""
    try:
        text = path.read_text()
    except FileNotFoundError:
        return 0
    try:
        value = int(text)
    except ValueError:
        raise ValueError(
            f"signing sequence file {path} is corrupt: restore it or delete it"
        ) from None
    if value < 0:
        raise ValueError(f"signing sequence file {path} holds a negative number")
    return value


def write_seq(path: Path, seq: int) -> None:
    """Store `seq` at `path` atomically and durably (fsync of the file and its directory)."""
    tmp = path.with_name(path.name + ".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    try:
        os.write(fd, str(seq).encode())
        os.fsync(fd)
    finally:
        os.close(fd)
    os.replace(tmp, path)
    directory = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(directory)
    finally:
        os.close(directory)


class Signer:
    """Signs commands to robots with one key; thread-safe.

    With `seq_file`, the last sequence number is read from it at start and written to it before
    `sign` returns; without, it lives in memory (an in-memory key dies with the process anyway).
    """

    def __init__(
        self,
        key: Ed25519PrivateKey,
        *,
        clock: Callable[[], int] = time.time_ns,
        seq_file: Path | None = None,
    ) -> None:
        self._key = key
        self._clock = clock
        self._seq_file = seq_file
        self._last = read_seq(seq_file) if seq_file is not None else 0
        self._lock = threading.Lock()
        self.public_pem = public_pem(key)

    @classmethod
    def from_file(cls, path: Path | None, *, clock: Callable[[], int] = time.time_ns) -> Signer:
        """The key in `path` (created on first use) and its sequence file beside it; a fresh
        in-memory key for None."""
        if path is None:
            return cls(Ed25519PrivateKey.generate(), clock=clock)
        return cls(load_or_create_key(path), clock=clock, seq_file=seq_path(path))

    @property
    def last_seq(self) -> int:
        with self._lock:
            return self._last

    def next_seq(self) -> int:
        """Strictly increasing, across restarts too: the clock, or one more than the last signed
        if the clock is behind it; stored before it is returned."""
        with self._lock:
            seq = max(self._clock(), self._last + 1)
            if self._seq_file is not None:
                write_seq(self._seq_file, seq)
            self._last = seq
            return seq

    def sign(self, *, kind: str, robot: str, push_id: str, document: str | None) -> tuple[int, str]:
        """(seq, hex signature) of one command to one robot."""
        seq = self.next_seq()
        message = signed_bytes(kind=kind, robot=robot, push_id=push_id, seq=seq, document=document)
        return seq, self._key.sign(message).hex()


class PemResponse(PlainTextResponse):
    """PEM text; as the response class it also declares the content type in OpenAPI."""

    media_type = "application/x-pem-file"


router = APIRouter(tags=["robots"])


@router.get(
    "/api/server-key",
    response_class=PemResponse,
    responses={
        200: {"description": "the public key, PEM (SubjectPublicKeyInfo)"},
        503: {
            "description": "the server has no signing key yet",
            "content": {"application/json": {"schema": ErrorOut.model_json_schema()}},
        },
    },
)
def server_key(request: Request) -> PemResponse:
    """The server's Ed25519 public key (PEM) that agents pin to verify pushes."""
    signer: Signer | None = getattr(request.app.state, "signer", None)
    if signer is None:
        raise HTTPException(503, "the server has no signing key yet")
    return PemResponse(signer.public_pem)
