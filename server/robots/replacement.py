"""What a stuck robot gets: the replacement policies, and the validated rankings of a run's
candidates that they choose from.

A stuck robot asks on KEY_REPLACE: the failure is recorded against the controller, and the
robot's policy (its own, else the colony's `RobotSettings.replacement`) chooses the reply.
`off`: none. `rank`: the run's validated champion, else the best of the validated ranking of
the run's candidates (`rank_in_world` in the run's world) that this robot has not
failed with in its last `recent_failures` stuck events (its current one included); none while
that ranking is computed (once per run and generation: as jobs workers take, sliced by
candidate, `Scheduler.rank`; the server's own evaluation only when no worker is live), for a
controller that came from no run, or when every candidate failed recently. `archive`: the
elite of that run's archive farthest in behaviour from the stuck controller's entry (the
fittest when it is not an elite), skipping recent failures; none when the run keeps no
archive. `fit`: the same ranking in the robot's calibrated world (`rank`'s choice meanwhile, or
for an uncalibrated robot). Without a replacement the agent's scripted escape carries on and
its controller resumes. Each stuck event keeps the policy that served it, and the next stuck
event of the robot fills in how many steps the previous one's outcome ran.
"""

from __future__ import annotations

import contextlib
import logging
import math
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future, InvalidStateError, ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from sqlalchemy import delete, select
from sqlalchemy.orm import Session, sessionmaker

from evorobotics.document import ControllerDocument, controller_sha256
from evorobotics.evaluate import DESCRIPTORS
from evorobotics.evolution import Ranked, StrategyHistory, rank_in_world, ranking_validation
from evorobotics.strategies import Archive
from schemas.robots import ReplacementPolicy, RobotCalibration, StuckRequest
from schemas.run import RunConfig
from schemas.world import World
from server.core.errors import NotFoundError, UnconfirmedError
from server.core.logs import context
from server.core.models import Controller, Robot, Run
from server.robots.settings import RobotSettings, effective_policy
from server.robots.store import RobotStateRow, StuckEventRow, field_row, serve, served
from server.runs import crud
from server.runs.evaluation import repeats_claim

log = logging.getLogger(__name__)

RANKINGS_KEPT = 32
RANKING_EVERY_S = 60.0
"""A robot's stuck requests start at most one new ranking this often (each is the workers'
simulation of up to 2 x `validation.candidates` candidates, leased before any run's jobs): a
robot rotating through many runs' champions cannot keep the workers from the runs."""
"""Validated rankings kept in memory, one per (robot calibration or none, run, generation)."""

Ranker = Callable[[RunConfig, World, np.ndarray], "Future[Ranked]"]
"""`rank_in_world(config, genomes, world)` asked of the scheduler (`Scheduler.rank`): its
jobs go to the workers."""


@dataclass(frozen=True)
class Candidate:
    """One of a run's candidates as the server itself scored it."""

    sha256: str
    rank: int | None
    """Its training rank in the run's latest generation, or None for an archive elite."""
    elite: int | None
    """Its entry in the run's archive, or None for a training rank."""
    roaming: float
    score: float


@dataclass(frozen=True)
class Ranking:
    """A run's candidates ranked by the server's own validation, best first: in a robot's
    calibrated world (`fit`), or with `robot` None in the run's world (`rank`)."""

    robot: str | None
    run_id: int
    poses: int
    steps: int
    candidates: tuple[Candidate, ...]

    @property
    def world(self) -> str:
        return "the run's world" if self.robot is None else f"robot {self.robot}'s calibrated world"

    def reason(self, c: Candidate) -> str:
        which = f"rank {c.rank}" if c.elite is None else f"elite {c.elite}"
        return (
            f"{which} of run {self.run_id}, roaming on {100 * c.roaming:.0f} % of {self.poses} "
            f"validation trials of {self.steps} steps in {self.world}"
        )


