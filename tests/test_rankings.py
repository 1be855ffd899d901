"""A run's candidates ranked in a robot's world as jobs (`Scheduler.rank`): the `rank` and
`fit` replacement policies' rankings are the workers' simulation, cut by candidate, and equal
`rank_in_world` bit for bit; the server ranks them itself only while no worker is live."""

from __future__ import annotations

import threading
from concurrent.futures import Future
from pathlib import Path

import numpy as np
import pytest

from evorobotics.evolution import Ranked, rank_in_world, ranking_config
from schemas.run import RunConfig, ValidationConfig
from schemas.wire import Job, JobKey
from schemas.world import World
from server.core.db import make_engine, session_factory
from server.core.errors import NotFoundError
from server.robots.replacement import Replacements
from server.robots.settings import RobotSettings
from server.runs.evaluation import run_job
from server.runs.policy import Policy
from server.runs.scheduler import Scheduler
from tests.helpers import (
    QUICK,
    WAIT,
    completed_run,
    eventually,
    make_scheduler,
    random_controller,
    serve,
)

SLOW = 10.0
"""A worker speed at which no generation is a span."""
CONFIG = RunConfig(
    network="reactive",
    validation=ValidationConfig(poses=4, steps=60, candidates=6, test_poses=0),
)
CALIBRATED = World(whisker_range=(0.03, 0.05, 0.08, 0.05, 0.1), motor_gain=(1.0, 0.9))
"""A robot's calibrated world: whiskers and wheels of its own."""
CANDIDATES = np.stack([random_controller(seed).weights for seed in range(6)])


def same(a: Ranked, b: Ranked) -> bool:
    """Order and every score, bit for bit."""
    return a[0].tolist() == b[0].tolist() and a[1].scores().tobytes() == b[1].scores().tobytes()


def settle_all(sched: Scheduler, names: list[str]) -> list[Job]:
    """Every worker leases and settles honestly until nothing is left; the jobs."""
    jobs: list[Job] = []
    while held := [(n, j) for n in names if (j := sched.lease(n)) is not None]:
        for name, job in held:
            assert sched.settle(run_job(job, name)).accepted
            jobs.append(job)
    return jobs


