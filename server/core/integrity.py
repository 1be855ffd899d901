"""Checksums on the stored blobs: a damaged row is an error naming it, never served.

A generation's GA state and population frame are stored sealed: `SEAL` + the CRC-32 of the
bytes + the bytes. A trace batch's arrays share one CRC-32 in `robot_traces.checksum`. CRC-32
catches what disks and copies do to bytes (flipped bits, truncation, a page of another file),
not an adversary who can write the database, who could recompute it. Rows written before
checksums (no seal, a null checksum) are read unverified; `colony db check` counts them.
"""

from __future__ import annotations

import zlib
from collections.abc import Iterable

from server.core.errors import ServerError

SEAL = b"CRC1"
"""Starts a sealed blob; a bare frame starts with `schemas.wire.MAGIC` instead."""


class DamagedRowError(ServerError):
    """A stored row's bytes do not match their checksum; the message names the row."""


def seal(data: bytes) -> bytes:
    """`data` as stored: the seal, its CRC-32, then the bytes."""
    return SEAL + zlib.crc32(data).to_bytes(4, "little") + data


def unseal(blob: bytes, where: str) -> bytes:
    """The bytes `seal` stored (a blob stored before seals as it is); DamagedRowError naming
    `where` if they changed since."""
    if not blob.startswith(SEAL):
        return blob
    data = blob[len(SEAL) + 4 :]
    if len(blob) < len(SEAL) + 4 or zlib.crc32(data) != int.from_bytes(blob[4:8], "little"):
        raise DamagedRowError(f"{where}: stored bytes are damaged (checksum mismatch)")
    return data


def sealed(blob: bytes) -> bool:
    return blob.startswith(SEAL)


def checksum(parts: Iterable[bytes | None]) -> int:
    """CRC-32 of a row's blobs in order (a missing one counts as empty)."""
    crc = 0
    for part in parts:
        crc = zlib.crc32(part or b"", crc)
    return crc