class Replacements:
    """Answers stuck robots (on the robot service's thread) and gives pushes a run's elites
    and rankings (from any thread); rankings are asked of `rank` (None: computed here) from
    a thread of their own until `close()`."""

    def __init__(
        self,
        sessions: sessionmaker[Session],
        settings: RobotSettings,
        archives: Callable[[int], tuple[int, RunConfig, Archive]] | None,
        rank: Ranker | None = None,
    ) -> None:
        self._sessions = sessions
        self._settings = settings
        self._archives = archives
        """run id -> (generations, config, archive) of a QD run (`RunManager.archive`)."""
        self._rank_jobs = rank
        self._lock = threading.RLock()  # a ranking failed under it resolves (`_resolved`)
        self._ranker = ThreadPoolExecutor(1, thread_name_prefix="fit-ranking")
        """Gathers and waits for rankings for the `rank` and `fit` policies off the service
        thread."""
        self._rankings: dict[tuple[str, str, int, int], Future[Ranking]] = {}
        self._started: dict[str, float] = {}
        """Robot -> when its stuck requests last started a new ranking (RANKING_EVERY_S)."""
        self._unresolved: set[Future[Ranking]] = set()
        """Every ranking not yet resolved, kept or not: `close` fails them."""

    def close(self) -> None:
        """Drop the rankings not yet started (one being computed finishes on its own): each
        fails, so no one waits for it."""
        self._ranker.shutdown(wait=False, cancel_futures=True)
        with self._lock:
            unresolved = list(self._unresolved)
        for future in unresolved:
            _fail(future, RuntimeError("the server is stopping"))

    def elite(
        self, run_id: int, elite: int, *, confirm: bool = False
    ) -> tuple[int, ControllerDocument]:
        """(generation, document) of entry `elite` of the run's archive; with `confirm`, only
        if the server's own evaluation repeats its archived claim (`_elite_holds`), else
        UnconfirmedError."""
        if self._archives is None:
            raise NotFoundError("this server keeps no archives")
        generations, config, archive = self._archives(run_id)
        document = _elite_document(run_id, generations, config, archive, elite)
        if confirm:
            with self._sessions() as db:
                history = crud.history(db, run_id=run_id, generations=generations)
            if not _elite_holds(config, history, archive, elite):
                raise UnconfirmedError(
                    f"run {run_id}'s elite {elite}: its archived fitness and descriptors are "
                    "not what the server's own evaluation gives; not served"
                )
        return generations - 1, document

    def replace(self, request: StuckRequest) -> tuple[ControllerDocument | None, str]:
        """Record the robot's stuck event and choose its reply under its policy: (the
        controller or None, why)."""
        with self._sessions.begin() as db:
            robot = db.get(Robot, request.robot)
            policy, _ = effective_policy(
                robot.replacement if robot else None, self._settings.replacement
            )
            state = db.get(RobotStateRow, request.robot)
            if state is None:
                state = RobotStateRow(
                    robot_id=request.robot, state="escaping", stuck_events=0, boot=0
                )
                db.add(state)
            _close_previous(db, request, state.boot)
            event = StuckEventRow(
                robot_id=request.robot,
                controller_sha256=request.sha256,
                reason=request.reason,
                step=request.step,
                policy=policy,
                boot=state.boot,
            )
            db.add(event)
            _trim_events(db, request.robot, self._settings.stuck_retention)
            state.stuck_events += 1
            if request.sha256 is not None and request.sha256 in served(robot):
                field_row(db, request.sha256).stuck_events += 1
            db.flush()
            doc, reason = self._pick(db, request, policy)
            event.replacement_sha256 = doc.sha256 if doc else None
            event.answer = reason
            if doc is not None and robot is not None:
                serve(robot, doc.sha256)
        context(log, robot=request.robot).info(
            "robot %s stuck at step %d (%s) with %s; policy %s, replacement %s: %s",
            request.robot,
            request.step,
            request.reason,
            request.sha256,
            policy,
            doc.sha256 if doc else None,
            reason,
        )
        return doc, reason

    def _pick(
        self, db: Session, request: StuckRequest, policy: ReplacementPolicy
    ) -> tuple[ControllerDocument | None, str]:
        """The reply to a stuck request under `policy` (one branch per policy), with its reason."""
        if policy == "off":
            return None, "replacement is off for this robot"
        failed = db.get(Controller, request.sha256) if request.sha256 else None
        if failed is None or failed.run_id is None:
            return None, "the failed controller comes from no stored run"
        recent = set(
            db.scalars(
                select(StuckEventRow.controller_sha256)
                .where(StuckEventRow.robot_id == request.robot)
                .order_by(StuckEventRow.id.desc())
                .limit(self._settings.recent_failures)
            )
        )
        if policy == "archive":
            return self._pick_elite(db, failed.run_id, request.sha256, recent)
        if policy == "fit":
            try:
                ranking = self.ranking(
                    db, failed.run_id, request.robot, wait=False, asker=request.robot
                )
            except NotFoundError as exc:
                doc, reason = self._pick_rank(db, failed.run_id, recent, request.robot)
                return doc, f"{exc}; {reason}"
            if ranking is not None:
                return self._pick_ranked(db, ranking, recent)
            doc, reason = self._pick_rank(db, failed.run_id, recent, request.robot)
            return doc, f"the fit ranking is being computed; {reason}"
        return self._pick_rank(db, failed.run_id, recent, request.robot)

    def _pick_rank(
        self, db: Session, run_id: int, recent: set[str | None], asker: str
    ) -> tuple[ControllerDocument | None, str]:
        """The run's validated champion, else the best of the validated ranking of its
        candidates that did not fail recently (none while that is being computed): nothing
        served rests on a worker's claimed training fitness."""
        run = db.get(Run, run_id)
        best = None if run is None else crud.champion(db, run=run)
        if best is not None and best.sha256 not in recent:  # chosen on unseen poses, tested
            return ControllerDocument.from_json(best.document), (
                f"the validated champion of run {run_id}"
            )
        try:
            ranking = self.ranking(db, run_id, None, wait=False, asker=asker)
        except NotFoundError as exc:
            return None, str(exc)
        if ranking is None:
            return None, f"run {run_id}'s candidates are being validated: ask again"
        return self._pick_ranked(db, ranking, recent)

    def _pick_ranked(
        self, db: Session, ranking: Ranking, recent: set[str | None]
    ) -> tuple[ControllerDocument | None, str]:
        """The ranking's first candidate that did not fail recently on this robot."""
        for candidate in ranking.candidates:
            if candidate.sha256 not in recent:
                return self.candidate_document(db, ranking, candidate), ranking.reason(candidate)
        return None, f"every candidate of run {ranking.run_id} failed recently on this robot"

    def candidate_document(
        self, db: Session, ranking: Ranking, candidate: Candidate
    ) -> ControllerDocument:
        """The candidate's document, stored: the champion's own (with its validation and test)
        when it is the champion."""
        run = db.get(Run, ranking.run_id)
        best = None if run is None else crud.champion(db, run=run)
        if best is not None and best.sha256 == candidate.sha256:
            return ControllerDocument.from_json(best.document)
        if candidate.elite is None:
            return ranked_document(db, ranking.run_id, candidate.rank or 0)
        generations, doc = self.elite(ranking.run_id, candidate.elite)
        if doc.sha256 != candidate.sha256:  # the archive moved on since the ranking
            raise NotFoundError(f"run {ranking.run_id}'s archive changed: ask again")
        return stored_document(db, ranking.run_id, generations, doc)

    def ranking(
        self,
        db: Session,
        run_id: int,
        robot_id: str | None,
        *,
        wait: bool,
        asker: str | None = None,
    ) -> Ranking | None:
        """The run's candidates ranked by validation, in the robot's calibrated world or
        (robot None) the run's, computed once per calibration and committed generation
        (waited for on the ranking thread); None while it is being computed unless `wait`.
        NotFoundError: no robot, no calibration, no run, no generation, or robot `asker`
        started a new ranking less than RANKING_EVERY_S ago."""
        calibration, calibrated = None, ""
        if robot_id is not None:
            robot = db.get(Robot, robot_id)
            if robot is None:
                raise NotFoundError(f"no robot with id {robot_id}")
            if robot.calibration is None or robot.calibrated_at is None:
                raise NotFoundError(f"robot {robot_id} has no calibration (colony robot calibrate)")
            calibration = RobotCalibration.model_validate_json(robot.calibration)
            calibrated = robot.calibrated_at.isoformat()
        if db.get(Run, run_id) is None:
            raise NotFoundError(f"no run with id {run_id}")
        latest = crud.latest_generation(db, run_id=run_id)
        if latest is None:
            raise NotFoundError(f"run {run_id} has no completed generation yet")
        key = (robot_id or "", calibrated, run_id, latest.generation)
        with self._lock:
            future = self._rankings.get(key)
            if future is None:
                if asker is not None:
                    now, last = time.monotonic(), self._started.get(asker, -math.inf)
                    if now - last < RANKING_EVERY_S:
                        raise NotFoundError(
                            f"robot {asker} started a ranking {now - last:.0f} s ago (one a "
                            f"minute at most): ask again later"
                        )
                    self._started[asker] = now
                future = self._rankings[key] = Future()
                self._unresolved.add(future)
                future.add_done_callback(self._resolved)
                while len(self._rankings) > RANKINGS_KEPT:
                    self._rankings.pop(next(iter(self._rankings)))
                try:
                    self._ranker.submit(
                        self._rank, future, robot_id, run_id, latest.generation, calibration
                    )
                except RuntimeError as exc:  # closed
                    _fail(future, exc)
        if not wait and not future.done():
            return None
        try:
            return future.result()
        except Exception as exc:  # asked anew next time
            with self._lock:
                if self._rankings.get(key) is future:
                    del self._rankings[key]
            raise NotFoundError(
                f"run {run_id}'s candidates could not be ranked ({exc}): ask again"
            ) from exc

    def _resolved(self, future: Future[Ranking]) -> None:
        with self._lock:
            self._unresolved.discard(future)

    def _rank(
        self,
        ranking: Future[Ranking],
        robot_id: str | None,
        run_id: int,
        generation: int,
        calibration: RobotCalibration | None,
    ) -> None:
        """Resolve `ranking`: score the run's candidates on its validation poses in the
        robot's calibrated world, or without one the run's world (no reality gap either way):
        its `validation.candidates` fittest training ranks of `generation` and as many of its
        archive's fittest elites; best first by roaming, then mean Eq 12, then candidate order.
        The scores are `rank`'s jobs, which this thread does not wait for: one ranking's
        workers never hold up another's."""
        try:
            config, world, top, labels = self._candidates(run_id, generation, calibration)
            if self._rank_jobs is None:
                ranked = rank_in_world(config, top, world)
                ranking.set_result(_ranking(robot_id, run_id, config, top, labels, ranked))
                return
            scoring = self._rank_jobs(config, world, top)
        except Exception as exc:
            log.exception("run %d's candidates could not be ranked", run_id)
            _fail(ranking, exc)
            return

        def scored(done: Future[Ranked]) -> None:
            try:
                ranking.set_result(_ranking(robot_id, run_id, config, top, labels, done.result()))
            except Exception as exc:
                log.warning("run %d's candidates could not be ranked: %s", run_id, exc)
                _fail(ranking, exc)

        scoring.add_done_callback(scored)

    def _candidates(
        self, run_id: int, generation: int, calibration: RobotCalibration | None
    ) -> tuple[RunConfig, World, np.ndarray, list[tuple[int | None, int | None]]]:
        """(config, world, genomes, (training rank, elite) of each) of the ranking `_rank`
        scores."""
        with self._sessions() as db:
            run = db.get(Run, run_id)
            assert run is not None  # checked by the caller; runs are never deleted under it
            config = RunConfig.model_validate_json(run.config)
            _, genomes = crud.ranked(db, run_id=run_id, generation=generation)
        v = ranking_validation(config)
        top = np.asarray(genomes[: v.candidates])
        labels: list[tuple[int | None, int | None]] = [(r, None) for r in range(len(top))]
        if self._archives is not None:
            try:
                _, _, archive = self._archives(run_id)
            except NotFoundError:
                pass  # a strategy without an archive
            else:
                fittest = np.argsort(-np.nan_to_num(archive.fitness, nan=-np.inf), kind="stable")
                elites = [int(k) for k in fittest[: v.candidates]]
                top = np.concatenate([top, archive.genomes[elites]])
                labels += [(None, k) for k in elites]
        world = config.world if calibration is None else calibration.world(config.world)
        return config, world, top, labels

    def _pick_elite(
        self, db: Session, run_id: int, failed: str | None, recent: set[str | None]
    ) -> tuple[ControllerDocument | None, str]:
        """The elite of the run's archive farthest, in its descriptors, from the failed
        controller's entry (the fittest first when the failed one is not in the archive),
        skipping those that failed recently on this robot and those whose archived claim the
        server's own evaluation does not repeat (`_elite_holds`, logged): an archive is made of
        workers' claims, so no forged fitness or descriptor alone chooses what is served."""
        try:
            if self._archives is None:
                raise NotFoundError("this server keeps no archives")
            generations, config, archive = self._archives(run_id)
        except NotFoundError as exc:
            return None, str(exc)
        history = crud.history(db, run_id=run_id, generations=generations)
        spec = config.network_spec
        shas = [controller_sha256(spec, genome) for genome in archive.genomes]
        if failed in shas:
            origin = archive.descriptors[shas.index(failed)]
            order = np.argsort(-np.linalg.norm(archive.descriptors - origin, axis=1), kind="stable")
            why = "farthest in behaviour"
        else:
            order = np.argsort(-np.nan_to_num(archive.fitness, nan=-np.inf), kind="stable")
            why = "fittest (the stuck controller is not in it)"
        for k in (int(i) for i in order):
            if shas[k] in recent:
                continue
            if not _elite_holds(config, history, archive, k):
                log.warning(
                    "run %d elite %d: its archived fitness and descriptors are not what the "
                    "server's own evaluation gives; not served",
                    run_id,
                    k,
                )
                continue
            doc = _elite_document(run_id, generations, config, archive, k)
            reason = f"elite {k} of run {run_id}'s archive, {why}"
            return stored_document(db, run_id, generations - 1, doc), reason
        return None, (
            f"every elite of run {run_id}'s archive failed recently on this robot or rests on a "
            "claim the server's own evaluation does not repeat"
        )


