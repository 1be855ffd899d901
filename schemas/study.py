"""A study: one base run config, named conditions that override it, and seeds (docs/studies.md).

Its runs are the conditions x seeds, each an ordinary run named `STUDY/CONDITION/SEED`.
`StudyCreate` validates every condition's config here, so a client (the CLI) and the server
refuse the same bodies with the same one-line messages; the server then checks its limits.
"""

from __future__ import annotations

import itertools
import json
import re
from datetime import datetime
from typing import Any

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)
from pydantic_core import PydanticCustomError

from schemas.run import RunConfig

STUDY_NAME = r"^[A-Za-z0-9_.-]{1,64}$"
CONDITION_NAME = r"^[A-Za-z0-9_.=,-]{1,64}$"
MAX_CONDITIONS = 100
MAX_SEEDS = 1000
MAX_STUDY_RUNS = 1000
"""conditions x seeds of one study: a study is created in one request and one transaction."""
BASE_CONDITION = "base"
"""The one condition of a study that gives neither conditions nor grid."""


def _refuse(message: str) -> PydanticCustomError:
    """An error whose message is exactly `message` (no "Value error, " prefix)."""
    return PydanticCustomError("study", "{message}", {"message": message})


def merge(base: dict[str, Any], overrides: dict[str, Any]) -> dict[str, Any]:
    """`base` with `overrides` applied; a dict value merges into the base's dict."""
    merged = dict(base)
    for key, value in overrides.items():
        if isinstance(value, dict) and isinstance(merged.get(key), dict):
            merged[key] = merge(merged[key], value)
        else:
            merged[key] = value
    return merged


def condition_config(base: RunConfig, name: str, overrides: dict[str, Any]) -> RunConfig:
    """The condition's RunConfig; ValueError `NAME: FIELD: problem` for the first bad field."""
    if "seed" in overrides:
        raise ValueError(f"{name}: seed: a study's runs take their seeds from `seeds`")
    try:
        return RunConfig.model_validate(merge(base.model_dump(mode="json"), overrides))
    except ValidationError as exc:
        error = exc.errors()[0]
        message = str(error["msg"]).removeprefix("Value error, ")
        field = ".".join(str(p) for p in error["loc"])
        raise ValueError(f"{name}: {field}: {message}" if field else f"{name}: {message}") from None


def _label(value: Any) -> str:
    return value if isinstance(value, str) else json.dumps(value)


def expand_grid(grid: dict[str, list[Any]]) -> dict[str, dict[str, Any]]:
    """Every combination of the grid's values, in the grid's order, named `f=v,g=w`; a
    dotted field (`ga.eta`) overrides a member of a nested config."""
    conditions: dict[str, dict[str, Any]] = {}
    fields = list(grid)
    for values in itertools.product(*(grid[f] for f in fields)):
        name = ",".join(f"{f}={_label(v)}" for f, v in zip(fields, values, strict=True))
        overrides: dict[str, Any] = {}
        for field, value in zip(fields, values, strict=True):
            *parents, leaf = field.split(".")
            node = overrides
            for part in parents:
                node = node.setdefault(part, {})
            node[leaf] = value
        conditions[name] = overrides
    return conditions


