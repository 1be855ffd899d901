"""generations store what they were told; genomes only at checkpoints

A run is a pure function of its config, seed and the fitness it was told, so a generation keeps
its statistics and its told fitness (and descriptors, for a strategy that resumes from them);
every 50th generation, a run's last written one and its final one also keep their GA state,
genomes and components, from which the others are replayed (`server.runs.population`,
`server.crud.replay`). Rows before held every generation's individuals by rank, a copy pointing
to the earlier row with its genome bytes; they are rewritten here, a run at a time. The freed
pages are reused by later rows (VACUUM returns them to the file system).

Revision ID: 0008_checkpoints
Revises: 0007_served_checksums
Create Date: 2026-12-04 17:30:00.000000
"""

from __future__ import annotations

import json
import struct
import zlib
from collections.abc import Sequence

import numpy as np
import sqlalchemy as sa
from alembic import op

revision: str = "0008_checkpoints"
down_revision: str | None = "0007_served_checksums"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

EVERY = 50
"""The checkpoint interval of the rows rewritten here (`Settings.checkpoint_every`'s default)."""


def upgrade() -> None:
    with op.batch_alter_table("generations", schema=None) as batch_op:
        batch_op.alter_column("state", existing_type=sa.LargeBinary(), nullable=True)
    conn = op.get_bind()
    generations = sa.table(
        "generations",
        sa.column("run_id", sa.Integer),
        sa.column("generation", sa.Integer),
        sa.column("state", sa.LargeBinary),
        sa.column("population", sa.LargeBinary),
    )
    runs = conn.execute(sa.text("SELECT id, config FROM runs")).all()
    for run_id, config in runs:
        settings = json.loads(config)
        final = int(settings.get("generations", 0)) - 1
        in_state = settings.get("strategy", "paper-ga") == "paper-ga"
        rows = conn.execute(
            sa.select(generations.c.generation, generations.c.population)
            .where(generations.c.run_id == run_id)
            .order_by(generations.c.generation)
        ).all()
        old = {g: _old_frame(_unseal(blob)) for g, blob in rows}
        if not old or next(iter(old.values())) is None:
            continue  # already rewritten
        last = max(old)
        for g, arrays in old.items():
            assert arrays is not None
            n = len(arrays["index"])
            index = arrays["index"].astype(np.int64)
            fitness, descriptors = np.empty(n), np.empty((n, 4))
            fitness[index] = arrays["fitness"]
            descriptors[index] = arrays.get("descriptors", np.full((n, 4), np.nan))
            keep = (g + 1) % EVERY == 0 or g in (last, final)
            genomes = components = None
            if keep:
                genomes = np.empty((n, arrays["genomes"].shape[1]))
                genomes[index] = _resolve(old, g)
                components = np.empty((n, *arrays["components"].shape[1:]))
                components[index] = arrays["components"]
            out: dict[str, np.ndarray] = {"fitness": fitness}
            packed: dict[str, list[int]] = {}
            if not in_state:
                out["descriptors"] = descriptors
            for name, value in (("genomes", genomes), ("components", components)):
                if value is not None:
                    packed[name] = list(value.shape)
                    out[name] = _pack(value)
            frame = _frame({"kind": "told", "packed": packed}, out)
            values: dict[str, bytes | None] = {"population": _seal(frame)}
            if not keep:
                values["state"] = None
            conn.execute(
                generations.update()
                .where(generations.c.run_id == run_id, generations.c.generation == g)
                .values(**values)
            )


# The codecs as of this revision (docs/architecture.md: a migration keeps its own copy).
_PREFIX = struct.Struct("<4sI")


def _unseal(blob: bytes) -> bytes:
    """A stored blob's bytes: `CRC1` + CRC-32 + bytes, or bare from before seals."""
    if not blob.startswith(b"CRC1"):
        return blob
    data = blob[8:]
    if zlib.crc32(data) != int.from_bytes(blob[4:8], "little"):
        raise RuntimeError("a generation's stored bytes are damaged: run `colony db check`")
    return data


def _seal(data: bytes) -> bytes:
    return b"CRC1" + zlib.crc32(data).to_bytes(4, "little") + data


def _old_frame(data: bytes) -> dict[str, np.ndarray] | None:
    """The arrays of a frame of the old `population` kind, None for a rewritten one."""
    magic, size = _PREFIX.unpack_from(data)
    header = json.loads(data[_PREFIX.size : _PREFIX.size + size])
    if magic != b"EVC1" or header.get("kind") != "population":
        return None
    arrays, offset = {}, _PREFIX.size + size
    for entry in header["arrays"]:
        dtype, shape = np.dtype(entry["dtype"]), tuple(entry["shape"])
        count = int(np.prod(shape, dtype=np.int64))
        arrays[entry["name"]] = np.frombuffer(data, dtype, count, offset).reshape(shape)
        offset += count * dtype.itemsize
    return arrays


def _frame(header: dict[str, object], arrays: dict[str, np.ndarray]) -> bytes:
    """A frame: `EVC1`, the JSON header's length and the header with its array index, then
    the arrays' little-endian bytes."""
    index = [{"name": k, "dtype": v.dtype.str, "shape": list(v.shape)} for k, v in arrays.items()]
    head = json.dumps({**header, "arrays": index}).encode()
    return b"".join(
        [_PREFIX.pack(b"EVC1", len(head)), head, *(v.tobytes() for v in arrays.values())]
    )


def _pack(a: np.ndarray) -> np.ndarray:
    """float64 bytes grouped by byte position, zlib'd (level 6)."""
    shuffled = np.ascontiguousarray(a, "<f8").reshape(-1).view(np.uint8).reshape(-1, 8).T
    return np.frombuffer(zlib.compress(shuffled.tobytes(), 6), dtype=np.uint8)


def _resolve(old: dict[int, dict[str, np.ndarray] | None], g: int) -> np.ndarray:
    """Generation g's genomes by rank: each row read at its (generation, row) of `genomes`."""
    arrays = old[g]
    assert arrays is not None
    at = arrays["genome_at"]
    out = np.empty((len(at), arrays["genomes"].shape[1]))
    for k, (holder, row) in enumerate(at):
        source = old[int(holder)]
        assert source is not None
        out[k] = source["genomes"][int(row)]
    return out


def downgrade() -> None:
    """Only a store without generations goes back: between checkpoints none hold genomes."""
    if op.get_bind().execute(sa.text("SELECT 1 FROM generations LIMIT 1")).first() is not None:
        raise RuntimeError("generations stored with checkpoints cannot be downgraded")
    with op.batch_alter_table("generations", schema=None) as batch_op:
        batch_op.alter_column("state", existing_type=sa.LargeBinary(), nullable=False)
