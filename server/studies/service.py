"""Studies: create their runs, report their status and statistics (docs/studies.md).

A study's runs are ordinary runs (`RunManager.create_study`), so the scheduler serves them
fairly with every other run. Its statistics are computed on read from the store and kept
while its runs' states stay the same: a GET while nothing changed costs one query. Summaries
of a generation whose values did not change are reused, so a GET while runs evolve summarises
only the new generations.

A completed run's metrics come from its champion: `validation_score` from the document's
`validation` member, `gap_roaming` and `gap_stuck` from its held-out `test` under the reality
gap; `roaming`, `stuck` (by the report's horizon), `max_offset` and `coverage`
from its exploration report on unseen start poses at `colony evaluate`'s defaults (not from
the validation poses: the champion was chosen on those, so they flatter it)
(`server.studies.evaluation`, the cache that serves `GET /api/controllers/{sha}/evaluation`).
A report costs about a second of one core: the first read that finds the run completed asks
the scheduler for it, as jobs that workers take, and until it is known those metrics are None.
"""

from __future__ import annotations

import json
import logging
import math
import threading
import time
from collections.abc import Hashable, Sequence
from concurrent.futures import Future
from dataclasses import asdict, dataclass
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session

from evorobotics.errors import EvoError
from evorobotics.stats import METRICS, Summary, compare, summarize, verdicts
from schemas.study import ComparisonOut, StudyCreate, StudyOut, StudyRun, StudySummary
from server.core.auth import run_limit_error
from server.core.errors import NotFoundError, ServerError
from server.core.models import Controller, Generation, Study, aware
from server.runs import crud
from server.runs.lifecycle import RunManager
from server.studies.evaluation import Evaluations, Params

log = logging.getLogger(__name__)

CURVE_POINTS = 64
"""Generations per condition's fitness curve: enough for a plot, few enough bootstraps that
a GET of a 60-run paper study stays fast."""
CURVES_REFRESH_S = 5.0
"""While a study runs, its fitness curves are recomputed at most this often (every run's new
generations change most points); its status, runs and final statistics are always current."""
EXPLORATION = Params()
"""`colony evaluate`'s defaults: 1000 unseen poses x 1000 steps in the paper maze."""


class StudyRefusedError(ServerError):
    """A study body the server will not run: a condition beyond its limits (HTTP 422)."""

    status_code = 422


class StudyConflictError(ServerError):
    """A study of that name exists (its runs' names and tag would be ambiguous; HTTP 409)."""

    status_code = 409


_Summaries = dict[tuple[str, str], tuple[tuple[float, ...], Summary]]
"""(condition, what) -> the values last summarised and their Summary."""


def _summarize(known: _Summaries, key: tuple[str, str], values: tuple[float, ...]) -> Summary:
    """`summarize(values)`, reused while the values stay the same (a bootstrap costs
    milliseconds, mostly scipy's overhead, and a study has hundreds)."""
    found = known.get(key)
    if found is None or found[0] != values:
        found = (values, summarize(values))
        known[key] = found
    return found[1]


@dataclass(frozen=True)
class _RunState:
    id: int
    condition: str
    seed: int
    status: str
    name: str
    champion: str | None


@dataclass
class _Cached:
    key: Hashable
    out: StudyOut
    summaries: _Summaries
    curves_at: float
    """When its fitness curves were computed (time.monotonic)."""


def _finite(x: Any) -> float | None:
    return float(x) if isinstance(x, int | float) and math.isfinite(x) else None


def _summary_dict(summary: Summary) -> dict[str, Any]:
    return {k: _finite(v) if isinstance(v, float) else v for k, v in asdict(summary).items()}


