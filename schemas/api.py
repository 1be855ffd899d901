"""Request and response bodies of the server's REST API (see docs/api.md).

Requests: `POST /api/runs` takes a `RunCreate`: a `schemas.run.RunConfig` (every field
optional) with an optional `name` and `tags`; studies are in `schemas.study`.
Controller documents are returned as the document's own JSON (evorobotics.document).
"""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, StringConstraints

from schemas.robots import RobotOut
from schemas.run import HeldOutScore, RunConfig, ValidationScore

TAG = r"^[A-Za-z0-9_.:=-]{1,64}$"
MAX_TAGS = 16


class RunCreate(RunConfig):
    """The body of `POST /api/runs`: the run's config plus how a person finds it again."""

    name: str | None = Field(None, min_length=1, max_length=128, description="free text")
    tags: list[Annotated[str, StringConstraints(pattern=TAG)]] = Field(
        default_factory=list, max_length=MAX_TAGS, description="e.g. `study:NAME`"
    )

    def run_config(self) -> RunConfig:
        """The pure RunConfig (what is stored and what the run is a function of)."""
        return RunConfig.model_validate(self.model_dump(exclude={"name", "tags"}))


RunStatus = Literal["queued", "running", "paused", "completed", "failed", "cancelled"]
TERMINAL: frozenset[str] = frozenset({"completed", "failed", "cancelled"})


class ChampionOut(BaseModel):
    """A completed run's champion: the controller it exports (`GET /api/runs/{id}/best`),
    chosen on its validation set, and its held-out test figures."""

    model_config = ConfigDict(frozen=True)

    sha256: str
    training_fitness: float | None = Field(
        description="its Eq 12 on its training trials of the run's last generation"
    )
    validation: ValidationScore | None = Field(
        description="how it was chosen; None when validation is off (it is training rank 0)"
    )
    test: HeldOutScore | None = Field(
        description="roaming and stuck on start poses never used to choose it, in the nominal "
        "world and under the reality gap; None when the run's config has no test"
    )


class RunOut(BaseModel):
    """A run as the API reports it. Its numbers keep three words apart: *training fitness*
    (Eq 12 on training trials), *best of generation g* (the fittest of one generation on
    training), and the *champion* (the controller a completed run exports, with its held-out
    test figures)."""

    model_config = ConfigDict(frozen=True)

    id: int
    status: RunStatus
    seed: int
    config: RunConfig
    generation: int = Field(description="generations committed so far (0..generations)")
    generations: int = Field(description="generations the run evolves in total")
    best_fitness: float | None = Field(
        description="training fitness of the best of the latest committed generation"
    )
    best_fitness_so_far: float | None = Field(
        None, description="the highest training fitness any committed generation's best reached"
    )
    trial_steps: int = Field(
        description="steps of each training trial: `config.steps`, or when that is None the "
        "steps `config.crossings` crossings of the maze take"
    )
    champion: ChampionOut | None = Field(
        None, description="a completed run's champion; None before the run completes"
    )
    evaluations: int = Field(description="controllers evaluated so far (each over `trials`)")
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
    error: str | None
    name: str | None = None
    tags: list[str] = Field(default_factory=list)
    study_id: int | None = Field(None, description="the study it belongs to, if any")
    condition: str | None = Field(None, description="its condition in that study")
    keeps_archive: bool = Field(
        False, description="its strategy keeps an archive of elites (GET /api/runs/{id}/archive)"
    )


class GenerationOut(BaseModel):
    """Fitness statistics of one committed generation."""

    model_config = ConfigDict(frozen=True)

    generation: int
    best: float
    mean: float
    worst: float
    nan_count: int = Field(description="evaluations that gave NaN (ranked last)")


class IndividualOut(BaseModel):
    """One evaluated controller of a generation; rank 0 is the fittest."""

    model_config = ConfigDict(frozen=True)

    rank: int
    index: int = Field(description="position in the population as evaluated")
    parent: int | None = Field(description="rank in the previous generation it descends from")
    fitness: float | None
    components: list[list[float]] = Field(
        description="per trial: curve length, net offset, max offset, stuck (Eq 12)"
    )
    sha256: str = Field(
        description="the controller's identity (docs/controller.md), as a push of this rank "
        "stores it; a completed run's champion (GET /api/runs/{id}/best) is the individual of "
        "its validation.training_rank"
    )


class IndividualsOut(BaseModel):
    model_config = ConfigDict(frozen=True)

    run_id: int
    generation: int
    individuals: list[IndividualOut]


class ArchiveCell(BaseModel):
    """One elite of a quality-diversity or novelty archive."""

    model_config = ConfigDict(frozen=True)

    descriptors: list[float]
    """Its values of the run's two archive axes (`strategy_settings.axes`), each in [0, 1]."""
    fitness: float | None
    """Eq 12 on training; None for a failed evaluation."""
    sha256: str
    """Its controller document's sha256."""


class ArchiveOut(BaseModel):
    """A run's archive after its committed generations (GET /api/runs/{id}/archive)."""

    model_config = ConfigDict(frozen=True)

    run_id: int
    generation: int
    """Generations the archive holds (0..generation - 1)."""
    axes: list[str]
    cells: list[ArchiveCell]


class WorkerOut(BaseModel):
    """A simulation worker as the server's dispatcher sees it (GET /api/workers)."""

    model_config = ConfigDict(frozen=True)

    name: str
    host: str
    state: Literal["idle", "busy", "gone"] = Field(description="gone: its liveliness vanished")
    jobs_done: int = Field(
        description="jobs accepted from it since the server started: one per generation of "
        "one slice of a population (a span of G generations counts G)"
    )
    evaluations: int = Field(
        0,
        description="controllers it evaluated whose fitness the server took (each over the "
        "run's trials); they add up to the runs' `evaluations`",
    )
    late: int = Field(
        0,
        description="evaluations it returned that the server dropped: a span's generations "
        "past the point where the server cut it, a slice whose lease had expired, a duplicate",
    )
    robot_steps_per_s: float | None = Field(description="its last measured speed")
    last_seen: datetime
    quarantined: bool = Field(
        False, description="it failed a spot-check: no more jobs while this server runs"
    )
    quarantine_reason: str | None = Field(
        None,
        description="the spot-check it failed: run, generation, individual, claimed and "
        "recomputed fitness",
    )


class JobCounts(BaseModel):
    model_config = ConfigDict(frozen=True)

    pending: int
    leased: int
    done: int


class ColonyOut(BaseModel):
    """Everything a status query needs in one response."""

    model_config = ConfigDict(frozen=True)

    runs: dict[str, int] = Field(description="number of runs in each status")
    active: list[RunOut] = Field(description="runs queued, running or paused")
    jobs: JobCounts
    workers: list[WorkerOut]
    robots: list[RobotOut] = Field(description="as GET /api/robots")


class HealthOut(BaseModel):
    """`ok`, or (with HTTP 503) `unhealthy` and the server loops that stopped, or `degraded`
    and why the store refuses writes."""

    status: Literal["ok", "degraded", "unhealthy"] = "ok"
    version: str
    stopped: list[str] = Field(default_factory=list, description="loops that no longer run")
    problems: list[str] = Field(
        default_factory=list, description="why the store refuses writes (runs paused meanwhile)"
    )


class ErrorOut(BaseModel):
    """Body of every error response (FastAPI's shape)."""

    detail: str