def _elite_document(
    run_id: int, generation: int, config: RunConfig, archive: Archive, elite: int
) -> ControllerDocument:
    """The controller of entry `elite` of a run's archive after `generation` generations."""
    if not 0 <= elite < len(archive.fitness):
        raise NotFoundError(
            f"run {run_id}'s archive has {len(archive.fitness)} entries, not {elite + 1}"
        )
    value = float(archive.fitness[elite])
    return ControllerDocument(
        spec=config.network_spec,
        weights=np.array(archive.genomes[elite], dtype=np.float64),
        fitness=value if np.isfinite(value) else None,
        provenance={
            "seed": config.seed,
            "generation": generation - 1,
            "elite": elite,
            "run": run_id,
        },
        world=config.world,
    )


def ranked_document(db: Session, run_id: int, rank: int) -> ControllerDocument:
    """The controller of rank `rank` in the run's latest generation, stored in `controllers`."""
    run = db.get(Run, run_id)
    latest = crud.latest_generation(db, run_id=run_id)
    if run is None or latest is None:
        raise NotFoundError(f"run {run_id} has no completed generation yet")
    found, genomes = crud.ranked(db, run_id=run_id, generation=latest.generation, rank=rank)
    config = RunConfig.model_validate_json(run.config)
    doc = ControllerDocument(
        spec=config.network_spec,
        weights=genomes[0],
        fitness=found.fitness_of(rank),
        provenance={
            "seed": config.seed,
            "generation": latest.generation,
            "rank": rank,
            "run": run_id,
        },
        world=config.world,
    )
    return stored_document(db, run_id, latest.generation, doc)


