"""A committed generation as stored: the `generations.population` frame, and its view by rank.

A run is a pure function of its config, its seed and the fitness it was told, so the store keeps
only what cannot be recomputed without simulating: what each generation was told (fitness, and
descriptors for a strategy that resumes from them) and, at a checkpoint, its genomes and Eq 12
components. Everything else is derived: the rank order is `ga.rank(fitness)` (what `tell`
ranked by), the parents are `ga.lineage`, and a generation between checkpoints gets its genomes
by replaying ask/tell from the checkpoint before it (`server.crud.replay`).

The frame (`schemas.wire`: raw arrays, self-describing, no pickle) holds, in ask order (the
position of each individual in the population as asked, which job slices cut):

- `fitness` (n,) float64: Eq 12 averaged over trials, NaN for a failed evaluation;
- `descriptors` (n, 4) float64: behaviour descriptors (`evorobotics.evaluate.DESCRIPTORS`),
  only for a strategy that resumes from its history (`strategies.traits(config).in_state`
  false);
- at a checkpoint only: `genomes` (n, weights) and `components` (n, trials, 4) (curve length,
  net offset, max offset, stuck), each byte-shuffled and zlib-compressed into a `|u1` array
  (mutants differ from their parents in a few high bytes: a third of the raw size).
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass
from typing import Any

import numpy as np

from evorobotics.ga import GAParams, GAState, lineage, rank
from evorobotics.strategies import traits
from schemas.run import RunConfig
from schemas.wire import WireError, decode_frame, encode_frame

KIND = "told"
_FLOAT = np.dtype("<f8")
_PACKED = ("genomes", "components")
"""Arrays stored compressed (`_pack`), described in the header's `packed` entry."""
_LEVEL = 6
"""zlib level: 9 saves 2 % more for three times the writer's time."""


class PopulationError(ValueError):
    """A stored population frame that does not hold what this module writes."""


@dataclass(frozen=True)
class Stored:
    """A generation's frame as stored, in ask order; `genomes` and `components` only at a
    checkpoint, `descriptors` only for a strategy that resumes from its history."""

    fitness: np.ndarray
    descriptors: np.ndarray | None = None
    genomes: np.ndarray | None = None
    components: np.ndarray | None = None

    @property
    def checkpoint(self) -> bool:
        return self.genomes is not None


@dataclass(frozen=True)
class Population:
    """A generation as the API shows it, by rank (0 = fittest)."""

    index: np.ndarray
    """(n,) its position in the population as asked."""
    parent: np.ndarray
    """(n,) the rank in the previous generation it descends from, -1 for none."""
    fitness: np.ndarray
    components: np.ndarray | None
    """(n, trials, 4), or None when the caller did not ask for them between checkpoints."""

    def __len__(self) -> int:
        return len(self.index)

    def parent_of(self, rank: int) -> int | None:
        p = int(self.parent[rank])
        return None if p < 0 else p

    def fitness_of(self, rank: int) -> float | None:
        """None for a failed (NaN) evaluation, as the REST API shows it."""
        f = float(self.fitness[rank])
        return f if np.isfinite(f) else None


def by_rank(
    config: RunConfig, generation: int, fitness: np.ndarray, components: np.ndarray | None
) -> Population:
    """The rank view of a generation told `fitness` (ask order), `components` in ask order."""
    order = rank(fitness)
    parents = np.full(len(fitness), -1, dtype=np.int64)
    if traits(config).in_state:
        kinds = lineage(GAParams.from_config(config), min(generation, 2))  # the same from 2 on
        parents = np.array([max(p, -1) for _, p in kinds], dtype=np.int64)
    return Population(
        index=order,
        parent=parents[order],
        fitness=fitness[order],
        components=None if components is None else components[order],
    )


def encode(stored: Stored) -> bytes:
    arrays: dict[str, np.ndarray] = {"fitness": stored.fitness.astype(_FLOAT, copy=False)}
    packed: dict[str, Any] = {}
    if stored.descriptors is not None:
        arrays["descriptors"] = stored.descriptors.astype(_FLOAT, copy=False)
    for name in _PACKED:
        value = getattr(stored, name)
        if value is not None:
            value = np.ascontiguousarray(value, dtype=_FLOAT)
            packed[name] = list(value.shape)
            arrays[name] = _pack(value)
    return encode_frame({"kind": KIND, "packed": packed}, arrays)


