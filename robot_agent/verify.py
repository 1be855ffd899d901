"""Verification of the server's signed commands on the robot (docs/security.md).

An agent with a server key refuses a push, stop or replacement that is unsigned or whose
Ed25519 signature over schemas.security.signed_bytes fails. A push or replacement must also
carry a sequence number above the highest it has accepted (kept in the state dir, so a restart
does not reopen replay). A stop needs only its signature: it is applied whatever its sequence
number and never moves the highest one, so no clock can lock a robot's STOP out and a replayed
STOP can only stop the robot, never let a push be replayed.
The key comes from `colony agent --server-key FILE`, or is fetched once from
GET /api/server-key and pinned in the state dir (trust on first use).
"""

from __future__ import annotations

import os
import threading
from pathlib import Path

from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PublicKey

from schemas.security import signed_bytes

PINNED_KEY = "server-key.pem"
LAST_SEQ = "last-seq"


def load_public_key(pem: bytes) -> Ed25519PublicKey:
    """ValueError unless `pem` is an Ed25519 public key in PEM."""
    try:
        key = serialization.load_pem_public_key(pem)
    except ValueError as exc:
        raise ValueError(f"not a PEM public key: {exc}") from None
    if not isinstance(key, Ed25519PublicKey):
        raise ValueError("the server key must be an Ed25519 public key")
    return key


def pin_key(state_dir: Path, pem: bytes) -> Path:
    """Write the server key to the state dir (checked first); returns its path."""
    load_public_key(pem)
    path = state_dir / PINNED_KEY
    state_dir.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_bytes(pem)
    os.replace(tmp, path)
    return path


def pinned_key(state_dir: Path) -> bytes | None:
    """The pinned server key's PEM, or None if nothing is pinned."""
    try:
        return (state_dir / PINNED_KEY).read_bytes()
    except FileNotFoundError:
        return None


class Verifier:
    """Checks signatures and sequence numbers for one robot; thread-safe."""

    def __init__(self, pem: bytes, robot: str, state_dir: Path) -> None:
        self._key = load_public_key(pem)
        self._robot = robot
        self._path = state_dir / LAST_SEQ
        self._lock = threading.Lock()
        try:
            self._last = int(self._path.read_text())
        except (OSError, ValueError):
            self._last = -1

    @property
    def last_seq(self) -> int:
        return self._last

    def check(
        self, *, kind: str, push_id: str, seq: int, signature: str, document: str | None
    ) -> str | None:
        """None if the command is authentic and, unless a stop, fresh (its seq is then
        recorded), else why not."""
        if not signature:
            return "unsigned command refused: this robot verifies the server's signature"
        try:
            raw = bytes.fromhex(signature)
        except ValueError:
            return "signature is not hex"
        try:
            message = signed_bytes(
                kind=kind, robot=self._robot, push_id=push_id, seq=seq, document=document
            )
            self._key.verify(raw, message)
        except (InvalidSignature, ValueError):
            return "bad signature: the command was not signed by the pinned server key"
        if kind == "stop":
            return None
        with self._lock:
            if seq <= self._last:
                return f"replayed command: seq {seq} is not above the last accepted {self._last}"
            self._last = seq
            tmp = self._path.with_suffix(".tmp")
            self._path.parent.mkdir(parents=True, exist_ok=True)
            tmp.write_text(str(seq))
            os.replace(tmp, self._path)
        return None