def stored_document(
    db: Session, run_id: int, generation: int, doc: ControllerDocument
) -> ControllerDocument:
    """`doc`, a controller of the run's `generation`, stored in `controllers` (once)."""
    crud.put_controller(
        db,
        sha256=doc.sha256,
        document=doc.to_json(),
        run_id=run_id,
        generation=generation,
        fitness=doc.fitness,
    )
    return doc


def _elite_holds(config: RunConfig, history: StrategyHistory, archive: Archive, elite: int) -> bool:
    """Whether the server's own evaluation of entry `elite`, in a generation that was told its
    archived fitness and descriptors, repeats them bit for bit (`repeats_claim`; usually one
    evaluation of one controller)."""
    axes = [DESCRIPTORS.index(a) for a in config.strategy_settings.axes]
    fitness, descriptors = archive.fitness[elite], archive.descriptors[elite]
    told = (_bits(history.fitness) == _bits(fitness)) & (
        _bits(history.descriptors[..., axes]) == _bits(descriptors)
    ).all(axis=-1)
    return any(
        repeats_claim(config, g, archive.genomes[elite], float(fitness), (axes, descriptors))
        for g in sorted({int(g) for g in np.nonzero(told)[0]})
    )


def _bits(values: np.ndarray) -> np.ndarray:
    """float64 values as their bits, so equal means identical (NaN too)."""
    return np.ascontiguousarray(values, dtype="<f8").view("<u8")


