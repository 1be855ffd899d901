"""An evolutionary run's configuration: every field optional, defaulting to the paper's experiment.

This is the single description of a run that crosses process boundaries: `colony evolve`
flags, `POST /api/runs` bodies, evaluation jobs sent to workers. A run is a pure function of it.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from schemas.network import NetworkSpec, resolve_network
from schemas.world import World


class FitnessWeights(BaseModel):
    """Eq 12: F = k1 total_curve_length + k2 net_offset + k3 max_offset - k4 stuck (metres)."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    k1: float = 0.0
    k2: float = 20.0
    k3: float = 20.0
    k4: float = Field(50.0, description="penalty subtracted once per trial that ends stuck")


class GAConfig(BaseModel):
    """Genetic algorithm parameters (Eqs 7, 9-11)."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    replacement: float = Field(
        0.25, gt=0.0, lt=0.5, description="m/n: fraction kept unchanged and fraction mutated"
    )
    selection: Literal["prose", "literal"] = Field(
        "prose",
        description="fill the rest with the fittest remaining (prose) or ranks 2m+1..n-1 (Eq 11 as printed)",
    )
    base_rate: float = Field(8.0, gt=0.0, description="Eq 9: expected mutations per sub-matrix")
    eta: float = Field(1.0, gt=0.0, description="Eq 10: base mutation step")
    init_scale: float = Field(1.0, gt=0.0, description="Eq 7: mu(1), the layer-1 init range")
    layer_slope: float = Field(
        0.25,
        ge=0.0,
        lt=1.0,
        description="mu(m) = scale * max(1 - slope*(m-1), 0.1): linear decrease",
    )
    delay_decay: float = Field(0.5, ge=0.0, description="tau(t) = exp(-decay * t), max 1 at t=0")
    recurrence_decay: float = Field(
        0.5, ge=0.0, description="sigma(s) = exp(-decay * s), max 1 at s=0"
    )


StrategyName = Literal["paper-ga", "cma-es", "sep-cma-es", "map-elites", "cma-me", "novelty"]
"""The optimisers behind the run loop (docs/strategies.md)."""

Descriptor = Literal["final_x", "final_y", "max_offset", "coverage"]
"""Behaviour descriptors of an evaluated individual, each in [0, 1] (`evaluate.DESCRIPTORS`)."""


ARCHIVE_BYTES = 256 * 2**20
"""Largest archive a run may ask for: pyribs allocates cells^2 genomes of float64 at once."""

CMA_FULL_WEIGHTS = 2_000
"""Largest network full CMA-ES may evolve: its covariance costs N^2 memory and an N^3
eigendecomposition per generation (7,104 weights: 400 MB and minutes); sep-cma-es has no limit."""

NOVELTY_ARCHIVE = 100_000
"""Most entries a novelty archive may reach (novelty_add x generations): every generation
measures distances to all of them."""


class StrategyConfig(BaseModel):
    """The settings of the strategies other than the paper's GA (each names who reads it)."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    sigma0: float = Field(
        0.5,
        gt=0.0,
        le=100.0,
        description="cma-es, sep-cma-es, cma-me: initial step size; map-elites: the Gaussian "
        "mutation step. In units of Eq 7's initial range of each weight (per weight for pycma "
        "and map-elites, its layer-1 value for cma-me)",
    )
    axes: tuple[Descriptor, Descriptor] = Field(
        ("final_x", "final_y"),
        description="map-elites, cma-me: the archive's two axes; novelty: the behaviour space",
    )
    cells: int = Field(
        20,
        ge=2,
        le=1000,
        description="map-elites, cma-me: archive cells per axis (the archive holds cells^2 "
        "genomes: at most ARCHIVE_BYTES of them)",
    )
    emitters: int = Field(
        1,
        ge=1,
        le=100,
        description="map-elites, cma-me: emitters sharing each generation's population (sizes "
        "differ by at most one)",
    )
    novelty_k: int = Field(
        15, ge=1, le=1000, description="novelty: nearest behaviours averaged into novelty"
    )
    novelty_add: int = Field(
        3,
        ge=0,
        le=10_000,
        description="novelty: each generation's most novel this many join its archive",
    )

    @model_validator(mode="after")
    def _check(self) -> StrategyConfig:
        if self.axes[0] == self.axes[1]:
            raise ValueError(f"axes must be two different descriptors, got {self.axes}")
        return self


