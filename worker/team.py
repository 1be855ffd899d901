"""A team span (protocol 7): idle workers split each generation of one span between them.

A generation of a few milliseconds is cheaper to evolve in one process than through the server
(spans), but one process leaves the other workers idle. A team splits each generation into
`team_cuts` slices instead: every member evaluates its slice, sends the fitness to the others
on their `team_key` (through the router, no server in between), and once it has the whole
generation tells and asks the next one itself, as `evolve` would. Fitness depends on the
genome and the generation only, so the members ask identical generations and the run stays
bit-identical to `evolve`.

Only the leader (member 0) holds the span's lease and sends results to the server; the others
send it nothing. Every slice carries the digest of the generation its sender asked, so a
member whose GA differs (another version) never has its fitness counted: the leader only
takes slices under its own digest, which the server checks. A member silent for
`LEADER_WAIT_S`, or that leaves, is dropped: the leader evaluates its slice itself from then
on, so each member that dies or hangs costs the span that long once (one that leaves, or asks
other genomes, nothing). A member that hears nothing for `MEMBER_WAIT_S` (the leader died, or
waits on the server) or is told the span is over goes back to asking the server for jobs.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import time
from collections.abc import Callable

import numpy as np
import zenoh

from schemas.run import RunConfig
from schemas.wire import (
    Job,
    TeamMessage,
    WireError,
    decode_team_message,
    encode_team_message,
    team_cuts,
    team_key,
)

log = logging.getLogger(__name__)

Evaluator = Callable[[RunConfig, int, np.ndarray], tuple[np.ndarray, np.ndarray]]
"""(config, generation, genomes (n, w)) -> fitness (n,), components (n, trials, 4)."""


def checked_evaluation(
    evaluator: Evaluator, config: RunConfig, generation: int, genomes: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The evaluator's fitness (n,) and components (n, trials, 4) of `genomes` as float64;
    ValueError if it returned other shapes or non-finite fitness (a result must not carry
    them to the server, nor a member to its team)."""
    f, c = evaluator(config, generation, genomes)
    f = np.ascontiguousarray(f, dtype=np.float64)
    c = np.ascontiguousarray(c, dtype=np.float64)
    n = genomes.shape[0]
    if f.shape != (n,) or c.shape != (n, config.trials, 4):
        raise ValueError(f"evaluator returned {f.shape} and {c.shape} for {n}")
    if not np.isfinite(f).all():
        raise ValueError("evaluator returned non-finite fitness")
    return f, c


LEADER_WAIT_S = 0.5
"""How long the leader waits for a member's slice before evaluating it itself."""
MEMBER_WAIT_S = 2.0
"""How long a member waits for the rest of a generation before leaving the team: the leader
may be waiting for the server to acknowledge its results."""


class Inbox:
    """The team messages sent to this worker, queued by a subscriber callback (no zenoh call
    and no blocking inside it) for the span loop to take with a timeout."""

    def __init__(self, session: zenoh.Session, name: str) -> None:
        self._queue: queue.SimpleQueue[bytes] = queue.SimpleQueue()
        self._subscriber = session.declare_subscriber(
            team_key(name), lambda sample: self._queue.put(sample.payload.to_bytes())
        )

    def get(self, timeout: float) -> bytes | None:
        """The next message, or None after `timeout` seconds without one."""
        try:
            return self._queue.get(timeout=max(timeout, 0.0))
        except queue.Empty:
            return None

    def close(self) -> None:
        """Undeclare the subscriber before the session closes (or the process may hang)."""
        with contextlib.suppress(zenoh.ZError):
            self._subscriber.undeclare()  # type: ignore[no-untyped-call]