class StudyCreate(BaseModel):
    """The body of `POST /api/studies`: conditions x seeds runs of `base` with overrides."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    name: str = Field(pattern=STUDY_NAME, description="names its runs `NAME/CONDITION/SEED`")
    base: RunConfig = Field(
        default_factory=RunConfig, description="the run config every condition overrides"
    )
    conditions: dict[str, dict[str, Any]] = Field(
        default_factory=dict,
        description="condition name -> RunConfig fields it overrides (a dict merges into the "
        "base's); `seed` may not be overridden",
    )
    grid: dict[str, list[Any]] = Field(
        default_factory=dict,
        description="field (dotted for nested: `ga.eta`) -> values: one condition per "
        "combination, named `field=value` (`,`-joined for several fields)",
    )
    seeds: list[int] = Field(
        min_length=1, max_length=MAX_SEEDS, description="distinct seeds, each run's `seed`"
    )

    @field_validator("base")
    @classmethod
    def _base_seed(cls, base: RunConfig) -> RunConfig:
        if "seed" in base.model_fields_set:
            raise _refuse("seed: a study's runs take their seeds from `seeds`")
        return base

    @field_validator("conditions")
    @classmethod
    def _conditions(
        cls, conditions: dict[str, dict[str, Any]], info: ValidationInfo
    ) -> dict[str, dict[str, Any]]:
        if len(conditions) > MAX_CONDITIONS:
            raise _refuse(f"{len(conditions)} conditions exceed the limit of {MAX_CONDITIONS}")
        _check_conditions(conditions, info.data.get("base"))
        return conditions

    @field_validator("grid")
    @classmethod
    def _grid(cls, grid: dict[str, list[Any]], info: ValidationInfo) -> dict[str, list[Any]]:
        for field, values in grid.items():
            if not values:
                raise _refuse(f"{field}: no values")
            if any(isinstance(v, dict | list) or v is None for v in values):
                raise _refuse(f"{field}: values must be strings, numbers or booleans")
        size = 1
        for values in grid.values():
            size *= len(values)
        if size > MAX_CONDITIONS:
            raise _refuse(f"{size} combinations exceed the limit of {MAX_CONDITIONS} conditions")
        _check_conditions(expand_grid(grid), info.data.get("base"))
        return grid

    @field_validator("seeds")
    @classmethod
    def _seeds(cls, seeds: list[int]) -> list[int]:
        if any(not 0 <= s < 2**63 for s in seeds):
            raise _refuse("every seed must be >= 0 and < 2**63")
        if len(set(seeds)) != len(seeds):
            raise _refuse("seeds must be distinct")
        return seeds

    @model_validator(mode="after")
    def _size(self) -> StudyCreate:
        if self.conditions and self.grid:
            raise _refuse("give conditions or grid, not both")
        runs = len(self.expanded()) * len(self.seeds)
        if runs > MAX_STUDY_RUNS:
            raise _refuse(
                f"{len(self.expanded())} conditions x {len(self.seeds)} seeds = {runs} runs "
                f"exceed the limit of {MAX_STUDY_RUNS}"
            )
        return self

    def expanded(self) -> dict[str, dict[str, Any]]:
        """Condition name -> overrides, in order (the grid expanded; `base` alone if none)."""
        if self.grid:
            return expand_grid(self.grid)
        return dict(self.conditions) or {BASE_CONDITION: {}}

    def configs(self) -> dict[str, RunConfig]:
        """Condition name -> its RunConfig (seed still the base's: each run sets its own)."""
        return {
            name: condition_config(self.base, name, overrides)
            for name, overrides in self.expanded().items()
        }


def _check_conditions(conditions: dict[str, dict[str, Any]], base: RunConfig | None) -> None:
    for name, overrides in conditions.items():
        if not re.fullmatch(CONDITION_NAME, name):
            raise _refuse(f"{name!r}: a condition name must match {CONDITION_NAME}")
        if base is not None:
            try:
                condition_config(base, name, overrides)
            except ValueError as exc:
                raise _refuse(str(exc)) from None


class StudyRun(BaseModel):
    """One run of a study."""

    model_config = ConfigDict(frozen=True)

    run_id: int
    condition: str
    seed: int
    status: str
    name: str = Field(description="STUDY/CONDITION/SEED")
    metrics: dict[str, float | None] = Field(
        description="a completed run's final metrics (keys of evorobotics.stats.METRICS); "
        "None until known"
    )


class StudySummary(BaseModel):
    """One condition's statistics (each Summary as a dict: n, median, q1, q3, ci_low, ci_high)."""

    model_config = ConfigDict(frozen=True)

    condition: str
    runs: int
    completed: int
    generations: list[dict[str, Any]] = Field(
        description='[{"generation": g, "best": Summary, "mean": Summary}] over the '
        "condition's runs that reached g"
    )
    final: dict[str, dict[str, Any]] = Field(
        description="metric -> Summary over the completed runs that have it"
    )


class ComparisonOut(BaseModel):
    """Two conditions on one final metric: Mann-Whitney U and Vargha-Delaney A12."""

    model_config = ConfigDict(frozen=True)

    a: str
    b: str
    metric: str
    u: float
    p_value: float = Field(description="raw, two-sided")
    p_holm: float = Field(description="Holm-corrected over all of the study's comparisons")
    a12: float = Field(description="P(a > b) + 0.5 P(a == b)")


class StudyOut(BaseModel):
    """A study as the API reports it."""

    model_config = ConfigDict(frozen=True)

    id: int
    name: str
    status: str = Field(
        description="running | completed | cancelled | failed (a run failed, the others finished)"
    )
    created_at: datetime
    finished_at: datetime | None
    base: dict[str, Any]
    conditions: dict[str, dict[str, Any]] = Field(description="name -> overrides, in order")
    seeds: list[int]
    runs: list[StudyRun]
    summary: list[StudySummary] = Field(description="in condition order")
    comparisons: list[ComparisonOut]
    verdicts: list[str]
