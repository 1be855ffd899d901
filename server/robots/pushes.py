"""Controllers and stops sent to robots, and their acknowledgements.

A command goes on the robot's command key, signed when the server has a key (docs/security.md),
and its caller waits for the robot's acknowledgement: the agent applies it at a step boundary.
A waiter outlives its caller's wait (the last `WAITERS_KEPT`), so an acknowledgement that comes
late still makes its controller served. A run's controller is pushed only if the server's own
evaluation repeats the claim that chose it.
"""

from __future__ import annotations

import threading
import uuid
from collections import OrderedDict
from collections.abc import Callable

from sqlalchemy.orm import Session, sessionmaker

from schemas.robots import (
    ControllerPush,
    PushAck,
    PushOut,
    StopCommand,
    command_key,
    encode_message,
)
from schemas.run import RunConfig
from server.core.errors import NotFoundError, ServerError
from server.core.models import Robot, Run
from server.robots.replacement import Replacements, stored_document
from server.robots.settings import RobotSettings
from server.robots.signing import Signer
from server.robots.store import serve
from server.runs import crud
from server.runs.champions import confirmed_document

WAITERS_KEPT = 256
"""Pushes remembered for their acknowledgement, answered or not (a few minutes of a colony's
pushes: a robot acknowledges within a step)."""


class RobotOfflineError(ServerError):
    """The robot has no liveliness token: nothing can be pushed to it (HTTP 409)."""

    status_code = 409


class _Waiter:
    def __init__(self, sha: str | None) -> None:
        self.sha = sha
        """What was pushed (None: a stop): an acknowledgement of it makes it served."""
        self.done = threading.Event()
        self.ack: PushAck | None = None


class Pushes:
    """Sends pushes and stops (from any thread) and resolves their acknowledgements (on the
    robot service's thread)."""

    def __init__(
        self,
        sessions: sessionmaker[Session],
        settings: RobotSettings,
        signer: Signer | None,
        replacements: Replacements,
        is_online: Callable[[str], bool],
        publish: Callable[[str, bytes], None],
    ) -> None:
        self._sessions = sessions
        self._settings = settings
        self._signer = signer
        """Signs pushes, stops and replacements; None sends them unsigned."""
        self._replacements = replacements
        self._is_online = is_online
        self._publish = publish
        """Puts a payload on a key, losing nothing (the service's zenoh session)."""
        self._lock = threading.Lock()
        self._waiters: OrderedDict[str, _Waiter] = OrderedDict()
        """push id -> its waiter, kept after its caller stops waiting (the last `WAITERS_KEPT`):
        an acknowledgement that comes late still makes its controller served."""

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
        if (sha256 is None) == (run_id is None):
            raise ValueError("give exactly one of sha256 or run_id")
        chosen_elite = (
            None
            if elite is None or run_id is None
            else self._replacements.elite(run_id, elite, confirm=True)
        )
        with self._sessions.begin() as db:
            if db.get(Robot, robot_id) is None:
                raise NotFoundError(f"no robot with id {robot_id}")
            if sha256 is not None:
                row = crud.find_controller(db, sha256=sha256)
                text, sha = row.document, row.sha256
            else:
                assert run_id is not None  # one of the two, checked above
                run = db.get(Run, run_id)
                if run is None:
                    raise NotFoundError(f"no run with id {run_id}")
                plain = rank is None and elite is None and not fit
                best = crud.champion(db, run=run) if plain else None
                if fit:
                    ranking = self._replacements.ranking(db, run_id, robot_id, wait=True)
                    assert ranking is not None  # waited for
                    doc = self._replacements.candidate_document(db, ranking, ranking.candidates[0])
                    text, sha = doc.to_json(), doc.sha256
                elif chosen_elite is not None:
                    doc = stored_document(db, run_id, *chosen_elite)
                    text, sha = doc.to_json(), doc.sha256
                elif best is not None:
                    text, sha = best.document, best.sha256
                else:
                    config = RunConfig.model_validate_json(run.config)
                    doc = stored_document(db, run_id, *confirmed_document(db, run, config, rank))
                    text, sha = doc.to_json(), doc.sha256
        push_id = uuid.uuid4().hex
        seq, signature = self.sign("push", robot_id, push_id, text)
        message = ControllerPush(
            push_id=push_id, sha256=sha, document=text, seq=seq, signature=signature
        )
        return self._send(robot_id, push_id, encode_message(message), sha, timeout)

    def sign(self, kind: str, robot: str, push_id: str, document: str | None) -> tuple[int, str]:
        """(seq, signature) of a command, or (0, "") without a signer."""
        if self._signer is None:
            return 0, ""
        return self._signer.sign(kind=kind, robot=robot, push_id=push_id, document=document)

    def stop(self, robot_id: str, timeout: float | None = None) -> PushOut:
        """Stop the robot's motors until the next push."""
        with self._sessions() as db:
            if db.get(Robot, robot_id) is None:
                raise NotFoundError(f"no robot with id {robot_id}")
        push_id = uuid.uuid4().hex
        seq, signature = self.sign("stop", robot_id, push_id, None)
        payload = encode_message(StopCommand(push_id=push_id, seq=seq, signature=signature))
        return self._send(robot_id, push_id, payload, None, timeout)

    def _send(
        self, robot: str, push_id: str, payload: bytes, sha: str | None, timeout: float | None
    ) -> PushOut:
        if not self._is_online(robot):
            raise RobotOfflineError(f"robot {robot} is offline")
        waiter = _Waiter(sha)
        with self._lock:
            self._waiters[push_id] = waiter
            while len(self._waiters) > WAITERS_KEPT:
                self._waiters.popitem(last=False)
        self._publish(command_key(robot), payload)
        waiter.done.wait(self._settings.push_timeout if timeout is None else timeout)
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

    def acknowledged(self, ack: PushAck) -> None:
        """Resolve the push `ack` answers: an accepted controller is what the robot runs, and
        served if it is the one pushed."""
        with self._lock:
            waiter = self._waiters.pop(ack.push_id, None)
        if ack.accepted:
            with self._sessions.begin() as db:
                row = db.get(Robot, ack.robot)
                if row is not None:
                    row.controller_sha256 = ack.sha256
                    if waiter is not None and waiter.sha is not None and waiter.sha == ack.sha256:
                        serve(row, waiter.sha)
        if waiter is not None:
            waiter.ack = ack
            waiter.done.set()
