"""The robot side of the server: registry, traces, pushes, replacements and the replay check.

`RobotService` lives on the server's one zenoh session (router mode). Zenoh callbacks only
enqueue; one service thread stores traces, answers replacement requests, tracks liveliness and
resolves push acknowledgements, so the database sees one writer from here.

Replacement (a stuck robot asks on KEY_REPLACE): the failure is recorded against the
controller, and the robot's policy (its own, else the colony's `RobotSettings.replacement`)
chooses the reply. `off`: none. `rank`: the run's validated champion, else the best of the
server's own validated ranking of the run's candidates (`rank_in_world` in the run's world)
that this robot has not failed with in its last `recent_failures` stuck events (its current
one included); none while that ranking is computed (on a thread of its own, once per run and
generation), for a controller that came from no run, or when every candidate failed
recently. `archive`: the elite of that run's archive farthest in behaviour from the stuck
controller's entry (the fittest when it is not an elite), skipping recent failures; none when
the run keeps no archive. `fit`: the same ranking in the robot's calibrated world (`rank`'s
choice meanwhile, or for an uncalibrated robot). Without a replacement
the agent's scripted escape carries on and its controller resumes. Each stuck event keeps the policy that served it,
and the next stuck event of the robot fills in how many steps the previous one's outcome ran.

Trace batches are checked and stored by `traces.TraceIngest`.
"""

from __future__ import annotations

import json
import logging
import queue
import threading
import time
import uuid
from collections import OrderedDict
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, replace
from datetime import datetime
from typing import Any

import numpy as np
import zenoh
from fastapi import FastAPI
from sqlalchemy import Engine, delete, func, select
from sqlalchemy.exc import SQLAlchemyError
from sqlalchemy.orm import Session, sessionmaker

from evorobotics.document import ControllerDocument, controller_sha256
from evorobotics.evaluate import DESCRIPTORS
from evorobotics.evolution import StrategyHistory, rank_in_world, ranking_validation
from evorobotics.strategies import Archive
from schemas.robots import (
    KEY_ACKS,
    KEY_REPLACE,
    KEY_ROBOTS_ALIVE,
    KEY_TRACES,
    KEY_TRACKER,
    CalibrationOut,
    ControllerPush,
    FieldStats,
    FieldWindow,
    LedgerController,
    PushAck,
    PushOut,
    Replacement,
    ReplacementPolicy,
    ReplayOut,
    RobotCalibration,
    RobotDetail,
    RobotOut,
    StopCommand,
    StuckEventOut,
    StuckEventsOut,
    StuckRequest,
    TraceAck,
    TracesOut,
    TrackerPose,
    command_key,
    decode_message,
    decode_trace,
    encode_message,
    robot_from_key,
    tracker_key,
)
from schemas.run import RunConfig
from schemas.wire import WireError
from schemas.world import MAX_GAP_ROBOTS
from server.core.errors import NotFoundError, ServerError, UnconfirmedError
from server.core.logs import context
from server.core.models import Controller, Robot, Run, aware, utcnow
from server.robots.settings import POLICIES, RobotSettings, effective_policy
from server.robots.signing import Signer
from server.robots.store import (
    FieldStatsRow,
    RobotStateRow,
    StuckEventRow,
    TraceRow,
    field_row,
    serve,
    served,
)
from server.robots.traces import TraceIngest, TraceRefusedError, recent_samples, replay_stored
from server.runs import crud
from server.runs.champions import confirmed_document
from server.runs.evaluation import repeats_claim

log = logging.getLogger(__name__)

RANKINGS_KEPT = 32
"""Validated rankings kept in memory, one per (robot calibration or none, run, generation)."""


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


class RobotOfflineError(ServerError):
    """The robot has no liveliness token: nothing can be pushed to it (HTTP 409)."""

    status_code = 409


class RobotOnlineError(ServerError):
    """The robot holds a liveliness token: it cannot be forgotten while it runs (HTTP 409)."""

    status_code = 409


class _Waiter:
    def __init__(self, sha: str | None) -> None:
        self.sha = sha
        """What was pushed (None: a stop): an acknowledgement of it makes it served."""
        self.done = threading.Event()
        self.ack: PushAck | None = None