class ValidationConfig(BaseModel):
    """The end-of-run re-scoring that picks the champion (docs/evolve.md, "The champion").

    The final population's `candidates` fittest on training are re-scored on `poses` start poses
    of their own seed stream (never a training pose) for `steps` steps each; the champion roams
    (neither stuck nor confined) on the most of them, ties to the higher mean Eq 12.
    `poses = 0` turns validation off: the champion is training rank 0.
    """

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    poses: int = Field(40, ge=0, le=10_000, description="validation start poses; 0: off")
    steps: int = Field(1000, ge=1, le=100_000, description="steps of each validation trial")
    candidates: int = Field(
        100, ge=1, le=10_000, description="the final population's fittest this many are re-scored"
    )
    test_poses: int = Field(
        200,
        ge=0,
        le=10_000,
        description="the champion's held-out test: start poses (and gap worlds) never used to "
        "choose it, each run nominal and under the gap for `steps` steps; 0: no test",
    )


class Proportion(BaseModel):
    """A fraction of trials with its 95 % Wilson score interval."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    value: float = Field(ge=0.0, le=1.0)
    low: float = Field(ge=0.0, le=1.0)
    high: float = Field(ge=0.0, le=1.0)


class WorldScore(BaseModel):
    """A champion's held-out figures in one kind of world."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    roaming: Proportion = Field(description="neither stuck nor confined over the whole trial")
    stuck: Proportion = Field(description="stuck by the trial's last step")
    max_offset: float = Field(ge=0.0, le=1e6, description="mean largest distance from start, m")


class HeldOutScore(BaseModel):
    """A champion's held-out test (the `test` member of its document): start poses from
    Purpose.TEST and gap worlds from Purpose.TEST_GAP, streams that neither training nor
    validation draw from, so these figures are not biased by the choice they report on."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    poses: int = Field(ge=1, le=10_000)
    steps: int = Field(ge=1, le=100_000)
    seed: int = Field(ge=0, lt=2**63, description="the run's seed")
    nominal: WorldScore = Field(description="the world's nominal robot")
    gap: WorldScore = Field(description="every trial's robot drawn from the reality gap")


class ValidationScore(BaseModel):
    """How a champion did on its run's validation set: the `validation` member of its document."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    poses: int = Field(ge=1, le=10_000)
    steps: int = Field(ge=1, le=100_000)
    seed: int = Field(
        ge=0, lt=2**63, description="the run's seed; poses from its validation stream"
    )
    candidates: int = Field(ge=1, le=10_000, description="individuals re-scored")
    training_rank: int = Field(ge=0, le=10_000, description="the champion's rank on training")
    score: float = Field(allow_inf_nan=False, description="mean Eq 12 over the validation trials")
    stuck: float = Field(ge=0.0, le=1.0, description="fraction of validation trials ending stuck")
    roaming: float = Field(
        ge=0.0, le=1.0, description="fraction neither stuck nor confined (evorobotics.explore)"
    )


@lru_cache(maxsize=64)
def _with_gap_range(world: World, whisker_range: tuple[float, float]) -> World:
    """`world` with another gap range, cached: every job of a run asks for the same one."""
    return world.model_copy(update={"gap_whisker_range": whisker_range})


NO_GAP_ROBOTS = (
    "reality_gap 'colony' needs the calibrated robots in world.gap_robots (POST /api/runs fills "
    "them from the colony's calibrations: colony robot calibrate ROBOT)"
)