def _close_previous(db: Session, request: StuckRequest, boot: int) -> None:
    """Fill in the steps the robot's previous stuck event's outcome ran, if `request` shows the
    robot was still running it (the replacement sent, or without one the same controller) in the
    same boot, whose step counter both share."""
    previous = db.scalars(
        select(StuckEventRow)
        .where(StuckEventRow.robot_id == request.robot)
        .order_by(StuckEventRow.id.desc())
        .limit(1)
    ).first()
    if previous is None or previous.steps_run is not None or previous.boot != boot:
        return
    ran = previous.replacement_sha256 or previous.controller_sha256
    if ran is not None and ran == request.sha256 and request.step > previous.step:
        previous.steps_run = request.step - previous.step


def _trim_events(db: Session, robot: str, keep: int) -> None:
    """Delete the robot's stuck events older than its newest `keep` (the one being added
    included)."""
    cutoff = db.scalar(
        select(StuckEventRow.id)
        .where(StuckEventRow.robot_id == robot)
        .order_by(StuckEventRow.id.desc())
        .offset(keep - 1)
        .limit(1)
    )
    if cutoff is not None:
        db.execute(
            delete(StuckEventRow).where(StuckEventRow.robot_id == robot, StuckEventRow.id < cutoff)
        )


def _ranking(
    robot_id: str | None,
    run_id: int,
    config: RunConfig,
    top: np.ndarray,
    labels: list[tuple[int | None, int | None]],
    ranked: Ranked,
) -> Ranking:
    """The candidates `top` (labelled (training rank, elite)) in `ranked`'s order, each
    controller once."""
    order, scored = ranked
    v = ranking_validation(config)
    seen: set[str] = set()
    candidates = []
    for k in (int(i) for i in order):
        sha = controller_sha256(config.network_spec, top[k])
        if sha not in seen:
            seen.add(sha)
            rank, elite = labels[k]
            roaming, score = float(scored.roaming[k]), float(scored.score[k])
            candidates.append(Candidate(sha, rank, elite, roaming, score))
    ranking = Ranking(robot_id, run_id, v.poses, v.steps, tuple(candidates))
    log.info(
        "run %d's %d candidates validated in %s; the best roams %.0f %%",
        run_id, len(candidates), ranking.world, 100 * candidates[0].roaming,
    )  # fmt: skip
    return ranking


def _fail(future: Future[Ranking], exc: BaseException) -> None:
    """Fail `future` unless it is resolved already."""
    with contextlib.suppress(InvalidStateError):
        future.set_exception(exc)