class RobotService:
    """Zenoh endpoints and store of the robot side, between `start()` and `close()`."""

    def __init__(
        self,
        session: zenoh.Session,
        engine_or_sessionmaker: Engine | sessionmaker[Session],
        settings: RobotSettings | None = None,
        signer: Signer | None = None,
        archives: Callable[[int], tuple[int, RunConfig, Archive]] | None = None,
    ) -> None:
        self.settings = settings or RobotSettings()
        self.signer = signer
        """Signs pushes, stops and replacements (docs/security.md); None sends them unsigned."""
        self._archives = archives
        """run id -> (generations, config, archive) of a QD run (`RunManager.archive`)."""
        self._zenoh = session
        self.sessions = (
            engine_or_sessionmaker
            if isinstance(engine_or_sessionmaker, sessionmaker)
            else sessionmaker(engine_or_sessionmaker, expire_on_commit=False)
        )
        self._inbox: queue.SimpleQueue[tuple[str, Any]] = queue.SimpleQueue()
        self._lock = threading.Lock()
        self._online: set[str] = set()
        self.poses_dropped = 0
        """Tracker poses dropped: malformed, out of order, or of a robot not online."""
        self._waiters: OrderedDict[str, _Waiter] = OrderedDict()
        """push id -> its waiter, kept after its caller stops waiting (the last `WAITERS_KEPT`):
        an acknowledgement that comes late still makes its controller served."""
        self._ingest = TraceIngest(self.sessions, self.settings, self.is_online)
        self._stuck_tokens: dict[str, tuple[float, float]] = {}
        """Per robot: stuck-request tokens left and when they were counted (service thread)."""
        self._entities: list[Any] = []
        self._thread: threading.Thread | None = None
        self._ranker = ThreadPoolExecutor(1, thread_name_prefix="fit-ranking")
        """Validates candidates for the `rank` and `fit` policies off the service thread."""
        self._rankings: dict[tuple[str, str, int, int], Future[Ranking]] = {}
        self.traces_received = 0
        """Trace samples stored (duplicates excluded); for benchmarks."""

    # ------------------------------------------------------------------ lifecycle

    def start(self) -> RobotService:
        if self._thread is not None:
            raise RuntimeError("robot service already started")
        with self.sessions.begin() as db:
            for robot in db.scalars(select(Robot)):
                robot.status = "offline"
        z = self._zenoh
        self._entities = [
            z.declare_queryable(KEY_TRACES, lambda q: self._inbox.put(("trace", q))),
            z.declare_queryable(KEY_REPLACE, lambda q: self._inbox.put(("replace", q))),
            z.declare_subscriber(KEY_ACKS, lambda s: self._inbox.put(("ack", s))),
            z.declare_subscriber(KEY_TRACKER, lambda s: self._inbox.put(("pose", s))),
            z.liveliness().declare_subscriber(
                KEY_ROBOTS_ALIVE, lambda s: self._inbox.put(("alive", s)), history=True
            ),
        ]
        self._thread = threading.Thread(target=self._run, name="robot-service", daemon=True)
        self._thread.start()
        return self

    def close(self, timeout: float = 10.0) -> None:
        """Undeclare every endpoint and stop the service thread (the session stays open)."""
        for entity in self._entities:
            entity.undeclare()
        self._entities = []
        if self._thread is not None:
            self._inbox.put(("halt", None))
            self._thread.join(timeout)
            if self._thread.is_alive():
                raise RuntimeError("robot service thread did not stop")
            self._thread = None
        self._ranker.shutdown(wait=False, cancel_futures=True)

    # ------------------------------------------------------------------ service thread

    def _run(self) -> None:
        while True:
            kind, item = self._inbox.get()
            if kind == "halt":
                return
            try:
                if kind == "trace":
                    self._on_trace(item)
                elif kind == "replace":
                    self._on_replace(item)
                elif kind == "ack":
                    self._on_ack(item)
                elif kind == "pose":
                    self._on_pose(item)
                else:
                    self._on_alive(item)
            except Exception:  # one bad message must not stop the robot side
                log.exception("robot service: handling %s failed", kind)

    def _on_alive(self, sample: zenoh.Sample) -> None:
        try:
            robot = robot_from_key(str(sample.key_expr))
        except ValueError:
            log.warning("ignoring robot liveliness key %s", sample.key_expr)
            return
        online = sample.kind == zenoh.SampleKind.PUT
        with self.sessions.begin() as db:  # registered before it is online: pushable
            row = db.get(Robot, robot)
            if row is None:
                row = Robot(id=robot, status="online")
                db.add(row)
            row.status = "online" if online else "offline"
            row.last_seen = utcnow()
        with self._lock:
            was_online = robot in self._online
            (self._online.add if online else self._online.discard)(robot)
        if online != was_online:
            context(log, robot=robot).info("robot %s %s", robot, "online" if online else "offline")

    def _on_pose(self, sample: zenoh.Sample) -> None:
        """Keep a tracker's pose of an online robot, to be matched with its trace samples."""
        try:
            pose = decode_message(sample.payload.to_bytes())
            if not isinstance(pose, TrackerPose) or str(sample.key_expr) != tracker_key(pose.robot):
                raise WireError(f"not a TrackerPose of the robot its key names ({sample.key_expr})")
        except (WireError, ValueError) as exc:
            self.poses_dropped += 1
            log.debug("dropping a tracker pose: %s", exc)
            return
        if not self._ingest.track(pose):
            self.poses_dropped += 1

    def _on_ack(self, sample: zenoh.Sample) -> None:
        try:
            ack = decode_message(sample.payload.to_bytes())
        except WireError as exc:
            log.warning("dropping malformed ack: %s", exc)
            return
        if not isinstance(ack, PushAck):
            return
        if ack.robot != str(sample.key_expr).split("/")[2]:
            log.warning("dropping an ack for robot %s sent on %s", ack.robot, sample.key_expr)
            return
        robot_log = context(log, robot=ack.robot)
        if ack.accepted:
            robot_log.info("robot %s accepted push %s (%s)", ack.robot, ack.push_id, ack.sha256)
        else:
            robot_log.warning("robot %s rejected push %s: %s", ack.robot, ack.push_id, ack.reason)
        with self._lock:
            waiter = self._waiters.pop(ack.push_id, None)
        if ack.accepted:
            with self.sessions.begin() as db:
                row = db.get(Robot, ack.robot)
                if row is not None:
                    row.controller_sha256 = ack.sha256
                    if waiter is not None and waiter.sha is not None and waiter.sha == ack.sha256:
                        serve(row, waiter.sha)
        if waiter is not None:
            waiter.ack = ack
            waiter.done.set()

    def _on_trace(self, query: zenoh.Query) -> None:
        with query:
            try:
                batch = decode_trace(_payload(query))
                _check_sender(batch.robot, query)
            except WireError as exc:
                query.reply_err(f"malformed: {exc}".encode())
                return
            try:
                last, added = self._ingest.store(batch)
            except TraceRefusedError as exc:
                context(log, robot=batch.robot).warning(
                    "refusing a trace batch of robot %s (boot %d, steps %d-%d): %s",
                    batch.robot,
                    batch.boot,
                    batch.first,
                    batch.last,
                    exc,
                )
                query.reply_err(f"refused: {exc}".encode())
                return
            except SQLAlchemyError as exc:
                context(log, robot=batch.robot).error("storing traces failed: %s", exc)
                query.reply_err(b"not stored: the database failed; send the samples again")
                return
            self.traces_received += added
            ack = TraceAck(robot=batch.robot, last=last)
            query.reply(query.key_expr, encode_message(ack))

    def _on_replace(self, query: zenoh.Query) -> None:
        with query:
            try:
                request = decode_message(_payload(query))
                if not isinstance(request, StuckRequest):
                    raise WireError(f"expected a stuck request, got {request.kind}")
                _check_sender(request.robot, query)
            except WireError as exc:
                query.reply_err(f"malformed: {exc}".encode())
                return
            if not self._stuck_allowed(request.robot, time.monotonic()):
                query.reply_err(
                    f"rate limited: more than {self.settings.stuck_burst} stuck requests at over "
                    f"{self.settings.stuck_per_s:g} a second; not recorded".encode()
                )
                return
            doc, reason = self._replace(request)
            text = doc.to_json() if doc else None
            seq, signature = self._sign("replacement", request.robot, request.nonce, text)
            reply = Replacement(
                robot=request.robot,
                document=text,
                reason=reason,
                seq=seq,
                signature=signature,
            )
            query.reply(query.key_expr, encode_message(reply))

    def _stuck_allowed(self, robot: str, now: float) -> bool:
        """Take a token from the robot's bucket (service thread only)."""
        s = self.settings
        tokens, at = self._stuck_tokens.get(robot, (float(s.stuck_burst), now))
        tokens = min(float(s.stuck_burst), tokens + (now - at) * s.stuck_per_s)
        allowed = tokens >= 1.0
        self._stuck_tokens[robot] = (tokens - 1.0 if allowed else tokens, now)
        return allowed

    # ------------------------------------------------------------------ replacement

    def _elite(
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
            with self.sessions() as db:
                history = crud.history(db, run_id=run_id, generations=generations)
            if not _elite_holds(config, history, archive, elite):
                raise UnconfirmedError(
                    f"run {run_id}'s elite {elite}: its archived fitness and descriptors are "
                    "not what the server's own evaluation gives; not served"
                )
        return generations - 1, document

    def _replace(self, request: StuckRequest) -> tuple[ControllerDocument | None, str]:
        with self.sessions.begin() as db:
            robot = db.get(Robot, request.robot)
            policy, _ = effective_policy(
                robot.replacement if robot else None, self.settings.replacement
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
            _trim_events(db, request.robot, self.settings.stuck_retention)
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
                .limit(self.settings.recent_failures)
            )
        )
        if policy == "archive":
            return self._pick_elite(db, failed.run_id, request.sha256, recent)
        if policy == "fit":
            try:
                ranking = self._ranking(db, failed.run_id, request.robot, wait=False)
            except NotFoundError as exc:
                doc, reason = self._pick_rank(db, failed.run_id, recent)
                return doc, f"{exc}; {reason}"
            if ranking is not None:
                return self._pick_ranked(db, ranking, recent)
            doc, reason = self._pick_rank(db, failed.run_id, recent)
            return doc, f"the fit ranking is being computed; {reason}"
        return self._pick_rank(db, failed.run_id, recent)

    def _pick_rank(
        self, db: Session, run_id: int, recent: set[str | None]
    ) -> tuple[ControllerDocument | None, str]:
        """The run's validated champion, else the best of the server's own validated ranking
        of its candidates that did not fail recently (none while that is being computed):
        nothing served rests on a worker's claimed fitness alone."""
        run = db.get(Run, run_id)
        best = None if run is None else crud.champion(db, run=run)
        if best is not None and best.sha256 not in recent:  # chosen on unseen poses, tested
            return ControllerDocument.from_json(best.document), (
                f"the validated champion of run {run_id}"
            )
        try:
            ranking = self._ranking(db, run_id, None, wait=False)
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
                return self._ranked_document(db, ranking, candidate), ranking.reason(candidate)
        return None, f"every candidate of run {ranking.run_id} failed recently on this robot"

    def _ranked_document(
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
        generations, doc = self._elite(ranking.run_id, candidate.elite)
        if doc.sha256 != candidate.sha256:  # the archive moved on since the ranking
            raise NotFoundError(f"run {ranking.run_id}'s archive changed: ask again")
        return _stored(db, ranking.run_id, generations, doc)

    def _ranking(
        self, db: Session, run_id: int, robot_id: str | None, *, wait: bool
    ) -> Ranking | None:
        """The run's candidates ranked by the server's validation, in the robot's calibrated
        world or (robot None) the run's, computed once per calibration and committed
        generation on the ranking thread; None while it is being computed unless `wait`.
        NotFoundError: no robot, no calibration, no run, no generation."""
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
                future = self._ranker.submit(
                    self._rank, robot_id, run_id, latest.generation, calibration
                )
                self._rankings[key] = future
                while len(self._rankings) > RANKINGS_KEPT:
                    self._rankings.pop(next(iter(self._rankings)))
        if not wait and not future.done():
            return None
        return future.result()

    def _rank(
        self,
        robot_id: str | None,
        run_id: int,
        generation: int,
        calibration: RobotCalibration | None,
    ) -> Ranking:
        """Score the run's candidates on its validation poses in the robot's calibrated world,
        or without one the run's world (no reality gap either way): its `validation.candidates`
        fittest training ranks of `generation` and as many of its archive's fittest elites;
        best first by roaming, then mean Eq 12, then candidate order."""
        with self.sessions() as db:
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
        order, scored = rank_in_world(config, top, world)
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
            return _stored(
                db, run_id, generations - 1, doc
            ), f"elite {k} of run {run_id}'s archive, {why}"
        return None, (
            f"every elite of run {run_id}'s archive failed recently on this robot or rests on a "
            "claim the server's own evaluation does not repeat"
        )

    # ------------------------------------------------------------------ API operations

    def is_online(self, robot_id: str) -> bool:
        with self._lock:
            return robot_id in self._online

    def robots(self) -> list[RobotOut]:
        with self.sessions() as db:
            return robot_summaries(db, self.is_online, self.settings.replacement)

    def robot(self, robot_id: str) -> RobotDetail:
        with self.sessions() as db:
            row = db.get(Robot, robot_id)
            if row is None:
                raise NotFoundError(f"no robot with id {robot_id}")
            state = db.get(RobotStateRow, robot_id)
            summary = self._summary(row, state)
            origin: dict[str, Any] = {}
            if summary.controller_sha256:
                ctrl = db.get(Controller, summary.controller_sha256)
                if ctrl is not None:
                    origin = json.loads(ctrl.document).get("provenance", {})
                    origin["run"] = ctrl.run_id
                    origin["generation"] = ctrl.generation
            status = json.loads(state.status) if state else {}
            calibrated: dict[str, Any] = {}
            if row.calibration is not None and row.calibrated_at is not None:
                at = row.calibrated_at
                calibrated = {
                    "calibration": RobotCalibration.model_validate_json(row.calibration),
                    "calibrated_at": aware(at),
                    "before_calibration": self._window(db, robot_id, None, at),
                    "since_calibration": self._window(db, robot_id, at, None),
                }
            return RobotDetail(
                **summary.model_dump(),
                controller_run=_int_or_none(origin.get("run")),
                controller_rank=_int_or_none(origin.get("rank")),
                controller_generation=_int_or_none(origin.get("generation")),
                whiskers=state.whiskers if state else "00000",
                boot=state.boot if state else 0,
                link={"zenoh": "online" if summary.online else "offline", **status},
                **calibrated,
            )

    def _window(
        self, db: Session, robot_id: str, since: datetime | None, until: datetime | None
    ) -> FieldWindow:
        """The robot's retained samples and stuck events that arrived in [since, until)."""
        samples = select(func.coalesce(func.sum(TraceRow.count), 0)).where(
            TraceRow.robot_id == robot_id
        )
        events = select(func.count(StuckEventRow.id)).where(StuckEventRow.robot_id == robot_id)
        if since is not None:
            samples = samples.where(TraceRow.received_at >= since)
            events = events.where(StuckEventRow.at >= since)
        if until is not None:
            samples = samples.where(TraceRow.received_at < until)
            events = events.where(StuckEventRow.at < until)
        hours = int(db.scalar(samples) or 0) * self.settings.dt / 3600.0
        stuck = int(db.scalar(events) or 0)
        return FieldWindow(
            robot_hours=hours, stuck_events=stuck, stuck_per_hour=stuck / hours if hours else None
        )

    def _summary(self, row: Robot, state: RobotStateRow | None) -> RobotOut:
        return _summary(row, state, self.is_online(row.id), self.settings.replacement)

    def set_replacement(self, robot_id: str, policy: ReplacementPolicy | None) -> RobotDetail:
        """Give the robot its own replacement policy, or None to follow the colony's."""
        if policy is not None and policy not in POLICIES:
            raise ValueError(f"policy must be one of {POLICIES} or None, got {policy!r}")
        with self.sessions.begin() as db:
            row = db.get(Robot, robot_id)
            if row is None:
                raise NotFoundError(f"no robot with id {robot_id}")
            row.replacement = policy
        context(log, robot=robot_id).info(
            "robot %s replacement policy: %s", robot_id, policy or "the colony's"
        )
        return self.robot(robot_id)

    def stuck_events(self, robot_id: str, limit: int = 1000) -> StuckEventsOut:
        """The robot's newest `limit` stuck events, oldest first: the field ledger."""
        if limit < 1:
            raise ValueError(f"limit must be >= 1, got {limit}")
        with self.sessions() as db:
            if db.get(Robot, robot_id) is None:
                raise NotFoundError(f"no robot with id {robot_id}")
            rows = list(
                db.scalars(
                    select(StuckEventRow)
                    .where(StuckEventRow.robot_id == robot_id)
                    .order_by(StuckEventRow.id.desc())
                    .limit(limit)
                )
            )
        events = [_event_out(r) for r in reversed(rows)]
        return StuckEventsOut(
            robot=robot_id, events=events, controllers=_ledger(events, self.settings.dt)
        )

    def calibration(self, robot_id: str) -> CalibrationOut:
        """The robot's stored calibration; NotFoundError for an unknown or uncalibrated robot."""
        with self.sessions() as db:
            row = db.get(Robot, robot_id)
            if row is None:
                raise NotFoundError(f"no robot with id {robot_id}")
            if row.calibration is None or row.calibrated_at is None:
                raise NotFoundError(f"robot {robot_id} has no calibration (colony robot calibrate)")
            return CalibrationOut(
                robot=robot_id,
                stored_at=aware(row.calibrated_at),
                calibration=RobotCalibration.model_validate_json(row.calibration),
            )

    def set_calibration(self, robot_id: str, calibration: RobotCalibration) -> CalibrationOut:
        """Store the robot's fitted physics (replacing any earlier fit)."""
        with self.sessions.begin() as db:
            row = db.get(Robot, robot_id)
            if row is None:
                raise NotFoundError(f"no robot with id {robot_id}")
            row.calibration = calibration.model_dump_json()
            row.calibrated_at = utcnow()
        log.info(
            "robot %s calibrated: whiskers %s m, gains %s", robot_id,
            [round(r, 4) for r in calibration.whisker_range],
            [round(g, 4) for g in calibration.motor_gain],
        )  # fmt: skip
        return self.calibration(robot_id)

    def forget(self, robot_id: str) -> None:
        """Remove an offline robot: its registry row, last report, stuck events and traces.

        The field statistics stay: they are the controllers' record over the whole colony.
        """
        with self.sessions.begin() as db:
            if db.get(Robot, robot_id) is None:
                raise NotFoundError(f"no robot with id {robot_id}")
            if self.is_online(robot_id):
                raise RobotOnlineError(f"robot {robot_id} is online: stop its agent first")
            for table in (TraceRow, StuckEventRow, RobotStateRow):
                db.execute(delete(table).where(table.robot_id == robot_id))
            db.execute(delete(Robot).where(Robot.id == robot_id))
        self._ingest.forget(robot_id)
        context(log, robot=robot_id).info("robot %s forgotten", robot_id)

    def push(
        self,
        robot_id: str,
        *,
        sha256: str | None = None,
        run_id: int | None = None,
        rank: int | None = None,
        elite: int | None = None,
        fit: bool = False,
        timeout: float | None = None,
    ) -> PushOut:
        """Push a stored controller (sha256) or a run's controller; wait for the ack.

        A run's `rank` is that training rank of its latest committed generation, its `elite`
        that entry of its archive (`RunManager.archive`), each only if the server's own
        evaluation repeats its claim (else UnconfirmedError); `fit` its candidate that roams
        most in the robot's calibrated world (waiting for the ranking); without any, the run's
        best: its validated champion once completed, else the best training rank whose claim
        the server's evaluation repeats (`confirmed_document`)."""
        if sha256 is not None and run_id is not None:
            raise ValueError("give exactly one of sha256 or run_id")
        chosen_elite = (
            None if elite is None or run_id is None else self._elite(run_id, elite, confirm=True)
        )
        with self.sessions.begin() as db:
            if db.get(Robot, robot_id) is None:
                raise NotFoundError(f"no robot with id {robot_id}")
            if sha256 is not None:
                row = crud.find_controller(db, sha256=sha256)
                text, sha = row.document, row.sha256
            elif run_id is None:
                raise ValueError("give exactly one of sha256 or run_id")
            else:
                run = db.get(Run, run_id)
                if run is None:
                    raise NotFoundError(f"no run with id {run_id}")
                plain = rank is None and elite is None and not fit
                best = crud.champion(db, run=run) if plain else None
                if fit:
                    ranking = self._ranking(db, run_id, robot_id, wait=True)
                    assert ranking is not None  # waited for
                    doc = self._ranked_document(db, ranking, ranking.candidates[0])
                    text, sha = doc.to_json(), doc.sha256
                elif chosen_elite is not None:
                    doc = _stored(db, run_id, *chosen_elite)
                    text, sha = doc.to_json(), doc.sha256
                elif best is not None:
                    text, sha = best.document, best.sha256
                else:
                    config = RunConfig.model_validate_json(run.config)
                    doc = _stored(db, run_id, *confirmed_document(db, run, config, rank))
                    text, sha = doc.to_json(), doc.sha256
        push_id = uuid.uuid4().hex
        seq, signature = self._sign("push", robot_id, push_id, text)
        message = ControllerPush(
            push_id=push_id, sha256=sha, document=text, seq=seq, signature=signature
        )
        return self._send(robot_id, push_id, encode_message(message), sha, timeout)

    def _sign(self, kind: str, robot: str, push_id: str, document: str | None) -> tuple[int, str]:
        """(seq, signature) of a command, or (0, "") without a signer."""
        if self.signer is None:
            return 0, ""
        return self.signer.sign(kind=kind, robot=robot, push_id=push_id, document=document)

    def stop_robot(self, robot_id: str, timeout: float | None = None) -> PushOut:
        """Stop the robot's motors until the next push."""
        with self.sessions() as db:
            if db.get(Robot, robot_id) is None:
                raise NotFoundError(f"no robot with id {robot_id}")
        push_id = uuid.uuid4().hex
        seq, signature = self._sign("stop", robot_id, push_id, None)
        payload = encode_message(StopCommand(push_id=push_id, seq=seq, signature=signature))
        return self._send(robot_id, push_id, payload, None, timeout)

    def _send(
        self, robot: str, push_id: str, payload: bytes, sha: str | None, timeout: float | None
    ) -> PushOut:
        if not self.is_online(robot):
            raise RobotOfflineError(f"robot {robot} is offline")
        waiter = _Waiter(sha)
        with self._lock:
            self._waiters[push_id] = waiter
            while len(self._waiters) > WAITERS_KEPT:
                self._waiters.popitem(last=False)
        self._zenoh.put(
            command_key(robot), payload, congestion_control=zenoh.CongestionControl.BLOCK
        )
        waiter.done.wait(self.settings.push_timeout if timeout is None else timeout)
        ack = waiter.ack
        if ack is None:
            return PushOut(
                robot=robot,
                push_id=push_id,
                sha256=sha,
                acknowledged=False,
                accepted=False,
                reason="no acknowledgement within the timeout",
            )
        return PushOut(
            robot=robot,
            push_id=push_id,
            sha256=ack.sha256,
            acknowledged=True,
            accepted=ack.accepted,
            reason=ack.reason,
        )

    def traces(self, robot_id: str, limit: int = 1000) -> TracesOut:
        """The newest `limit` stored samples, oldest first."""
        with self.sessions() as db:
            return recent_samples(db, robot_id=robot_id, limit=limit)

    def replay(self, robot_id: str) -> ReplayOut:
        """Feed the stored whiskers into the same controllers; compare motor commands bitwise."""
        with self.sessions() as db:
            return replay_stored(db, robot_id=robot_id)

    def field_stats(self, sha256: str) -> FieldStats | None:
        """Robot-hours and stuck events of a controller over the colony; None if never run."""
        with self.sessions() as db:
            row = db.get(FieldStatsRow, sha256.lower())
            if row is None:
                return None
            hours = row.steps * self.settings.dt / 3600.0
            return FieldStats(
                sha256=row.sha256,
                robot_hours=hours,
                stuck_events=row.stuck_events,
                stuck_per_hour=row.stuck_events / hours if hours > 0 else None,
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
    return _stored(db, run_id, latest.generation, doc)


def _stored(
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


def _ledger(events: list[StuckEventOut], dt: float) -> list[LedgerController]:
    """Per controller of `events`: the steps run after the events that left the robot with
    it, and the events in which it stuck; longest run first."""
    steps: dict[str, int] = {}
    stuck: dict[str, int] = {}
    for e in events:
        ran = e.replacement_sha256 or e.controller_sha256
        if ran is not None and e.steps_run is not None:
            steps[ran] = steps.get(ran, 0) + e.steps_run
        if e.controller_sha256 is not None:
            stuck[e.controller_sha256] = stuck.get(e.controller_sha256, 0) + 1
    shas = sorted(steps.keys() | stuck.keys(), key=lambda s: (-steps.get(s, 0), s))
    return [
        LedgerController(
            sha256=s,
            steps_run=steps.get(s, 0),
            seconds_run=steps.get(s, 0) * dt,
            stuck_events=stuck.get(s, 0),
        )
        for s in shas
    ]


def _event_out(row: StuckEventRow) -> StuckEventOut:
    policy = next((p for p in POLICIES if p == row.policy), None)
    at = aware(row.at)
    return StuckEventOut(
        id=row.id,
        at=at.timestamp() if at else 0.0,
        step=row.step,
        reason=row.reason,
        controller_sha256=row.controller_sha256,
        policy=policy,
        replacement_sha256=row.replacement_sha256,
        answer=row.answer,
        steps_run=row.steps_run,
    )


WAITERS_KEPT = 256
"""Pushes remembered for their acknowledgement, answered or not (a few minutes of a colony's
pushes: a robot acknowledges within a step)."""


def with_colony_gap(db: Session, config: RunConfig) -> RunConfig:
    """`config` with the colony's calibrated robots as its gap when it asks for `reality_gap:
    "colony"` and names none (stored with the run: it stays a function of its config);
    NotFoundError when no robot is calibrated."""
    if config.reality_gap != "colony" or config.world.gap_robots:
        return config
    rows = db.scalars(
        select(Robot).where(Robot.calibration.is_not(None)).order_by(Robot.id).limit(MAX_GAP_ROBOTS)
    ).all()
    robots = tuple(
        RobotCalibration.model_validate_json(r.calibration).gap_robot(r.id)
        for r in rows
        if r.calibration is not None
    )
    if not robots:
        raise NotFoundError(
            "reality_gap 'colony' draws from the calibrated robots, and no robot is calibrated: "
            "colony robot calibrate ROBOT"
        )
    world = config.world.model_copy(update={"gap_robots": robots})
    return RunConfig.model_validate({**config.model_dump(), "world": world.model_dump()})


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


def _check_sender(robot: str, query: zenoh.Query) -> None:
    """WireError unless `robot` is the robot whose key the query came on: zenoh's access
    control lets only that robot's credentials use its keys (docs/security.md)."""
    key = str(query.key_expr)
    if robot != key.split("/")[2]:
        raise WireError(f"robot {robot} may not send on {key}")


def _payload(query: zenoh.Query) -> bytes:
    return query.payload.to_bytes() if query.payload is not None else b""


def _int_or_none(value: object) -> int | None:
    return value if isinstance(value, int) and not isinstance(value, bool) else None


def robot_service(
    settings: RobotSettings | None = None,
) -> Callable[[FastAPI, zenoh.Session], Callable[[], None]]:
    """A `create_app(..., services=[robot_service()])` hook: the service on the server's session.

    It uses the run manager's sessionmaker and the colony's replacement policy from its
    settings (COLONY_REPLACEMENT), and is exposed as `app.state.robots` for the routes.
    """

    def install(app: FastAPI, session: zenoh.Session) -> Callable[[], None]:
        signer = getattr(app.state, "signer", None)
        manager = app.state.manager
        tuned = replace(settings or RobotSettings(), replacement=manager.settings.replacement)
        service = RobotService(session, manager.sessions, tuned, signer, manager.archive).start()
        app.state.robots = service

        def close() -> None:
            app.state.robots = None
            service.close()

        return close

    return install


def robot_summaries(
    db: Session, is_online: Callable[[str], bool], colony: ReplacementPolicy
) -> list[RobotOut]:
    """Every robot ever seen, by id: the one robot view of /api/robots and /api/colony;
    `colony` is the colony's replacement policy."""
    rows = list(db.scalars(select(Robot).order_by(Robot.id)))
    states = {s.robot_id: s for s in db.scalars(select(RobotStateRow))}
    return [_summary(r, states.get(r.id), is_online(r.id), colony) for r in rows]


def _summary(
    row: Robot, state: RobotStateRow | None, online: bool, colony: ReplacementPolicy
) -> RobotOut:
    last = state.updated_at if state else row.last_seen
    policy, source = effective_policy(row.replacement, colony)
    return RobotOut(
        id=row.id,
        online=online,
        state=(state.state if state else "idle") if online else "offline",
        controller_sha256=row.controller_sha256,
        steps=state.steps if state else 0,
        stuck_events=state.stuck_events if state else 0,
        last_seen=aware(last),
        replacement=policy,
        replacement_source=source,
    )
