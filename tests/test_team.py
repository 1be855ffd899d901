"""A team span's exchange (worker.team) over real zenoh sessions on 127.0.0.1: members in
threads, each with its own client session to a router, no server."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager

import numpy as np
import pytest
import zenoh

from evorobotics.ga import GAParams, init
from evorobotics.layout import layout
from schemas.run import RunConfig
from schemas.wire import (
    Job,
    JobKey,
    TeamMessage,
    decode_team_message,
    encode_team_message,
    genome_digest,
    team_cuts,
    team_key,
)
from tests.helpers import free_port
from tests.test_dispatch import client_config
from tests.test_robots_server import router_config
from worker import team as team_module
from worker.team import Inbox, Team

CONFIG = RunConfig(population=10, generations=20, trials=2, steps=5, seed=3)
W = CONFIG.network_spec.weight_count
TEAM_ID = "00000000000000aa"
WAIT = 20.0


def evaluator(
    config: RunConfig, generation: int, genomes: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Fitness of a genome alone (its row sum, shifted by the generation), as the science is."""
    n = genomes.shape[0]
    fitness = genomes.sum(axis=1) + generation
    return fitness, np.repeat(fitness[:, None, None], config.trials * 4).reshape(n, -1, 4)


def place(names: tuple[str, ...], member: int) -> Job:
    state = init(layout(CONFIG.network_spec), GAParams.from_config(CONFIG)).to_arrays()
    genomes = np.random.default_rng(1).normal(size=(CONFIG.population, W))
    key = JobKey(run_id=1, generation=0, index=0)
    return Job(
        key, 0, CONFIG.population, CONFIG, genomes, span=CONFIG.generations, state=state,
        team=names, member=member, team_id=TEAM_ID,
    )  # fmt: skip


@contextmanager
def router() -> Iterator[int]:
    port = free_port()
    with zenoh.open(router_config(port)):
        yield port


@contextmanager
def members(port: int, names: tuple[str, ...]) -> Iterator[list[tuple[zenoh.Session, Inbox]]]:
    """A session and inbox per name, every inbox reachable (a probe went through) on exit."""
    with ExitStack() as stack:
        out = []
        for name in names:
            session = stack.enter_context(zenoh.open(client_config(port)))
            inbox = Inbox(session, name)
            stack.callback(inbox.close)
            out.append((session, inbox))
        probe = out[0][0]
        for name, (_, inbox) in zip(names, out, strict=True):
            payload = encode_team_message(TeamMessage("ffffffffffffffff", 0, 63, over=True))
            for _ in range(200):  # subscriptions reach the router asynchronously
                probe.put(team_key(name), payload)
                if inbox.get(0.05) is not None:
                    break
            else:
                raise AssertionError(f"{name}'s inbox is unreachable")
        yield out


Step = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None
"""A generation's fitness, components, seconds and individuals evaluated (None: left)."""
Outcome = dict[int, tuple[list[Step], set[int]]]
"""Per member: its generations, and the members it still counted on at the end."""


def step(team: Team, g: int, skew: float = 0.0) -> Step:
    """Generation g of the test's span: the first generation's genomes shifted by g (and by
    `skew`, a member whose GA differs)."""
    genomes = place(("a", "b"), 0).genomes + g + skew
    out = team.generation(g, genomes, genome_digest(genomes))
    return None if out is None else (out[0], out[1], np.array(out[2]), np.array(out[3]))


def run_member(
    session: zenoh.Session,
    inbox: Inbox,
    job: Job,
    generations: int,
    out: Outcome,
    skew: float = 0.0,
) -> None:
    team = Team(session, inbox, job, evaluator)
    try:
        got: list[Step] = []
        for g in range(generations):
            result = step(team, g, skew)
            got.append(result)
            if result is None:
                break
        out[job.member] = (got, set(team.active))
    finally:
        team.close()


def run_team(
    sessions: list[tuple[zenoh.Session, Inbox]],
    names: tuple[str, ...],
    generations: int,
    skew: float = 0.0,
) -> Outcome:
    """Every member in its own thread for `generations` (member m's GA shifted by m x `skew`);
    each must finish within WAIT."""
    out: Outcome = {}
    threads = [
        threading.Thread(
            target=run_member, args=(s, i, place(names, m), generations, out, skew * m)
        )
        for m, (s, i) in enumerate(sessions)
    ]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(WAIT)
    assert not any(thread.is_alive() for thread in threads)
    return out


def whole(generation: int) -> tuple[np.ndarray, np.ndarray]:
    genomes = place(("a", "b"), 0).genomes + generation
    fitness, components = evaluator(CONFIG, generation, genomes)
    return np.asarray(fitness), np.asarray(components)