class RunConfig(BaseModel):
    """One evolutionary experiment; defaults are the paper's (section 4)."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    population: int = Field(100, ge=4, le=10_000)
    generations: int = Field(350, ge=1, le=100_000)
    trials: int = Field(3, ge=1, le=100)
    steps: int | None = Field(
        None,
        ge=1,
        le=100_000,
        description="steps of each training trial; None: `crossings` x the crossing rule",
    )
    crossings: int = Field(
        3,
        ge=1,
        le=100,
        description="with steps None, trials last this many maze crossings at full speed "
        "(1 is the paper's rule; docs/simulator.md)",
    )
    seed: int = Field(0, ge=0, lt=2**63)
    maze: str = Field("paper", min_length=1, max_length=4096, description="maze name or text")
    network: str | NetworkSpec = Field("paper-best", description="preset name or a spec")
    fitness: FitnessWeights = FitnessWeights()
    reality_gap: Literal["on", "off", "colony"] = Field(
        "on",
        description="'on': every trial's robot is drawn from the paper's reality gap (each "
        "whisker 25-100 mm, each wheel +-15 %: `world`'s gap fields), in training after "
        "`nominal_first`, in validation and in the champion's test; 'colony': drawn from the "
        "calibrated robots of `world.gap_robots` instead (POST /api/runs fills them from the "
        "colony's calibrations), `train_whisker_range` unused; 'off': the ideal world of "
        "`world`'s nominal values",
    )
    world: World = World()
    train_whisker_range: tuple[float, float] | None = Field(
        (0.025, 0.06),
        description="with the gap on, training and validation draw each whisker's trigger "
        "distance from this range, m: the short whiskers under which controllers get stuck "
        "(docs/evolve.md); the champion's test draws from the world's whole gap range. None: "
        "the world's range throughout",
    )
    nominal_first: float = Field(
        0.5,
        ge=0.0,
        lt=1.0,
        description="with the gap on, this fraction of the generations trains in the nominal "
        "world before the rest trains under the gap: a curriculum that roams more under the gap "
        "and keeps the nominal world's roaming (docs/evolve.md); 0: under the gap throughout. "
        "Validation and the champion's test are under the gap either way",
    )
    validation: ValidationConfig = ValidationConfig()
    ga: GAConfig = GAConfig()
    strategy: StrategyName = Field(
        "paper-ga",
        description="the optimiser: the paper's GA (Eqs 7, 9-11), pycma's CMA-ES or its "
        "separable variant, pyribs' MAP-Elites or CMA-ME, or novelty search",
    )
    strategy_settings: StrategyConfig = StrategyConfig()
    job_size: int = Field(
        25,
        ge=1,
        le=10_000,
        description="smallest evaluation job: the server cuts generations into jobs of this "
        "size, or one per live zenoh worker if larger; results never depend on the cut",
    )

    @field_validator("reality_gap", mode="before")
    @classmethod
    def _stored_flag(cls, value: object) -> object:
        """Configs stored before the gap was a choice hold a boolean: read true as on."""
        if isinstance(value, bool):
            return "on" if value else "off"
        return value

    @model_validator(mode="after")
    def _check(self) -> RunConfig:
        if isinstance(self.network, str):
            resolve_network(self.network)  # raises ValueError naming the presets
        if self.train_whisker_range is not None:
            lo, hi = self.train_whisker_range
            if not 0.0 <= lo <= hi <= 1.0:
                raise ValueError(
                    f"train_whisker_range must be 0 <= low <= high <= 1 m, got {lo} and {hi}"
                )
        if self.world.gap_robots and self.reality_gap != "colony":
            raise ValueError(
                "world.gap_robots are drawn from only under reality_gap 'colony', got "
                f"{self.reality_gap!r}"
            )
        m = self.replacement_count
        if 2 * m + 1 > self.population:
            raise ValueError(
                f"population {self.population} is too small for replacement "
                f"{self.ga.replacement}: Eq 11 needs n >= 2m+1 with m = {m}"
            )
        s = self.strategy_settings
        if self.strategy in ("map-elites", "cma-me"):
            if self.population < 2 * s.emitters:
                raise ValueError(
                    f"population {self.population} is too small for {s.emitters} emitters: "
                    "at least 2 genomes each"
                )
            size = s.cells**2 * self.network_spec.weight_count * 8
            if size > ARCHIVE_BYTES:
                raise ValueError(
                    f"an archive of {s.cells}^2 cells of {self.network_spec.weight_count}-weight "
                    f"genomes needs {size / 2**20:.0f} MiB, more than {ARCHIVE_BYTES // 2**20}"
                )
        weights = self.network_spec.weight_count
        if self.strategy == "cma-es" and weights > CMA_FULL_WEIGHTS:
            raise ValueError(
                f"cma-es on {weights} weights: full covariance is limited to "
                f"{CMA_FULL_WEIGHTS} weights; use sep-cma-es"
            )
        if self.strategy == "novelty" and s.novelty_add * self.generations > NOVELTY_ARCHIVE:
            raise ValueError(
                f"novelty_add {s.novelty_add} x {self.generations} generations exceeds "
                f"{NOVELTY_ARCHIVE} archive entries"
            )
        return self

    @property
    def gap(self) -> bool:
        """Whether trials draw their robot from a reality gap (the paper's or the colony's)."""
        return self.reality_gap != "off"

    def trains_under_gap(self, generation: int) -> bool:
        """Whether generation `generation`'s training trials draw their robot from the gap."""
        return self.gap and generation >= round(self.nominal_first * self.generations)

    @property
    def training_world(self) -> World:
        """The world training and validation trials draw their gap from: `world` with
        `train_whisker_range` as its gap range."""
        if self.reality_gap == "colony":
            if not self.world.gap_robots:
                raise ValueError(NO_GAP_ROBOTS)
            return self.world
        if self.train_whisker_range is None:
            return self.world
        return _with_gap_range(self.world, self.train_whisker_range)

    @property
    def network_spec(self) -> NetworkSpec:
        return (
            self.network if isinstance(self.network, NetworkSpec) else resolve_network(self.network)
        )

    @property
    def replacement_count(self) -> int:
        """m of Eq 11: round(n * m/n), at least 1."""
        return max(1, round(self.population * self.ga.replacement))
