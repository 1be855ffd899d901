"""The strategies other than the paper's GA, behind `evolution.RunLoop`'s ask/tell.

- `cma-es`, `sep-cma-es`: pycma's `CMAEvolutionStrategy` (sep: option CMA_diagonal), popsize =
  population, minimising -fitness, from the origin with per-weight stds sigma0 x Eq 7's range.
- `map-elites`: pyribs' GridArchive over two descriptors (`StrategyConfig.axes`) and Gaussian
  emitters (per-weight step sigma0 x Eq 7's range) whose first batch is Eq 7's generation 0.
- `cma-me`: the same archive with CMA-ES emitters (pyribs' own CMA-ES, improvement ranking).
- `novelty`: the paper's GA (Eqs 7, 9-11) selecting on novelty instead of fitness: novelty =
  mean distance, in the `axes` plane, to the k nearest behaviours among its archive and the
  rest of the generation; each generation's `novelty_add` most novel join the archive.

Randomness: pycma draws from an option `randn` fed by rng(seed, generation, STRATEGY) and is
given seed=NaN, so it never touches numpy's global generator; pyribs' archive and emitters are
seeded from seed_sequence(seed, 0, STRATEGY, i); novelty's GA uses `ga_rng` as the paper GA
does. None of them reads the clock. Their objects are Python state, so a strategy is resumed by
replaying what it was told (`StrategyHistory`, `RunLoop.resume`), never pickled.

A failed evaluation (NaN fitness) ranks below every other: pycma and pyribs are told
FAILED_FITNESS for it (and descriptors 0 when they are NaN), novelty ranks it last.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from functools import cache
from typing import Any, Protocol

import numpy as np

from evorobotics.evaluate import DESCRIPTORS
from evorobotics.ga import GAParams, GAState, ga_rng, init, initial_population, weight_scale
from evorobotics.ga import ask as ga_ask
from evorobotics.ga import tell as ga_tell
from evorobotics.layout import Layout
from evorobotics.seeds import Purpose, rng, seed_sequence
from schemas.run import RunConfig

FAILED_FITNESS = -1e9
"""What pycma and pyribs are told for a failed evaluation (NaN fitness)."""


@dataclass(frozen=True)
class Traits:
    """What a strategy can do, for the roles that drive it (the server never compares names)."""

    in_state: bool
    """Its GAState is the whole loop (the paper's GA): a stored state resumes it, a worker
    evolves spans from it, its genomes have parents, and its champion comes from the ranked
    final generation without a replay. Otherwise the loop is replayed (`RunLoop.resume`)."""
    archive: bool
    """It keeps an archive of elites (`RunLoop.archive`)."""


def traits(config: RunConfig) -> Traits:
    """The traits of `config`'s strategy."""
    return Traits(
        in_state=config.strategy == "paper-ga",
        archive=config.strategy in ("map-elites", "cma-me", "novelty"),
    )


@cache
def _blas() -> Any:
    from threadpoolctl import ThreadpoolController

    return ThreadpoolController()


@contextmanager
def one_blas_thread() -> Iterator[None]:
    """pycma's and pyribs' linear algebra (eigh, matrix products) in one BLAS thread: OpenBLAS's
    threads spin against the simulation on a busy machine (a 222 x 222 eigh took 8x longer with
    two threads than with one on 2 loaded cores), and a fixed thread count keeps the sums'
    order, hence the bits, the same on every machine with the same BLAS kernels."""
    with _blas().limit(limits=1, user_api="blas"):
        yield


@dataclass(frozen=True)
class Archive:
    """A QD or novelty archive as arrays, m entries in a stable order (pyribs: by cell index;
    novelty: by arrival)."""

    descriptors: np.ndarray
    """(m, 2) the entries' values of `StrategyConfig.axes`."""
    fitness: np.ndarray
    """(m,) Eq 12 training fitness."""
    genomes: np.ndarray
    """(m, n_weights)."""


class Strategy(Protocol):
    """What RunLoop needs of a non-GA strategy: genomes to evaluate and the results back."""

    def ask(self, generation: int) -> np.ndarray:
        """(population, n_weights) genomes of `generation` (called once per generation)."""
        ...

    def tell(
        self, genomes: np.ndarray, fitness: np.ndarray, descriptors: np.ndarray | None
    ) -> None:
        """The results of the last `ask`: fitness (n,), descriptors (n, 4) or None; ValueError
        (and nothing changed) if the strategy needs descriptors it was not given."""
        ...

    def archive(self) -> Archive | None:
        """The archive, None for strategies without one."""
        ...


def make_strategy(config: RunConfig, spec_layout: Layout) -> Strategy | None:
    """The strategy of `config` at generation 0; None for paper-ga (RunLoop's own GA)."""
    if config.strategy == "paper-ga":
        return None
    if config.strategy in ("cma-es", "sep-cma-es"):
        return PyCMA(config, spec_layout)
    if config.strategy in ("map-elites", "cma-me"):
        return RibsQD(config, spec_layout)
    return Novelty(config, spec_layout)


def _objective(fitness: np.ndarray) -> np.ndarray:
    values = np.asarray(fitness, dtype=np.float64)
    return np.where(np.isnan(values), FAILED_FITNESS, values)


def _axes(config: RunConfig) -> list[int]:
    return [DESCRIPTORS.index(a) for a in config.strategy_settings.axes]


def _need(descriptors: np.ndarray | None, n: int, strategy: str) -> np.ndarray:
    if descriptors is None:
        raise ValueError(f"the {strategy} strategy needs the evaluation's descriptors")
    d = np.asarray(descriptors, dtype=np.float64)
    if d.shape != (n, len(DESCRIPTORS)):
        raise ValueError(f"descriptors must be ({n}, {len(DESCRIPTORS)}), got {d.shape}")
    return d


class PyCMA:
    """pycma's CMA-ES (full or separable) with a per-generation generator for its draws."""

    def __init__(self, config: RunConfig, spec_layout: Layout) -> None:
        import cma  # imported here: only runs that use it pay its import

        self.config = config
        self._gen = rng(config.seed, 0, Purpose.STRATEGY)
        scale = weight_scale(spec_layout, GAParams.from_config(config))
        options = {
            "popsize": config.population,
            "seed": np.nan,  # no np.random.seed: our randn below is the only source
            "randn": self._randn,
            "CMA_stds": scale,
            "CMA_diagonal": config.strategy == "sep-cma-es",
            "verbose": -9,
            "verb_log": 0,
            "verb_disp": 0,
            "maxiter": np.inf,
            "tolfun": 0,
            "tolx": 0,
        }
        self.es = cma.CMAEvolutionStrategy(
            np.zeros(spec_layout.n_weights), config.strategy_settings.sigma0, options
        )

    def _randn(self, *shape: int) -> np.ndarray:
        return self._gen.standard_normal(shape)

    def ask(self, generation: int) -> np.ndarray:
        self._gen = rng(self.config.seed, generation, Purpose.STRATEGY)
        with one_blas_thread():
            return np.array(self.es.ask(), dtype=np.float64)

    def tell(
        self, genomes: np.ndarray, fitness: np.ndarray, descriptors: np.ndarray | None
    ) -> None:
        del descriptors  # CMA-ES optimises fitness alone
        with one_blas_thread():
            self.es.tell(list(np.asarray(genomes)), list(-_objective(fitness)))

    def archive(self) -> Archive | None:
        return None


def _seed(seed: int, index: int) -> int:
    """An integer seed for pyribs object `index` of a run (their `seed` takes an int)."""
    state = seed_sequence(seed, 0, Purpose.STRATEGY, index).generate_state(1, np.uint64)
    return int(state[0])


def _split(total: int, parts: int) -> list[int]:
    """`parts` sizes summing to `total`, differing by at most one, larger first."""
    return [total // parts + (1 if i < total % parts else 0) for i in range(parts)]


class RibsQD:
    """pyribs' GridArchive with Gaussian (map-elites) or CMA-ES (cma-me) emitters."""

    def __init__(self, config: RunConfig, spec_layout: Layout) -> None:
        from ribs.archives import GridArchive
        from ribs.emitters import EmitterBase, EvolutionStrategyEmitter, GaussianEmitter
        from ribs.schedulers import Scheduler

        s = config.strategy_settings
        self.axes = _axes(config)
        self.strategy = config.strategy
        seeds = [_seed(config.seed, i) for i in range(s.emitters + 1)]
        n = spec_layout.n_weights
        self.grid = GridArchive(
            solution_dim=n, dims=(s.cells, s.cells), ranges=[(0.0, 1.0)] * 2, seed=seeds[0]
        )
        params = GAParams.from_config(config)
        emitters: list[EmitterBase] = []
        start = 0
        first = initial_population(ga_rng(config.seed, 0), spec_layout, params)
        for i, size in enumerate(_split(config.population, s.emitters)):
            if config.strategy == "map-elites":
                emitters.append(
                    GaussianEmitter(
                        self.grid,
                        sigma=s.sigma0 * weight_scale(spec_layout, params),
                        initial_solutions=first[start : start + size],
                        batch_size=size,
                        seed=seeds[i + 1],
                    )
                )
            else:
                emitters.append(
                    EvolutionStrategyEmitter(
                        self.grid,
                        x0=np.zeros(n),
                        sigma0=s.sigma0 * params.init_scale,
                        ranker="2imp",
                        batch_size=size,
                        seed=seeds[i + 1],
                    )
                )
            start += size
        self.scheduler = Scheduler(self.grid, emitters)

    def ask(self, generation: int) -> np.ndarray:
        del generation  # the emitters' own generators, seeded once, carry on
        with one_blas_thread():
            return np.array(self.scheduler.ask(), dtype=np.float64)

    def tell(
        self, genomes: np.ndarray, fitness: np.ndarray, descriptors: np.ndarray | None
    ) -> None:
        del genomes  # the scheduler keeps what it asked
        d = _need(descriptors, len(fitness), self.strategy)[:, self.axes]
        with one_blas_thread():
            self.scheduler.tell(_objective(fitness), np.nan_to_num(d, nan=0.0))

    def archive(self) -> Archive | None:
        data = self.grid.data(["index", "measures", "objective", "solution"])
        order = np.argsort(data["index"], kind="stable")
        return Archive(
            np.array(data["measures"][order], dtype=np.float64),
            np.array(data["objective"][order], dtype=np.float64),
            np.array(data["solution"][order], dtype=np.float64),
        )


def novelty(behaviours: np.ndarray, archive: np.ndarray, k: int) -> np.ndarray:
    """(n,) mean distance of each behaviour (n, d) to its k nearest among `archive` (m, d) and
    the other n - 1 (fewer if there are fewer); NaN for a NaN behaviour, which is no one's
    neighbour."""
    b = np.asarray(behaviours, dtype=np.float64)
    known = np.isfinite(b).all(axis=1)
    others = np.concatenate([archive, b[known]])
    dist = np.sqrt(((b[:, None, :] - others[None, :, :]) ** 2).sum(axis=2))
    self_col = len(archive) + np.cumsum(known) - 1
    rows = np.flatnonzero(known)
    dist[rows, self_col[rows]] = np.inf  # no one is its own neighbour
    count = min(k, max(others.shape[0] - 1, 0))
    out = np.full(len(b), np.nan)
    if count == 0:
        out[known] = 0.0
        return out
    nearest = np.partition(dist[known], count - 1, axis=1)[:, :count]
    out[known] = nearest.mean(axis=1)
    return out


class Novelty:
    """The paper's GA selecting on novelty; the archive keeps the most novel of each generation."""

    def __init__(self, config: RunConfig, spec_layout: Layout) -> None:
        self.config = config
        self.layout = spec_layout
        self.params = GAParams.from_config(config)
        self.state: GAState = init(spec_layout, self.params)
        self.axes = _axes(config)
        n = spec_layout.n_weights
        self._descriptors = np.empty((0, 2))
        self._fitness = np.empty(0)
        self._genomes = np.empty((0, n))

    def ask(self, generation: int) -> np.ndarray:
        genomes, _ = ga_ask(
            ga_rng(self.config.seed, generation), self.state, self.params, self.layout
        )
        return genomes

    def tell(
        self, genomes: np.ndarray, fitness: np.ndarray, descriptors: np.ndarray | None
    ) -> None:
        s = self.config.strategy_settings
        d = _need(descriptors, len(fitness), "novelty")[:, self.axes]
        score = novelty(d, self._descriptors, s.novelty_k)
        self.state, metrics = ga_tell(genomes, score, self.state, self.params)
        add = metrics.order[: s.novelty_add]
        add = add[np.isfinite(score[add])]
        self._descriptors = np.concatenate([self._descriptors, d[add]])
        self._fitness = np.concatenate([self._fitness, np.asarray(fitness, dtype=np.float64)[add]])
        self._genomes = np.concatenate([self._genomes, np.asarray(genomes)[add]])

    def archive(self) -> Archive | None:
        return Archive(self._descriptors.copy(), self._fitness.copy(), self._genomes.copy())
