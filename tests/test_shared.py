"""A shared team (worker.shared): leader and members in threads of this process, the real file
in /dev/shm and real wake-up sockets; no server, no zenoh."""

from __future__ import annotations

import os
import secrets
import socket
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import replace
from typing import Any

import numpy as np
import pytest

from evorobotics.ga import GAParams, init
from evorobotics.layout import layout
from schemas.run import RunConfig
from schemas.wire import Job, JobKey, genome_digest
from worker import shared
from worker.shared import RING, SharedTeam, segment_path, stamp

pytestmark = pytest.mark.skipif(not shared.supported(), reason="shared teams need Linux x86-64")

CONFIG = RunConfig(population=10, generations=20, trials=2, steps=5, seed=3)
W = CONFIG.network_spec.weight_count
WAIT = 20.0


def evaluator(
    config: RunConfig, generation: int, genomes: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Fitness of a genome alone (its row sum, shifted by the generation), as the science is;
    slow enough (1 ms a call) that members wake up while the leader still has chunks."""
    time.sleep(0.001)
    n = genomes.shape[0]
    fitness = genomes.sum(axis=1) + generation
    return fitness, np.repeat(fitness[:, None, None], config.trials * 4).reshape(n, -1, 4)


def genomes_of(g: int) -> np.ndarray:
    return np.random.default_rng(1).normal(size=(CONFIG.population, W)) + g


def place(size: int, member: int, team_id: str, span: int = CONFIG.generations) -> Job:
    state = init(layout(CONFIG.network_spec), GAParams.from_config(CONFIG)).to_arrays()
    key = JobKey(run_id=1, generation=0, index=0)
    names = tuple(f"w{i}" for i in range(size))
    return Job(
        key, 0, CONFIG.population, CONFIG, genomes_of(0), span=span, state=state,
        team=names, member=member, team_id=team_id, shared=True,
    )  # fmt: skip


class Member(threading.Thread):
    """A member following its leader's span: what it evaluated, and whether it joined."""

    def __init__(self, job: Job) -> None:
        super().__init__(daemon=True)
        self.job = job
        self.joined = threading.Event()
        self.stop = threading.Event()
        self.individuals = 0
        self.failed = False

    def run(self) -> None:
        team = SharedTeam.join(self.job, evaluator)
        if team is None:
            self.failed = True
            self.joined.set()
            return
        self.joined.set()
        try:
            team.follow(self.stop, self.count)
        finally:
            team.close()

    def count(self, individuals: int, seconds: float) -> None:
        assert seconds > 0
        self.individuals += individuals


@contextmanager
def team(size: int, span: int = CONFIG.generations) -> Iterator[tuple[SharedTeam, list[Member]]]:
    """A leader (in this thread) and `size - 1` joined members; on exit the leader closes
    and every member has returned."""
    team_id = secrets.token_hex(8)
    leader = SharedTeam.join(place(size, 0, team_id, span), evaluator)
    assert leader is not None
    members = [Member(place(size, m, team_id, span)) for m in range(1, size)]
    try:
        for member in members:
            member.start()
            assert member.joined.wait(WAIT) and not member.failed
        yield leader, members
    finally:
        leader.close()
        for member in members:
            member.stop.set()
            member.join(WAIT)
            assert not member.is_alive()


def expected(g: int) -> tuple[np.ndarray, np.ndarray]:
    return evaluator(CONFIG, g, genomes_of(g))


@pytest.mark.parametrize("size", [2, 3])
def test_members_share_every_generation_and_the_leader_gets_it_whole(size: int) -> None:
    with team(size) as (leader, members):
        individuals = 0
        for g in range(CONFIG.generations):
            genomes = genomes_of(g)
            fitness, components, seconds, mine = leader.generation(
                g, genomes, genome_digest(genomes)
            )
            want_f, want_c = expected(g)
            np.testing.assert_array_equal(fitness, want_f)
            np.testing.assert_array_equal(components, want_c)
            assert 0 <= mine <= CONFIG.population and seconds >= 0
            individuals += mine
            assert not segment_path(leader.job.team_id).exists()  # every member mapped it
        for member in members:
            member.join(WAIT)  # each returns after the span's last generation
            assert not member.is_alive()
    helped = [m.individuals for m in members]
    assert all(n > 0 for n in helped), helped  # each took chunks...
    # ...claimed before evaluated: two members take the same chunk only in a rare race
    total = CONFIG.generations * CONFIG.population
    assert total <= individuals + sum(helped) <= 1.1 * total


def test_a_chunk_claimed_but_never_written_is_evaluated_by_the_leader() -> None:
    """A member that dies (or is descheduled) mid-chunk leaves its claim: the leader evaluates
    the chunk itself once nothing came for PATIENCE times its own chunk's time; stale or torn
    writes in the member's region never count."""
    team_id = secrets.token_hex(8)
    leader = SharedTeam.join(place(2, 0, team_id), evaluator)
    assert leader is not None
    try:
        seg, genomes = leader._segment, genomes_of(0)
        key = stamp(0, genome_digest(genomes))
        seg.claims[0, 1:] = key  # a dead member's claims on every chunk but the first
        seg.begin[0, 0, 2], seg.end[0, 0, 2] = key + 1, key  # torn: begun for another
        seg.begin[0, 0, 3], seg.end[0, 0, 3] = stamp(0 + RING, "0"), stamp(0 + RING, "0")
        seg.fitness[0, 0] = -1.0  # garbage where they would be
        fitness, components, _, mine = leader.generation(0, genomes, genome_digest(genomes))
        assert leader.taken_over == seg.chunks - 1
    finally:
        leader.close()
    np.testing.assert_array_equal(fitness, expected(0)[0])
    np.testing.assert_array_equal(components, expected(0)[1])
    assert mine == CONFIG.population
    assert not segment_path(team_id).exists()


def test_a_member_leaves_when_the_leader_ends_the_span_or_falls_silent(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(shared, "MEMBER_WAIT_S", 5.0)
    with team(2) as (leader, [member]):
        genomes = genomes_of(0)
        leader.generation(0, genomes, genome_digest(genomes))
        began = time.monotonic()
        leader.leave(0)
        member.join(WAIT)
        assert not member.is_alive() and time.monotonic() - began < 1.0  # told, not timed out
    monkeypatch.setattr(shared, "MEMBER_WAIT_S", 0.3)
    with team(2) as (leader, [member]):  # the leader publishes nothing: a dead one
        member.join(WAIT)
        assert not member.is_alive()


def test_a_failing_member_costs_the_leader_only_its_chunk() -> None:
    """A member whose evaluator raises leaves its claim unwritten (the worker logs it and
    asks for jobs): the leader evaluates the chunk too and goes on alone."""
    team_id = secrets.token_hex(8)
    leader = SharedTeam.join(place(2, 0, team_id), evaluator)
    assert leader is not None

    def broken(config: RunConfig, generation: int, genomes: np.ndarray) -> Any:
        raise RuntimeError("simulated fault")

    failed = threading.Event()

    def follow() -> None:
        member = SharedTeam.join(place(2, 1, team_id), broken)
        assert member is not None
        try:
            member.follow(threading.Event(), lambda n, s: None)
        except RuntimeError:
            failed.set()
        finally:
            member.close()

    thread = threading.Thread(target=follow)
    thread.start()
    try:
        for g in range(3):
            genomes = genomes_of(g)
            fitness, components, _, _ = leader.generation(g, genomes, genome_digest(genomes))
            np.testing.assert_array_equal(fitness, expected(g)[0])
            np.testing.assert_array_equal(components, expected(g)[1])
    finally:
        leader.close()
        thread.join(WAIT)
    assert failed.is_set() or leader.taken_over == 0  # it failed, unless it never got a chunk


def test_machine_names_what_shares_memory() -> None:
    name = shared.machine()
    assert name == shared.machine() and name.startswith(socket.gethostname())
    assert len(name.split("/")) == 4


def test_a_member_without_its_leaders_file_does_not_join(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """On another machine (same host name) the file never appears; one of another layout
    is never mapped."""
    monkeypatch.setattr(shared, "MEMBER_WAIT_S", 0.2)
    assert SharedTeam.join(place(2, 1, secrets.token_hex(8)), evaluator) is None
    assert "never appeared" in caplog.text
    team_id = secrets.token_hex(8)
    leader = SharedTeam.join(place(2, 0, team_id), evaluator)
    assert leader is not None
    try:
        other = replace(place(2, 1, team_id), config=CONFIG.model_copy(update={"trials": 3}))
        assert SharedTeam.join(other, evaluator) is None
        assert segment_path(team_id).exists()  # not every member mapped it yet
    finally:
        leader.close()
    assert not segment_path(team_id).exists()


def test_a_worker_sweeps_only_old_team_files_whose_leader_is_gone(tmp_path: Any) -> None:
    """A leader SIGKILLed before its members mapped the file leaves its name behind: swept once
    old, unless a process still holds the leader's socket; fresh files are a span starting."""

    def team_file(name: str, age_s: float) -> Any:
        path = tmp_path / f"evocolony-team-{name}"
        path.write_bytes(b"x")
        old = time.time() - age_s
        os.utime(path, (old, old))
        return path

    dead = team_file(secrets.token_hex(8), 2 * shared.STALE_AFTER_S)
    draft = team_file(f"{secrets.token_hex(8)}.draft", 2 * shared.STALE_AFTER_S)
    fresh = team_file(secrets.token_hex(8), 1.0)
    alive_id = secrets.token_hex(8)
    alive = team_file(alive_id, 2 * shared.STALE_AFTER_S)
    other = tmp_path / "unrelated"
    other.write_bytes(b"x")
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as leader:
        leader.bind(f"\0evocolony-team-{alive_id}-0")
        assert sorted(shared.sweep(tmp_path)) == sorted([dead, draft])
    assert fresh.exists() and alive.exists() and other.exists()
    assert shared.sweep(tmp_path) == [alive]  # its leader's socket is gone now
