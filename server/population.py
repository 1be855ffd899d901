"""A committed generation's individuals as one value: the `generations.population` frame.

One row per generation instead of one per individual: at the paper's scale the store's
per-row work, not its bytes, was most of the server's recording. The frame (`schemas.wire`: raw arrays, self-describing, no pickle) holds, by rank
(0 = fittest):

- `index` (n,) int32: position in the population as asked (the job slices cut this order);
- `parent` (n,) int32: rank in the previous generation it descends from, -1 for none;
- `fitness` (n,) float64: Eq 12 averaged over trials, NaN for a failed evaluation;
- `components` (n, trials, 4) float64: Eq 12's curve length, net offset, max offset, stuck;
- `descriptors` (n, 4) float64: behaviour descriptors (`evorobotics.evaluate.DESCRIPTORS`),
  NaN in a frame written before they were stored;
- `genome_at` (n, 2) int32: the (generation, row of that generation's `genomes`) holding the
  individual's genome bytes, its own generation for a genome first stored here;
- `genomes` (m, weights): the bytes first stored in this generation, in rank order. Eq 11's
  copies (elites, fill, k-2 elite: three quarters of a generation) point to earlier rows.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from schemas.wire import WireError, decode_frame, encode_frame

KIND = "population"
_INT = np.dtype("<i4")
_FLOAT = np.dtype("<f8")
_KINDS = {
    "index": "i",
    "parent": "i",
    "fitness": "f",
    "components": "f",
    "descriptors": "f",
    "genome_at": "i",
    "genomes": "f",
}
"""numpy dtype kind of each array (integers, floats)."""


class PopulationError(ValueError):
    """A stored population frame that does not hold what this module writes."""


@dataclass(frozen=True)
class Population:
    """A generation as stored, by rank; `genomes` are only those first stored here."""

    index: np.ndarray
    parent: np.ndarray
    fitness: np.ndarray
    components: np.ndarray
    descriptors: np.ndarray
    genome_at: np.ndarray
    genomes: np.ndarray

    def __len__(self) -> int:
        return len(self.index)

    def parent_of(self, rank: int) -> int | None:
        p = int(self.parent[rank])
        return None if p < 0 else p

    def fitness_of(self, rank: int) -> float | None:
        """None for a failed (NaN) evaluation, as the REST API shows it."""
        f = float(self.fitness[rank])
        return f if np.isfinite(f) else None


def encode(population: Population) -> bytes:
    return encode_frame(
        {"kind": KIND},
        {
            "index": population.index.astype(_INT, copy=False),
            "parent": population.parent.astype(_INT, copy=False),
            "fitness": population.fitness.astype(_FLOAT, copy=False),
            "components": population.components.astype(_FLOAT, copy=False),
            "descriptors": population.descriptors.astype(_FLOAT, copy=False),
            "genome_at": population.genome_at.astype(_INT, copy=False),
            "genomes": population.genomes,
        },
    )


def decode(data: bytes) -> Population:
    """Inverse of `encode`; PopulationError if the frame is not a population this module
    wrote (kind, names, dtypes and shapes)."""
    try:
        header, arrays = decode_frame(bytes(data))
    except WireError as exc:
        raise PopulationError(f"not a frame: {exc}") from None
    if header.get("kind") != KIND:
        raise PopulationError(f"frame of kind {header.get('kind')!r}, expected {KIND!r}")
    try:
        population = Population(
            index=arrays["index"],
            parent=arrays["parent"],
            fitness=arrays["fitness"],
            components=arrays["components"],
            descriptors=arrays.get("descriptors", np.full((len(arrays["index"]), 4), np.nan)),
            genome_at=arrays["genome_at"],
            genomes=arrays["genomes"],
        )
    except KeyError as exc:
        raise PopulationError(f"population frame lacks array {exc}") from None
    n = len(population.index) if population.index.ndim == 1 else -1
    shapes = {name: getattr(population, name).shape for name in _KINDS}
    expected = {
        "index": (n,),
        "parent": (n,),
        "fitness": (n,),
        "descriptors": (n, 4),
        "genome_at": (n, 2),
    }
    if (
        any(shapes[name] != shape for name, shape in expected.items())
        or population.components.ndim != 3
        or population.components.shape[::2] != (n, 4)
        or population.genomes.ndim != 2
    ):
        raise PopulationError(f"population frame has arrays of shapes {shapes}")
    for name, kind in _KINDS.items():
        if getattr(population, name).dtype.kind != kind:
            raise PopulationError(f"population array {name!r} is not of kind {kind!r}")
    return population


def resolve(
    generation: int,
    population: Population,
    load: Callable[[Iterable[int]], dict[int, Population]],
    ranks: Sequence[int] | None = None,
) -> np.ndarray:
    """(k, weights) the genomes of `population` (generation `generation`) of `ranks` (all, in
    rank order, by default), a copy's bytes read from the generation that holds them (`load`
    gives those by number; only the generations the ranks need are loaded)."""
    at = population.genome_at if ranks is None else population.genome_at[np.asarray(ranks, int)]
    wanted = {int(g) for g in np.unique(at[:, 0])} - {generation}
    holders = {generation: population, **(load(sorted(wanted)) if wanted else {})}
    missing = wanted - holders.keys()
    if missing:
        raise PopulationError(
            f"generation {generation} points to genome bytes in generations {sorted(missing)}, "
            "which are not stored"
        )
    width, dtype = population.genomes.shape[1], population.genomes.dtype
    out = np.empty((len(at), width), dtype=dtype)
    for g in holders:
        mine = at[:, 0] == g
        rows = at[mine, 1]
        source = holders[g].genomes
        if source.shape[1] != width or source.dtype != dtype:
            raise PopulationError(
                f"generation {generation}'s genomes are {width} x {dtype}, generation {g}'s "
                f"{source.shape[1]} x {source.dtype}"
            )
        if len(rows) and (rows.max() >= len(source) or rows.min() < 0):
            raise PopulationError(f"generation {generation} points past generation {g}'s genomes")
        out[mine] = source[rows]
    return out