class Team:
    """This worker's part in one team span: who evaluates which slice, and the exchange."""

    def __init__(
        self, session: zenoh.Session, inbox: Inbox, job: Job, evaluator: Evaluator
    ) -> None:
        self.job = job
        self.me = job.member
        self.leader = job.member == 0
        cuts = team_cuts(job.config.population, len(job.team))
        self.slices = [(cuts[i], cuts[i + 1]) for i in range(len(job.team))]
        self.owner = list(range(len(job.team)))
        """The member that evaluates each slice: the leader takes over a dropped member's."""
        self.active = set(range(len(job.team))) - {self.me}
        """The other members still in the team."""
        self._inbox = inbox
        self._evaluator = evaluator
        self._early: dict[int, list[TeamMessage]] = {}
        """Messages for generations this worker has not reached yet."""
        self._publishers: dict[int, zenoh.Publisher] = {}
        try:
            for i, name in enumerate(job.team):
                if i != self.me:
                    self._publishers[i] = session.declare_publisher(
                        team_key(name), congestion_control=zenoh.CongestionControl.BLOCK
                    )
        except BaseException:
            self.close()
            raise

    def generation(
        self, generation: int, genomes: np.ndarray, digest: str
    ) -> tuple[np.ndarray, np.ndarray, float, int] | None:
        """Fitness (n,) and components (n, trials, 4) of the whole generation (`genomes`, of
        `genome_digest` `digest`), with the seconds and individuals this worker evaluated;
        None once the team is over for it.

        Raises what the evaluator raises (for this worker's own slices).
        """
        config = self.job.config
        n = config.population
        fitness = np.empty(n)
        components = np.empty((n, config.trials, 4))
        have = np.zeros(n, dtype=bool)
        mine = [s for i, s in enumerate(self.slices) if self.owner[i] == self.me]
        began = time.perf_counter()
        self._evaluate(generation, genomes, mine, fitness, components, have)
        seconds = time.perf_counter() - began
        self._send(generation, digest, mine, fitness, components, self.active)
        wait = LEADER_WAIT_S if self.leader else MEMBER_WAIT_S
        deadline = time.monotonic() + wait
        while not have.all():
            message = self._next(generation, deadline)
            if message is None:
                if not self.leader:
                    log.info("leaving the team of %s: nothing heard", self.job.key.label())
                    self.leave(generation)
                    return None
                self._take_over(generation, digest, genomes, fitness, components, have, None)
            elif message.over and message.member == 0:
                log.info("the team of %s is over for this worker", self.job.key.label())
                self.active.clear()
                return None
            elif message.over:  # a member left: the leader evaluates its slices now
                self.active.discard(message.member)
                if self.leader:
                    gone = {message.member}
                    self._take_over(generation, digest, genomes, fitness, components, have, gone)
            elif message.digest != digest:
                if not self.leader:
                    if message.member == 0:
                        log.warning(
                            "leaving the team of %s: the leader asked other genomes "
                            "(its GA differs: another version?)",
                            self.job.key.label(),
                        )
                        self.leave(generation)
                        return None
                    continue  # the leader drops that member and sends its slices
                log.warning(
                    "team of %s: member %d asked other genomes at generation %d (its GA "
                    "differs: another version?); evaluating its slices here",
                    self.job.key.label(),
                    message.member,
                    generation,
                )
                wrong = {message.member}
                self._take_over(generation, digest, genomes, fitness, components, have, wrong)
            else:
                self._fill(message, fitness, components, have)
        return fitness, components, seconds, sum(b - a for a, b in mine)

    def leave(self, generation: int) -> None:
        """Tell the other members this worker is out (from the leader: the span is over)."""
        message = TeamMessage(self.job.team_id, generation, self.me, over=True)
        payload = encode_team_message(message)
        for i in sorted(self.active):
            self._publishers[i].put(payload)
        self.active.clear()

    def close(self) -> None:
        """Undeclare the publishers (the session outlives the team)."""
        for publisher in self._publishers.values():
            with contextlib.suppress(zenoh.ZError):
                publisher.undeclare()  # type: ignore[no-untyped-call]

    def _evaluate(
        self,
        generation: int,
        genomes: np.ndarray,
        slices: list[tuple[int, int]],
        fitness: np.ndarray,
        components: np.ndarray,
        have: np.ndarray,
    ) -> None:
        """Evaluate `slices` in one call (fitness does not depend on the company a genome
        keeps) and fill them in."""
        if not slices:
            return
        rows = np.concatenate([np.arange(a, b) for a, b in slices])
        f, c = checked_evaluation(self._evaluator, self.job.config, generation, genomes[rows])
        fitness[rows], components[rows], have[rows] = f, c, True

    def _send(
        self,
        generation: int,
        digest: str,
        slices: list[tuple[int, int]],
        fitness: np.ndarray,
        components: np.ndarray,
        to: set[int],
    ) -> None:
        """Slices' fitness to members `to`; their components to the leader, which records
        them."""
        if not slices or not to:
            return
        rows = np.concatenate([np.arange(a, b) for a, b in slices])
        ranges, team_id = tuple(slices), self.job.team_id
        plain = TeamMessage(team_id, generation, self.me, ranges, fitness[rows], digest=digest)
        for i in sorted(to):
            message = plain
            if i == 0:
                message = TeamMessage(
                    team_id, generation, self.me, ranges, fitness[rows], components[rows], digest
                )
            self._publishers[i].put(encode_team_message(message))

    def _next(self, generation: int, deadline: float) -> TeamMessage | None:
        """The next message of this team for `generation` (earlier ones are stale, later ones
        kept), or None at `deadline`."""
        early = self._early.pop(generation, None)
        if early:
            first, *rest = early
            if rest:
                self._early[generation] = rest
            return first
        while True:
            payload = self._inbox.get(deadline - time.monotonic())
            if payload is None:
                return None
            try:
                message = decode_team_message(payload)
            except WireError as exc:
                log.warning("dropping a malformed team message: %s", exc)
                continue
            if message.team_id != self.job.team_id or message.member == self.me:
                continue  # another (earlier) team's, or an echo
            if message.generation == generation or message.over:
                return message
            if message.generation > generation:
                self._early.setdefault(message.generation, []).append(message)

    def _fill(
        self,
        message: TeamMessage,
        fitness: np.ndarray,
        components: np.ndarray,
        have: np.ndarray,
    ) -> None:
        """Take a message's slices (whole slices of `team_cuts`; anything else is ignored).

        The leader records components, so it ignores fitness without them. Whoever sends a
        slice evaluates it from now on: a member learns so that the leader took over another
        member's slice, and stops sending to that member once it owns nothing."""
        if message.fitness is None:
            return
        if self.leader and message.components is None:
            log.warning("member %d sent the leader no components; ignoring it", message.member)
            return
        if message.components is not None and message.components.shape[1:] != components.shape[1:]:
            log.warning("member %d sent malformed components; ignoring it", message.member)
            return
        if not set(message.ranges) <= set(self.slices):
            log.warning("member %d sent slices %s; ignoring it", message.member, message.ranges)
            return
        offset = 0
        for start, stop in message.ranges:
            k = stop - start
            fitness[start:stop] = message.fitness[offset : offset + k]
            if message.components is not None:
                components[start:stop] = message.components[offset : offset + k]
            have[start:stop] = True
            offset += k
            i = self.slices.index((start, stop))
            previous, self.owner[i] = self.owner[i], message.member
            if previous not in self.owner:
                self.active.discard(previous)

    def _take_over(
        self,
        generation: int,
        digest: str,
        genomes: np.ndarray,
        fitness: np.ndarray,
        components: np.ndarray,
        have: np.ndarray,
        members: set[int] | None,
    ) -> None:
        """The leader drops `members` (None: the owners of every slice still missing): it
        owns their slices from now on and evaluates the missing ones. The dropped are told so,
        in case they are only slow; the others learn it from whose slices they get."""
        if members is None:
            members = {self.owner[i] for i, (a, b) in enumerate(self.slices) if not have[a:b].all()}
        silent = members & self.active
        if silent:
            log.info(
                "team of %s: member(s) %s dropped at generation %d; evaluating their slices here",
                self.job.key.label(),
                sorted(silent),
                generation,
            )
            over = encode_team_message(TeamMessage(self.job.team_id, generation, 0, over=True))
            for i in sorted(silent):
                self._publishers[i].put(over)
        self.active -= members
        taken = [i for i, owner in enumerate(self.owner) if owner in members]
        for i in taken:
            self.owner[i] = self.me
        missing = [self.slices[i] for i in taken if not have[slice(*self.slices[i])].all()]
        self._evaluate(generation, genomes, missing, fitness, components, have)
        self._send(generation, digest, missing, fitness, components, self.active)