@pytest.mark.parametrize("workers", [1, 3])
def test_a_ranking_is_cut_per_worker_and_is_rank_in_world_bit_for_bit(workers: int) -> None:
    sched, _ = make_scheduler()
    names = [f"w{i}" for i in range(workers)]
    for name in names:
        sched.join(name, speed=SLOW)
    future: Future[Ranked] = sched.rank(CONFIG, CALIBRATED, CANDIDATES)
    assert sched.rank(CONFIG, CALIBRATED, CANDIDATES) is future  # asked again: the same
    jobs = settle_all(sched, names)
    assert [(j.key.stage, j.start, j.stop) for j in jobs] == [
        ("rank", a, a + 6 // workers) for a in range(0, 6, 6 // workers)
    ]
    assert all(j.config == ranking_config(CONFIG, CALIBRATED) for j in jobs)
    assert future.done() and same(future.result(), rank_in_world(CONFIG, CANDIDATES, CALIBRATED))
    sched.close()


def test_with_no_live_worker_the_server_ranks_itself() -> None:
    sched, _ = make_scheduler()
    future = sched.rank(CONFIG, CONFIG.world, CANDIDATES)
    assert same(future.result(WAIT), rank_in_world(CONFIG, CANDIDATES, CONFIG.world))
    assert sched.totals()["leased"] == 0  # the referee's leases are not a worker's
    sched.close()


def test_a_rankings_forged_rows_quarantine_and_return_to_pending() -> None:
    sched, _ = make_scheduler(Policy(spot_checks=10))
    for name in ("honest", "cheat"):
        sched.join(name, speed=SLOW)
    future = sched.rank(CONFIG, CALIBRATED, CANDIDATES)
    forged = sched.lease("cheat")
    assert forged is not None and forged.key.stage == "rank"
    true = run_job(forged, "cheat")
    assert true.scores is not None
    crowned = true.scores.copy()
    crowned[:, 2] = 1.0  # every candidate roams on every pose: only a re-run tells
    ack = sched.settle(true.model_copy(update={"scores": crowned}))
    assert not ack.accepted and "rank row" in sched.quarantined()["cheat"]
    settle_all(sched, ["honest", "cheat"])
    assert same(future.result(WAIT), rank_in_world(CONFIG, CANDIDATES, CALIBRATED))
    sched.close()


def test_a_ranking_its_only_worker_lets_lapse_is_the_servers() -> None:
    """The worker takes a job and goes silent with its token held: once the lease expires the
    job is never its credential's again, and with no other worker live the referee ranks it."""
    sched, clock = make_scheduler(Policy(lease_unknown_s=30.0))
    sched.join("silent", speed=SLOW)
    future = sched.rank(CONFIG, CALIBRATED, CANDIDATES)
    held = sched.lease("silent")
    assert held is not None and held.key.stage == "rank"
    clock.t += 31.0
    assert sched.expire() == 1
    assert sched.lease("silent") is None  # never that job again
    assert same(future.result(WAIT), rank_in_world(CONFIG, CANDIDATES, CALIBRATED))
    sched.close()


def test_a_ranking_whose_only_worker_is_quarantined_is_the_servers() -> None:
    sched, _ = make_scheduler(Policy(spot_checks=10))
    sched.join("cheat", speed=SLOW)
    future = sched.rank(CONFIG, CALIBRATED, CANDIDATES)
    forged = sched.lease("cheat")
    assert forged is not None
    true = run_job(forged, "cheat")
    assert true.scores is not None
    crowned = true.scores.copy()
    crowned[:, 2] = 1.0
    assert not sched.settle(true.model_copy(update={"scores": crowned})).accepted
    assert "cheat" in sched.quarantined()
    assert same(future.result(WAIT), rank_in_world(CONFIG, CANDIDATES, CALIBRATED))
    sched.close()


def test_bad_candidates_are_refused_before_any_job() -> None:
    sched, _ = make_scheduler()
    sched.join("a", speed=SLOW)
    with pytest.raises(ValueError, match="for a network of"):
        sched.rank(CONFIG, CALIBRATED, CANDIDATES[:, :-1])
    with pytest.raises(ValueError, match="NaN or infinity"):
        sched.rank(CONFIG, CALIBRATED, np.full_like(CANDIDATES, np.nan))
    with pytest.raises(ValueError, match="candidates to rank"):
        sched.rank(CONFIG, CALIBRATED, np.concatenate([CANDIDATES, CANDIDATES, CANDIDATES]))
    with pytest.raises(ValueError, match="maze"):
        sched.rank(CONFIG.model_copy(update={"maze": "nowhere"}), CALIBRATED, CANDIDATES)
    assert not sched.has_pending() and sched.lease("a") is None
    sched.close()


def test_a_ranking_jobs_wire_checks_its_config_and_rows() -> None:
    config = ranking_config(CONFIG, CALIBRATED)
    key = JobKey(run_id=7, generation=0, index=0, stage="rank")
    job = Job(key=key, start=0, stop=6, config=config, genomes=CANDIDATES)
    assert run_job(job, "w").scores is not None
    with pytest.raises(ValueError, match="generation 0"):
        Job(key=key.at(1), start=0, stop=6, config=config, genomes=CANDIDATES)
    gap = config.model_copy(update={"reality_gap": "on"})
    with pytest.raises(ValueError, match="without a reality gap"):
        Job(key=key, start=0, stop=6, config=gap, genomes=CANDIDATES)
    with pytest.raises(ValueError, match="slice 0:13 outside 12"):
        Job(key=key, start=0, stop=13, config=config, genomes=np.ones((13, CANDIDATES.shape[1])))


def test_a_ranking_never_holds_up_another_and_a_failed_one_is_asked_anew(tmp_path: Path) -> None:
    """`Replacements` over a scheduler's `rank`: a ranking its workers have not finished
    leaves the others to start, and a failed one answers NotFoundError ("ask again", which the
    stuck robot's policy falls back on) and is asked of the scheduler again, never cached."""
    with serve(tmp_path) as served:
        first, second = completed_run(served.url, QUICK), completed_run(served.url, QUICK)
    engine = make_engine(f"sqlite:///{tmp_path / 'colony.db'}")
    asked: list[tuple[Future[Ranked], Ranked]] = []
    lock = threading.Lock()

    def rank(config: RunConfig, world: World, genomes: np.ndarray) -> Future[Ranked]:
        """The scheduler's ranking, resolved when the test says."""
        future: Future[Ranked] = Future()
        with lock:
            asked.append((future, rank_in_world(config, genomes, world)))
        return future

    replacements = Replacements(session_factory(engine), RobotSettings(), None, rank)
    sessions = session_factory(engine)
    with sessions() as db:
        assert replacements.ranking(db, first, None, wait=False) is None
        assert eventually(lambda: len(asked) == 1, WAIT)
        assert replacements.ranking(db, second, None, wait=False) is None  # not behind first
        assert eventually(lambda: len(asked) == 2, WAIT)
        asked[0][0].set_exception(RuntimeError("its workers failed"))
        with pytest.raises(NotFoundError, match=r"its workers failed.*ask again"):
            replacements.ranking(db, first, None, wait=False)
        assert replacements.ranking(db, first, None, wait=False) is None  # asked anew
        assert eventually(lambda: len(asked) == 3, WAIT)
        pending, ranked = asked[2]
        pending.set_result(ranked)
        ranking = replacements.ranking(db, first, None, wait=True)
        assert ranking is not None and ranking.run_id == first
    replacements.close()
    with sessions() as db, pytest.raises(NotFoundError, match="stopping"):
        replacements.ranking(db, second, None, wait=True)  # never waits past close
    engine.dispose()


def test_a_robots_stuck_requests_start_at_most_one_new_ranking_a_minute(tmp_path: Path) -> None:
    """A robot rotating through many runs' champions would start a full ranking (leased
    before any run's jobs) with every stuck request: its second new ranking within
    RANKING_EVERY_S answers "ask again later"; a ranking already started is anyone's, and an
    operator's push (no asker) is not limited."""
    with serve(tmp_path) as served:
        first, second = completed_run(served.url, QUICK), completed_run(served.url, QUICK)
    engine = make_engine(f"sqlite:///{tmp_path / 'colony.db'}")
    asked: list[Future[Ranked]] = []

    def rank(config: RunConfig, world: World, genomes: np.ndarray) -> Future[Ranked]:
        future: Future[Ranked] = Future()
        asked.append(future)
        return future

    replacements = Replacements(session_factory(engine), RobotSettings(), None, rank)
    with session_factory(engine)() as db:
        assert replacements.ranking(db, first, None, wait=False, asker="r1") is None
        with pytest.raises(NotFoundError, match=r"robot r1 started a ranking .* ask again later"):
            replacements.ranking(db, second, None, wait=False, asker="r1")
        assert replacements.ranking(db, first, None, wait=False, asker="r2") is None  # started
        assert replacements.ranking(db, second, None, wait=False, asker="r2") is None
        assert replacements.ranking(db, second, None, wait=False) is None
        assert eventually(lambda: len(asked) == 2, WAIT)  # first's and second's, once each
    replacements.close()
    engine.dispose()