def decode(data: bytes) -> Stored:
    """Inverse of `encode`; PopulationError if the frame is not one this module wrote (kind,
    names, dtypes and shapes)."""
    try:
        header, arrays = decode_frame(bytes(data))
    except WireError as exc:
        raise PopulationError(f"not a frame: {exc}") from None
    if header.get("kind") != KIND:
        raise PopulationError(f"frame of kind {header.get('kind')!r}, expected {KIND!r}")
    packed = header.get("packed")
    fitness = arrays.get("fitness")
    if (
        not isinstance(packed, dict)
        or set(packed) - set(_PACKED)
        or set(arrays) - {"fitness", "descriptors", *_PACKED}
        or set(packed) != set(arrays) & set(_PACKED)
        or fitness is None
        or fitness.dtype != _FLOAT
        or fitness.ndim != 1
    ):
        raise PopulationError(f"population frame of arrays {sorted(arrays)}, packed {packed!r}")
    n = len(fitness)
    values = {name: _unpack(arrays[name], shape, name) for name, shape in packed.items()}
    descriptors = arrays.get("descriptors")
    if descriptors is not None and (descriptors.dtype != _FLOAT or descriptors.shape != (n, 4)):
        raise PopulationError(f"descriptors of {descriptors.shape} for {n} individuals")
    genomes, components = values.get("genomes"), values.get("components")
    if (genomes is None) != (components is None):
        raise PopulationError("a checkpoint needs both genomes and components")
    if genomes is not None and (genomes.ndim != 2 or len(genomes) != n):
        raise PopulationError(f"genomes of {genomes.shape} for {n} individuals")
    if components is not None and (components.ndim != 3 or components.shape[::2] != (n, 4)):
        raise PopulationError(f"components of {components.shape} for {n} individuals")
    return Stored(fitness, descriptors, genomes, components)


def _pack(a: np.ndarray) -> np.ndarray:
    """The bytes of float64 `a`, grouped by byte position (sign and exponent together), zlib'd."""
    shuffled = a.reshape(-1).view(np.uint8).reshape(-1, _FLOAT.itemsize).T.tobytes()
    return np.frombuffer(zlib.compress(shuffled, _LEVEL), dtype=np.uint8)


def _unpack(packed: np.ndarray, shape: object, name: str) -> np.ndarray:
    """Inverse of `_pack`, refusing anything but exactly the bytes `shape` needs."""
    if (
        not isinstance(shape, list)
        or not all(isinstance(d, int) and 0 <= d < 2**31 for d in shape)
        or packed.dtype != np.uint8
    ):
        raise PopulationError(f"packed {name} of shape {shape!r}")
    size = int(np.prod(shape, dtype=np.int64)) * _FLOAT.itemsize
    inflate = zlib.decompressobj()
    try:
        raw = inflate.decompress(packed.tobytes(), size)
    except zlib.error as exc:
        raise PopulationError(f"packed {name}: {exc}") from None
    if len(raw) != size or inflate.unconsumed_tail or not inflate.eof:
        raise PopulationError(f"packed {name} does not hold {shape} float64")
    planes = np.frombuffer(raw, dtype=np.uint8).reshape(_FLOAT.itemsize, -1)
    return np.ascontiguousarray(planes.T).view(_FLOAT).reshape(shape)


def encode_state(state: GAState) -> bytes:
    """A checkpoint's GA state as a frame of raw arrays, without `ranked` (the generation's
    genomes in rank order, which its population frame holds)."""
    return encode_frame({"kind": "ga-state"}, state.to_arrays(ranked=False))


def decode_state(data: bytes, *, ranked: np.ndarray) -> GAState:
    """Inverse of `encode_state`, given the checkpoint's genomes in rank order (WireError or
    ValueError on anything but its frame)."""
    header, arrays = decode_frame(data)
    if header.get("kind") != "ga-state":
        raise WireError(f"frame of kind {header.get('kind')!r}, expected 'ga-state'")
    return GAState.from_arrays({**arrays, "ranked": ranked})