@pytest.mark.parametrize("size", [2, 3])
def test_members_split_each_generation_and_all_see_the_whole_of_it(size: int) -> None:
    names = ("a", "b", "c")[:size]
    with router() as port, members(port, names) as sessions:
        out = run_team(sessions, names, 4)
    assert sorted(out) == list(range(size))
    for member, (results, _) in out.items():
        assert len(results) == 4
        for g, result in enumerate(results):
            fitness, components = whole(g)
            assert result is not None
            assert result[0].tobytes() == fitness.tobytes()
            if member == 0:  # only the leader gets (and records) the components
                assert result[1].tobytes() == components.tobytes()
            cuts = team_cuts(CONFIG.population, size)
            assert result[3] == cuts[member + 1] - cuts[member]


def test_the_leader_evaluates_a_silent_member_s_slice_and_drops_it(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(team_module, "LEADER_WAIT_S", 0.2)
    names = ("lead", "silent")
    with router() as port, members(port, names) as [(session, inbox), (_, silent)]:
        team = Team(session, inbox, place(names, 0), evaluator)
        try:
            first = step(team, 0)
            second = step(team, 1)
        finally:
            team.close()
        heard = [decode_team_message(p) for p in iter(lambda: silent.get(1.0), None)]
    told = [m for m in heard if m.team_id == TEAM_ID]  # not the probes
    for g, result in enumerate((first, second)):
        fitness, components = whole(g)
        assert result is not None
        assert result[0].tobytes() == fitness.tobytes()
        assert result[1].tobytes() == components.tobytes()
    assert first is not None and second is not None
    assert (int(first[3]), int(second[3])) == (5, 10)  # its own half, then the whole generation
    assert team.active == set()
    # the silent member got the leader's first slice, then word that it is out, then nothing
    assert [(m.member, m.generation, m.over) for m in told] == [(0, 0, False), (0, 0, True)]


def test_a_member_leaves_when_the_leader_ends_the_span_and_drops_malformed_messages() -> None:
    names = ("lead", "member")
    with router() as port, members(port, names) as [(lead_session, lead_inbox), (s, inbox)]:
        leader = Team(lead_session, lead_inbox, place(names, 0), evaluator)
        member = Team(s, inbox, place(names, 1), evaluator)
        try:
            lead_session.put(team_key("member"), b"not a frame")
            done: dict[int, object] = {}
            thread = threading.Thread(target=lambda: done.setdefault(0, step(member, 0)))
            thread.start()
            assert step(leader, 0) is not None
            thread.join(WAIT)
            assert done[0] is not None  # the malformed message was dropped, not fatal
            leader.leave(1)
            assert step(member, 1) is None
        finally:
            leader.close()
            member.close()


def test_a_member_whose_ga_differs_is_dropped_and_its_slice_evaluated_by_the_leader(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A member asking other genomes (another GA version) sends fitness under another digest:
    the leader never counts it (no wait either), and the member leaves on the leader's."""
    monkeypatch.setattr(team_module, "LEADER_WAIT_S", 60.0)  # a wait would hang the test
    names = ("lead", "skewed")
    with router() as port, members(port, names) as sessions:
        out = run_team(sessions, names, 3, skew=0.5)
    leader, skewed = out[0], out[1]
    for g, result in enumerate(leader[0]):
        assert result is not None and result[0].tobytes() == whole(g)[0].tobytes()
    assert skewed[0][-1] is None  # it left the team


def test_a_member_that_leaves_costs_no_wait_and_the_others_learn_who_owns_its_slice(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Team of three: member 2 leaves after generation 0. The leader takes its slice over at
    once (no LEADER_WAIT_S, set to a minute), and member 1 stops counting on member 2 when
    the leader's messages carry member 2's slice."""
    monkeypatch.setattr(team_module, "LEADER_WAIT_S", 60.0)
    names = ("lead", "stays", "leaves")
    out: Outcome = {}

    def leaving(session: zenoh.Session, inbox: Inbox) -> None:
        team = Team(session, inbox, place(names, 2), evaluator)
        try:
            out[2] = ([step(team, 0)], set(team.active))
            team.leave(1)
        finally:
            team.close()

    with router() as port, members(port, names) as sessions:
        threads = [
            threading.Thread(target=run_member, args=(*sessions[0], place(names, 0), 3, out)),
            threading.Thread(target=run_member, args=(*sessions[1], place(names, 1), 3, out)),
            threading.Thread(target=leaving, args=sessions[2]),
        ]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(WAIT)
        assert not any(thread.is_alive() for thread in threads)
    for member in (0, 1):
        results, active = out[member]
        for g, result in enumerate(results):
            assert result is not None and result[0].tobytes() == whole(g)[0].tobytes()
        assert active == ({1} if member == 0 else {0})
    counts = [int(r[3]) for r in out[0][0] if r is not None]
    assert (counts[0], counts[-1]) == (3, 7)  # its own slice of 3, then member 2's 4 too