class StudyService:
    """Creates, reads, cancels and deletes studies through the run manager."""

    def __init__(self, manager: RunManager, evaluations: Evaluations) -> None:
        self.manager = manager
        self.evaluations = evaluations
        self._lock = threading.Lock()
        self._cache: dict[int, _Cached] = {}
        self._asked: set[str] = set()
        """Documents whose report is being computed, or failed (never asked again)."""

    # lifecycle ---------------------------------------------------------------------------

    def create(self, body: StudyCreate) -> int:
        """Check every condition against the server's limits, then store the study and queue
        its runs (condition by condition, seed by seed); its id."""
        settings = self.manager.settings
        configs = body.configs()
        for condition, config in configs.items():
            refused = run_limit_error(
                config,
                max_population_weights=settings.max_population_weights,
                max_generation_steps=settings.max_generation_steps,
                max_run_steps=settings.max_run_steps,
            )
            if refused is not None:
                raise StudyRefusedError(f"conditions.{condition}: {refused}")
        with self.manager.sessions() as session:
            taken = session.scalar(select(Study.id).where(Study.name == body.name).limit(1))
        if taken is not None:
            raise StudyConflictError(f"study {taken} is named {body.name!r}; pick another name")
        spec = {
            "base": body.base.model_dump(mode="json"),
            "conditions": body.expanded(),
            "seeds": body.seeds,
        }
        runs = [
            (config.model_copy(update={"seed": seed}), f"{body.name}/{condition}/{seed}", condition)
            for condition, config in configs.items()
            for seed in body.seeds
        ]
        study_id, _ = self.manager.create_study(name=body.name, spec=json.dumps(spec), runs=runs)
        return study_id

    def cancel(self, study_id: int) -> StudyOut:
        self.manager.cancel_study(study_id)
        return self.get(study_id)

    def delete(self, study_id: int) -> None:
        self.manager.delete_study(study_id)
        with self._lock:
            self._cache.pop(study_id, None)

    # reads --------------------------------------------------------------------------------

    def get(self, study_id: int) -> StudyOut:
        with self.manager.sessions() as session:
            study = crud.get_study(session, study_id=study_id)
            if study is None:
                raise NotFoundError(f"no study with id {study_id}")
            return self._out(session, study)

    def all(self) -> list[StudyOut]:
        """Newest first."""
        with self.manager.sessions() as session:
            return [self._out(session, s) for s in crud.list_studies(session)]

    def _out(self, session: Session, study: Study) -> StudyOut:
        rows = crud.study_runs(session, study_id=study.id)
        runs = [
            _RunState(r.id, r.condition or "", r.seed, r.status, r.name or "", r.champion_sha256)
            for r in rows
        ]
        documents = self._documents(session, runs)
        known = tuple(
            sorted(s for s, d in documents.items() if self.evaluations.peek(d, EXPLORATION))
        )
        progress = tuple((r.id, r.status, r.generation) for r in rows)
        key = (study.status, study.finished_at, progress, tuple(r.champion for r in runs), known)
        with self._lock:
            cached = self._cache.get(study.id)
        if cached is not None and cached.key == key:
            return cached.out
        now = time.monotonic()
        summaries = cached.summaries if cached is not None else {}
        curves = None
        fresh = cached is not None and now - cached.curves_at < CURVES_REFRESH_S
        if cached is not None and fresh and study.status == "running":
            curves = {s.condition: s.generations for s in cached.out.summary}
        out = self._compute(session, study, runs, documents, summaries, curves)
        with self._lock:
            at = now if curves is None or cached is None else cached.curves_at
            self._cache[study.id] = _Cached(key, out, summaries, at)
        return out

    def _documents(self, session: Session, runs: Sequence[_RunState]) -> dict[str, str]:
        """Champion sha256 -> its document text, for the completed runs (one query)."""
        shas = {r.champion for r in runs if r.champion is not None}
        if not shas:
            return {}
        query = select(Controller.sha256, Controller.document).where(
            Controller.sha256.in_(sorted(shas))
        )
        return {sha: document for sha, document in session.execute(query)}

    def _compute(
        self,
        session: Session,
        study: Study,
        runs: list[_RunState],
        documents: dict[str, str],
        summaries: _Summaries,
        curves: dict[str, list[dict[str, Any]]] | None = None,
    ) -> StudyOut:
        """The study from its runs' state; `curves` (condition -> generations) are reused
        instead of computed when given."""
        spec = json.loads(study.spec)
        conditions: dict[str, dict[str, Any]] = spec["conditions"]
        history: dict[int, list[tuple[int, float, float]]] = {r.id: [] for r in runs}
        query = (
            select(Generation.run_id, Generation.generation, Generation.best, Generation.mean)
            .where(Generation.run_id.in_([r.id for r in runs]))
            .order_by(Generation.run_id, Generation.generation)
        )
        for run_id, g, best, mean in session.execute(query):
            history[run_id].append((g, best, mean))
        metrics = {
            r.id: self._metrics(r, history[r.id], documents)
            for r in runs
            if r.status == "completed"
        }
        summary = []
        samples: dict[str, dict[str, list[float]]] = {}
        for condition in conditions:
            mine = [r for r in runs if r.condition == condition]
            finals = {
                m: [v for r in mine if (v := metrics.get(r.id, {}).get(m)) is not None]
                for m in METRICS
            }
            samples[condition] = {m: values for m, values in finals.items() if values}
            summary.append(
                StudySummary(
                    condition=condition,
                    runs=len(mine),
                    completed=sum(r.status == "completed" for r in mine),
                    generations=curves[condition]
                    if curves is not None and condition in curves
                    else self._curves(condition, [history[r.id] for r in mine], summaries),
                    final={
                        m: _summary_dict(_summarize(summaries, (condition, m), tuple(values)))
                        for m, values in samples[condition].items()
                    },
                )
            )
        comparisons = compare(samples)
        created = aware(study.created_at)
        if created is None:
            raise ValueError(f"study {study.id} has no creation time")
        return StudyOut(
            id=study.id,
            name=study.name,
            status=study.status,
            created_at=created,
            finished_at=aware(study.finished_at),
            base=spec["base"],
            conditions=conditions,
            seeds=spec["seeds"],
            runs=[
                StudyRun(
                    run_id=r.id,
                    condition=r.condition,
                    seed=r.seed,
                    status=r.status,
                    name=r.name,
                    metrics=metrics.get(r.id, dict.fromkeys(METRICS)),
                )
                for r in runs
            ],
            summary=summary,
            comparisons=[
                ComparisonOut(
                    a=c.a,
                    b=c.b,
                    metric=c.metric,
                    u=c.u,
                    p_value=c.p_value,
                    p_holm=c.p_holm,
                    a12=c.a12,
                )
                for c in comparisons
            ],
            verdicts=verdicts(comparisons),
        )

    def _curves(
        self, condition: str, histories: list[list[tuple[int, float, float]]], known: _Summaries
    ) -> list[dict[str, Any]]:
        """At most about CURVE_POINTS evenly spaced generations (the first and the last
        included): the Summary of best and of mean fitness over the runs that reached each."""
        reached = max((len(h) for h in histories), default=0)
        stride = max(1, math.ceil(reached / CURVE_POINTS))
        points = sorted({*range(0, reached, stride), reached - 1} - {-1})
        curves = []
        for g in points:
            row: dict[str, Any] = {"generation": g}
            for column, kind in ((1, "best"), (2, "mean")):
                values = tuple(h[g][column] for h in histories if len(h) > g)
                row[kind] = _summary_dict(_summarize(known, (condition, f"{kind}@{g}"), values))
            curves.append(row)
        return curves

    def _metrics(
        self, run: _RunState, history: list[tuple[int, float, float]], documents: dict[str, str]
    ) -> dict[str, float | None]:
        """A completed run's final metrics; the exploration's are queued when unknown."""
        found: dict[str, float | None] = dict.fromkeys(METRICS)
        if history:
            found["best_fitness"] = _finite(history[-1][1])
        document = documents.get(run.champion or "")
        if document is None:
            return found
        validation = json.loads(document).get("validation")
        if validation is not None:
            found["validation_score"] = _finite(validation["score"])
        test = json.loads(document).get("test")
        if test is not None:
            found["gap_roaming"] = _finite(test["gap"]["roaming"]["value"])
            found["gap_stuck"] = _finite(test["gap"]["stuck"]["value"])
        report = self.evaluations.peek(document, EXPLORATION)
        if report is None:
            self._ask(document)
        else:
            exploration = json.loads(report)
            found["roaming"] = _finite(exploration["roaming"])
            found["stuck"] = _finite(exploration["stuck"][str(EXPLORATION.steps)])
            found["max_offset"] = _finite(exploration["max_offset"][str(EXPLORATION.steps)])
            found["coverage"] = _finite(exploration["coverage"])
        return found

    # exploration by jobs ----------------------------------------------------------------

    def _ask(self, document: str) -> None:
        """Ask for a champion's exploration report, once (`Evaluations.request`)."""
        with self._lock:
            if document in self._asked:
                return
            self._asked.add(document)
        try:
            asked = self.evaluations.request(document, EXPLORATION)
        except (EvoError, ValueError) as exc:  # its metrics stay None, as it stays asked
            log.warning("study champion exploration refused: %s", exc)
            return
        asked.add_done_callback(lambda future: self._explored(document, future))

    def _explored(self, document: str, future: Future[str]) -> None:
        """A report is known (the next read shows it), or failed (its metrics stay None)."""
        if future.exception() is not None:
            log.warning("study champion exploration failed: %s", future.exception())
            return
        with self._lock:
            self._asked.discard(document)
