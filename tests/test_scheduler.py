"""The scheduler as a state machine: calls in, jobs and acknowledgements out, a fake clock, no
threads and no sockets. Fitness is a deterministic function of each genome (or the real
evaluation, which is fast at this size), so a run's told generations are comparable bit for bit
with an undisturbed run and with `evolve`."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from evorobotics.evolution import RunLoop, evaluate_population, evolve
from evorobotics.ga import GAState
from schemas.run import RunConfig, ValidationConfig
from schemas.wire import Job, Result, genome_digest
from server.runs.evaluation import run_job
from server.runs.outbox import Written
from server.runs.policy import SPEED_MAX, SPEED_MIN, Policy, clamp_speed
from server.runs.scheduler import Scheduler
from tests.helpers import (
    WAIT,
    Clock,
    eventually,
    fake_evaluator,
    fake_fitness,
    make_scheduler,
    plausible_forgery,
    reference,
    same_generations,
)

CONFIG = RunConfig(
    population=8,
    generations=4,
    trials=1,
    steps=5,
    job_size=3,
    validation=ValidationConfig(poses=0, test_poses=0),
)
"""Validation off: no champion stages after the last generation (tests/test_choosing.py)."""
FAST = 1e9
"""A speed at which a generation of CONFIG takes far less than span_below_s: spans."""
SLOW = 10.0
"""A speed at which it takes seconds: no spans."""


def result(
    job: Job, worker: str, genomes: np.ndarray | None = None, *, digest: bool = False
) -> Result:
    """The result of one generation of `job` (of `genomes`, a span's own, if given)."""
    genomes = job.genomes if genomes is None else genomes
    return Result(
        key=job.key,
        worker=worker,
        start=job.start,
        stop=job.stop,
        fitness=fake_fitness(genomes)[None],
        components=fake_evaluator(job.config, job.key.generation, genomes)[1][None],
        descriptors=fake_evaluator(job.config, job.key.generation, genomes)[2][None],
        digests=(genome_digest(genomes),) if digest else (),
    )


def span_message(job: Job, loop: RunLoop, k: int, worker: str = "fast") -> Result:
    """The worker evolves `k` generations of its span and sends them as one message."""
    results = []
    for _ in range(k):
        genomes = loop.ask()
        current = job.model_copy(update={"key": job.key.at(loop.generation)})
        results.append(result(current, worker, genomes, digest=True))
        loop.tell(fake_fitness(genomes))
    return results[0].model_copy(
        update={
            "fitness": np.concatenate([r.fitness for r in results if r.fitness is not None]),
            "components": np.concatenate(
                [r.components for r in results if r.components is not None]
            ),
            "descriptors": np.concatenate(
                [r.descriptors for r in results if r.descriptors is not None]
            ),
            "digests": tuple(d for r in results for d in r.digests),
        }
    )


def error_result(job: Job, worker: str) -> Result:
    return Result(key=job.key, worker=worker, start=job.start, stop=job.stop, error="boom")


# cutting ---------------------------------------------------------------------------------------


def test_with_no_worker_known_a_generation_is_cut_by_job_size() -> None:
    sched, _ = make_scheduler()
    sched.add(1, RunLoop(CONFIG), running=True)
    assert sched.counts() == {"pending": 3, "leased": 0, "done": 0}
    jobs = [sched.lease(f"w{i}") for i in range(4)]
    assert [(j.start, j.stop) for j in jobs if j] == [(0, 3), (3, 6), (6, 8)]
    assert jobs[3] is None


@pytest.mark.parametrize(
    ("workers", "per_worker", "expected"),
    [
        (1, 1, [(0, 8)]),
        (2, 1, [(0, 4), (4, 8)]),
        (5, 1, [(0, 3), (3, 6), (6, 8)]),  # never below the run's job_size
        (1, 2, [(0, 4), (4, 8)]),
    ],
)
def test_a_generation_is_cut_per_live_worker(
    workers: int, per_worker: int, expected: list[tuple[int, int]]
) -> None:
    sched, _ = make_scheduler(Policy(jobs_per_worker=per_worker))
    for i in range(workers):
        sched.join(f"w{i}", speed=SLOW)
    sched.join("other-protocol", serving=False)  # never counted
    sched.join("departed")
    sched.leave("departed")  # not live
    sched.add(1, RunLoop(CONFIG), running=True)
    jobs: list[Job] = []
    while (job := sched.lease(f"taker{len(jobs)}")) is not None:
        jobs.append(job)
    assert [(j.start, j.stop) for j in jobs] == expected
    assert all(j.span == 1 and j.state is None for j in jobs)


def test_the_next_generation_is_cut_for_the_workers_live_then() -> None:
    sched, _ = make_scheduler()
    sched.add(1, RunLoop(CONFIG), running=True)  # no worker yet: by job_size
    first = [sched.lease(f"w{i}") for i in range(3)]
    sched.leave("w2")  # its job returns; two live workers remain
    for i, job in enumerate(first[:2]):
        assert job is not None
        assert sched.settle(result(job, f"w{i}")).accepted
    last = sched.lease("w0")
    assert last is not None and (last.start, last.stop) == (6, 8)
    assert sched.settle(result(last, "w0")).accepted
    assert [w.told.generation for w in sched.take_told()] == [0]
    second = [sched.lease("w0"), sched.lease("w1")]
    assert [(j.start, j.stop) for j in second if j] == [(0, 4), (4, 8)]


def test_runs_share_workers_least_recently_served_first() -> None:
    sched, _ = make_scheduler()
    sched.add(1, RunLoop(CONFIG), running=True)
    sched.add(2, RunLoop(CONFIG.model_copy(update={"seed": 1})), running=True)
    order: list[int] = []
    while (job := sched.lease(f"w{len(order)}")) is not None:
        order.append(job.key.run_id)
    assert order == [1, 2, 1, 2, 1, 2]
    assert not sched.has_pending()


def test_a_paused_run_is_not_leased_from_until_resumed() -> None:
    sched, _ = make_scheduler()
    sched.add(1, RunLoop(CONFIG), running=False)
    assert not sched.has_pending() and sched.lease("w") is None
    sched.set_running(1, True)
    assert sched.has_pending()
    job = sched.lease("w")
    assert job is not None and job.key.run_id == 1


# leases ----------------------------------------------------------------------------------------


def test_a_lease_expires_exactly_at_its_deadline_and_goes_to_another_credential() -> None:
    sched, clock = make_scheduler(Policy(lease_unknown_s=30.0))
    sched.add(1, RunLoop(CONFIG), running=True)
    sched.join("b")
    clock.t = 5.0
    job = sched.lease("a")
    assert job is not None and job.lease_s == 30.0
    assert sched.next_deadline() == 35.0
    clock.t = np.nextafter(35.0, 0.0)
    assert sched.expire() == 0
    assert sched.counts()["leased"] == 1
    clock.t = 35.0
    assert sched.expire() == 1
    assert sched.next_deadline() is None
    other = sched.lease("a")  # never its lapsed job again: the next one
    assert other is not None and other.key != job.key
    again = sched.lease("b")
    assert again is not None and again.key == job.key
    late = sched.settle(result(job, "a"))
    assert not late.accepted and "late or duplicate" in late.reason
    assert sched.settle(result(again, "b")).accepted
    assert sched.settle(result(other, "a")).accepted
    assert sched.quarantined() == {}  # a lapse is no error
    assert sched.totals() == {"leased": 3, "done": 2, "requeued": 1, "duplicates_dropped": 1}
    sched.close()


def test_the_measured_speed_sets_the_lease_never_the_claimed_one() -> None:
    """Issue 38, attack 2: a claimed speed of 1e-300 got the longest lease. A worker's first
    lease is `lease_unknown_s` whatever it claims; later ones follow the time its last job
    took, lease to result, on the scheduler's clock."""
    policy = Policy(lease_min_s=1.0, lease_factor=10.0)
    sched, clock = make_scheduler(policy)
    sched.join("a", speed=1e-300)
    sched.add(1, RunLoop(CONFIG), running=True)
    first = sched.lease("a")
    assert first is not None and first.lease_s == policy.lease_unknown_s
    clock.t += 0.5
    claims = result(first, "a").model_copy(update={"robot_steps_per_s": 1e-300})
    assert sched.settle(claims).accepted
    job = sched.lease("a")
    assert job is not None
    steps = (first.stop - first.start) * CONFIG.trials * 5
    measured = steps / 0.5
    want = 10.0 * (job.stop - job.start) * CONFIG.trials * 5 / measured
    assert job.lease_s == pytest.approx(max(want, 1.0))


def test_duplicate_results_are_dropped_and_counted() -> None:
    sched, _ = make_scheduler()
    sched.add(1, RunLoop(CONFIG), running=True)
    job = sched.lease("a")
    assert job is not None
    first = sched.settle(result(job, "a"))
    assert first.accepted and first.key == job.key
    for _ in range(2):
        assert not sched.settle(result(job, "a")).accepted
    assert sched.totals()["duplicates_dropped"] == 2
    assert sched.totals()["done"] == 1
    assert sched.counts() == {"pending": 2, "leased": 0, "done": 1}


def test_only_the_lease_holders_result_counts() -> None:
    sched, _ = make_scheduler()
    sched.add(1, RunLoop(CONFIG), running=True)
    job = sched.lease("holder")
    assert job is not None
    assert not sched.settle(result(job, "stranger")).accepted
    wrong_slice = result(job, "holder").model_copy(update={"start": 1, "stop": 4})
    assert not sched.settle(wrong_slice).accepted
    assert sched.counts()["leased"] == 1  # the holder's lease stands
    assert sched.settle(result(job, "holder")).accepted


def test_a_worker_asking_again_gets_the_job_it_held_until_that_leases_deadline() -> None:
    """Its reply was lost: the same job, leased once. Asking again never extends the lease,
    so no worker holds a job by asking before each deadline."""
    sched, clock = make_scheduler(Policy(lease_unknown_s=30.0))
    sched.add(1, RunLoop(CONFIG), running=True)
    first = sched.lease("a")
    clock.t = 20.0
    again = sched.lease("a")
    assert first is not None and again is not None and again.key == first.key
    assert again.lease_s == 10.0 and sched.next_deadline() == 30.0
    assert sched.counts() == {"pending": 2, "leased": 1, "done": 0}
    assert sched.totals()["requeued"] == 1
    assert sched.settle(result(again, "a")).accepted
    sched.close()


def test_the_only_worker_cannot_hold_a_job_by_asking_again_or_letting_it_lapse() -> None:
    """Its lease ends at the first deadline however it times its asks; then the job is never
    leased to its credential again, and with no other credential live the server's referee
    evaluates it: the run moves on."""
    sched, clock = make_scheduler(Policy(lease_unknown_s=30.0))
    sched.add(1, RunLoop(CONFIG), running=True)
    held = sched.lease("a")
    assert held is not None
    for _ in range(3):  # it asks again just before each deadline
        clock.t += 9.0
        again = sched.lease("a")
        assert again is not None and again.key == held.key
    clock.t += 9.0
    again = sched.lease("a")  # past the first lease's deadline: never that job again
    assert again is not None and again.key != held.key
    clock.t += 31.0
    third = sched.lease("a")  # it let the second lapse too
    assert third is not None and third.key not in (held.key, again.key)
    clock.t += 31.0
    assert sched.expire() == 1  # and the third
    told: list[Written] = []

    def stored() -> bool:
        told.extend(sched.take_told())
        return bool(told)

    assert eventually(stored, WAIT)
    assert told[0].told.generation == 0  # the referee evaluated the jobs it let lapse
    assert sched.quarantined() == {}  # a lapse is no error
    sched.close()


def test_asking_again_never_trades_a_held_job_for_another() -> None:
    """A worker alone with two runs, asking every 29 s: the job it holds comes back each time
    (no fresh lease of the other run's), so the lease lapses at its deadline and the server's
    referee evaluates it; both runs move on."""
    sched, clock = make_scheduler(Policy(lease_unknown_s=30.0))
    sched.add(1, RunLoop(CONFIG), running=True)
    sched.add(2, RunLoop(CONFIG), running=True)
    held = sched.lease("a")
    assert held is not None
    clock.t += 29.0
    again = sched.lease("a")
    assert again is not None and again.key == held.key and again.lease_s == 1.0
    for _ in range(40):
        clock.t += 29.0
        sched.lease("a")
    told: list[Written] = []

    def both() -> bool:
        told.extend(sched.take_told())
        return {w.run_id for w in told} == {1, 2}

    assert eventually(both, WAIT)  # the referee's evaluations of the lapsed jobs
    sched.close()


class Ticking(Clock):
    """A clock that moves `step` s at every reading (the time a call takes)."""

    step = 0.0

    def __call__(self) -> float:
        self.t += self.step
        return self.t


def test_asking_again_just_before_the_deadline_leases_what_is_left_never_zero() -> None:
    clock = Ticking()
    sched = Scheduler(Policy(lease_unknown_s=30.0), clock=clock, wall=lambda: 0.0)
    sched.add(1, RunLoop(CONFIG), running=True)
    held = sched.lease("a")
    assert held is not None
    clock.t, clock.step = 29.4, 0.5  # its deadline passes between the scheduler's readings
    again = sched.lease("a")
    assert again is not None and 0 < again.lease_s <= 0.6
    sched.close()


def test_a_span_messages_speed_is_measured_over_the_whole_message() -> None:
    """Its later generations' leases are made as the message is taken: the speed is the
    message's robot-steps over the time since its first generation's lease, which sets the
    worker's next lease (lease_factor x its robot-steps / that speed)."""
    config = CONFIG.model_copy(update={"generations": 6})
    sched, clock = make_scheduler(Policy(lease_min_s=1e-3, lease_factor=10.0))
    sched.join("fast", speed=FAST)
    sched.add(1, RunLoop(config), running=True)
    job = sched.lease("fast")
    assert job is not None and job.span > 3
    clock.t += 2.0
    assert sched.settle(real_span(job, 3, "fast")).accepted
    sched.leave("fast")  # it returns its span's next generation
    sched.join("fast", speed=FAST)
    following = sched.lease("fast")
    assert following is not None and following.key.generation == 3
    assert following.lease_s == pytest.approx(10.0 * 2.0 / 3)  # 3 generations in 2 s
    sched.close()


def test_leave_releases_at_once() -> None:
    sched, _ = make_scheduler()
    sched.add(1, RunLoop(CONFIG), running=True)
    job = sched.lease("a")
    assert job is not None
    assert sched.leave("a") == [job.key]
    assert sched.counts()["leased"] == 0
    taken = sched.lease("b")
    assert taken is not None and taken.key == job.key
    assert [w.state for w in sched.workers()] == ["gone", "busy"]
    assert not sched.settle(result(job, "a")).accepted
    assert [w.state for w in sched.workers()] == ["gone", "busy"]  # a late result revives not
    sched.add(2, RunLoop(CONFIG), running=True)
    assert sched.counts()["pending"] == 2 + 1  # run 2 cut for "b" alone: one job, not two
    sched.join("a")  # its token again
    assert [w.state for w in sched.workers()] == ["idle", "busy"]


def lease_key(sched: Scheduler, worker: str, key: object) -> Job | None:
    """Lease as `worker` until it gets the job `key` (or nothing more)."""
    while (job := sched.lease(worker)) is not None and job.key != key:
        sched.settle(result(job, worker))
    return job


def test_an_error_result_sends_its_job_to_another_credential_then_to_the_server() -> None:
    """Issue 38, attack 1: a worker's error fails no run. Its job is never leased to that
    credential again; once `max_attempts` credentials erred on it, the server evaluates it."""
    sched, _ = make_scheduler(Policy(max_attempts=2))
    for name in ("a", "a.pc-2", "b", "c"):
        sched.join(name)
    sched.add(1, RunLoop(CONFIG), running=True)
    job = sched.lease("a")
    assert job is not None
    assert sched.settle(error_result(job, "a")).reason == "error recorded"
    again = sched.lease("a.pc-2")  # the same credential: another job
    assert again is not None and again.key != job.key
    retry = lease_key(sched, "b", job.key)
    assert retry is not None and sched.settle(error_result(retry, "b")).accepted
    assert lease_key(sched, "c", job.key) is None  # the server holds it now
    assert eventually(lambda: sched.counts()["done"] == 2, WAIT)  # c's and the server's
    assert sched.settle(result(again, "a.pc-2")).accepted
    (told,) = sched.take_told()
    evaluated = run_job(job, "x").fitness
    assert evaluated is not None
    np.testing.assert_array_equal(told.told.fitness[job.start : job.stop], evaluated[0])
    assert sched.take_failed() == {} and sched.quarantined() == {}
    sched.close()


def test_a_credential_whose_results_err_in_a_row_is_quarantined() -> None:
    """An error counts against its credential once another evaluates the job without one
    (the run's own failure counts against nobody); three in a row quarantine it."""
    sched, _ = make_scheduler(Policy(errors_quarantine=3, jobs_per_worker=5))
    sched.join("b")
    sched.join("rogue")
    sched.add(1, RunLoop(CONFIG.model_copy(update={"population": 30})), running=True)
    for honest in (False, True, False, False, False):  # an accepted result starts the count again
        job = sched.lease("rogue")
        assert job is not None and sched.quarantined() == {}
        sent = result(job, "rogue") if honest else error_result(job, "rogue")
        assert sched.settle(sent).accepted
        if not honest:  # the honest worker evaluates what the rogue erred on
            again = lease_key(sched, "b", job.key)
            assert again is not None and sched.settle(result(again, "b")).accepted
    why = sched.quarantined()["rogue"]
    assert "3 error results in a row" in why and "boom" in why
    assert sched.lease("rogue") is None and sched.lease("rogue.other") is None
    assert sched.lease("b") is not None and sched.take_failed() == {}
    sched.close()


def test_a_job_erred_on_goes_to_the_server_when_the_other_workers_fell_silent() -> None:
    """A worker whose token lives on but that asks nothing (wedged) takes no job: once it was
    silent for `lease_max_s`, a job the others erred on goes to the server."""
    sched, clock = make_scheduler(Policy(lease_max_s=60.0))
    sched.join("alice")
    sched.join("bob")
    sched.add(1, RunLoop(CONFIG), running=True)
    job = sched.lease("alice")
    assert job is not None and sched.settle(error_result(job, "alice")).accepted
    assert sched.counts()["leased"] == 0  # bob may take it
    clock.t += 61.0
    other = sched.lease("alice")  # bob has been silent since
    assert other is None or other.key != job.key
    assert eventually(lambda: sched.counts()["done"] >= 1, WAIT)  # the server's result
    sched.close()


def test_a_run_fails_only_when_the_servers_own_evaluation_fails(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """With no other credential live, the server evaluates the job: a failure there fails the
    run, saying why; an in-process executor's error is the server's own at once."""

    def broken(config: RunConfig, generation: int, genomes: np.ndarray) -> None:
        raise RuntimeError("the physics broke")

    monkeypatch.setattr("server.runs.evaluation.evaluate", broken)
    sched, _ = make_scheduler(Policy())
    sched.add(1, RunLoop(CONFIG), running=True)
    sched.add(2, RunLoop(CONFIG), running=True)
    job = sched.lease("a")
    assert job is not None and job.key.run_id == 1
    assert sched.settle(error_result(job, "a")).accepted
    failed: dict[int, str] = {}
    assert eventually(lambda: failed.update(sched.take_failed()) or 1 in failed, WAIT)
    assert failed == {
        1: "job 0/0 failed in the server's own evaluation: RuntimeError: the physics broke"
    }
    assert sched.quarantined() == {}  # the run's own failure counts against no worker
    sched.join("local-0", listed=False)
    local = sched.lease("local-0")
    assert local is not None and local.key.run_id == 2
    assert sched.settle(error_result(local, "local-0")).accepted
    assert sched.take_failed() == {2: "job 0/0 failed in the server's own evaluation: boom"}
    assert sched.lease("b") is None  # neither run is served any more
    sched.close()


def test_worker_statuses_and_gone_workers_are_kept_until_gone_keep_s() -> None:
    sched, clock = make_scheduler(Policy(gone_keep_s=60.0))
    sched.join("a", host="lab-1", speed=SLOW)
    sched.join("b")
    sched.add(1, RunLoop(CONFIG), running=True)
    job = sched.lease("b")
    assert job is not None
    rows = {w.name: w for w in sched.workers()}
    assert (rows["a"].state, rows["a"].host, rows["a"].robot_steps_per_s) == ("idle", "lab-1", SLOW)
    assert rows["b"].state == "busy"
    sched.settle(result(job, "b"))
    assert {w.name: w.jobs_done for w in sched.workers()} == {"a": 0, "b": 1}
    clock.t = 10.0
    sched.leave("a")
    clock.t = 70.0
    sched.expire()
    assert [(w.name, w.state) for w in sched.workers()] == [("a", "gone"), ("b", "idle")]
    clock.t = 70.001
    sched.expire()
    assert [w.name for w in sched.workers()] == ["b"]
    sched.join("a")  # back: listed again
    assert [w.state for w in sched.workers()] == ["idle", "idle"]


# told generations ------------------------------------------------------------------------------


def test_the_last_result_tells_the_loop_and_the_next_generation_is_installed() -> None:
    sched, _ = make_scheduler()
    sched.add(1, RunLoop(CONFIG), running=True)
    written: list[Written] = []
    for generation in range(CONFIG.generations):
        jobs = [sched.lease(f"w{i}") for i in range(3)]
        assert all(j is not None and j.key.generation == generation for j in jobs)
        for i, job in reversed(list(enumerate(jobs))):  # the order results come in is free
            assert job is not None
            assert sched.settle(result(job, f"w{i}")).accepted
            if i:
                assert sched.take_told() == []
        written += sched.take_told()
    same_generations(written, reference(CONFIG))
    assert all(w.run_id == 1 and w.config == CONFIG for w in written)
    assert sched.lease("w0") is None and not sched.has_pending()


def test_put_back_told_generations_come_first() -> None:
    sched, _ = make_scheduler()
    sched.add(1, RunLoop(CONFIG), running=True)
    written: list[Written] = []
    while len(written) < 2:
        job = sched.lease("w")
        assert job is not None
        sched.settle(result(job, "w"))
        written += sched.take_told()
    assert [w.told.generation for w in written] == [0, 1]
    sched.put_back(written)
    assert [w.told.generation for w in sched.take_told()] == [0, 1]


def test_real_evaluation_through_the_scheduler_equals_evolve_bit_for_bit() -> None:
    config = RunConfig(population=10, generations=3, trials=2, steps=8, job_size=3, seed=7)
    sched, _ = make_scheduler()
    sched.join("a", speed=SLOW)
    sched.join("b", speed=SLOW)
    sched.add(1, RunLoop(config), running=True)
    written: list[Written] = []
    while not (written and written[-1].last):
        a, b = sched.lease("a"), sched.lease("b")
        for job, worker in ((b, "b"), (a, "a")):
            if job is not None:
                assert sched.settle(run_job(job, worker)).accepted
        written += sched.take_told()
    loop = RunLoop(config)
    for w in written:
        fitness, components, descriptors = evaluate_population(config, loop.generation, loop.ask())
        assert w.told.genomes.tobytes() == loop.ask().tobytes()
        assert w.told.fitness.tobytes() == fitness.tobytes()
        assert w.told.components is not None and w.told.descriptors is not None
        assert w.told.components.tobytes() == components.tobytes()
        assert w.told.descriptors.tobytes() == descriptors.tobytes()
        loop.tell(fitness, components, descriptors)
    whole = evolve(config)
    assert [w.told.summary() for w in written] == list(whole.history)
    assert written[-1].told.fitness.tobytes() == whole.fitness.tobytes()
    assert written[-1].told.genomes.tobytes() == whole.genomes.tobytes()
    final = written[-1].told.after.to_arrays()
    assert final.keys() == whole.state.to_arrays().keys()
    for name, array in whole.state.to_arrays().items():
        assert final[name].tobytes() == array.tobytes()


# spans -----------------------------------------------------------------------------------------


def span_job(sched: Scheduler, worker: str = "fast") -> tuple[Job, RunLoop]:
    job = sched.lease(worker)
    assert job is not None and job.span > 1 and job.state is not None
    loop = RunLoop(job.config, GAState.from_arrays(job.state))
    assert loop.generation == job.key.generation
    return job, loop


def span_step(
    sched: Scheduler, job: Job, loop: RunLoop, worker: str = "fast", *, digest: bool = True
) -> bool:
    """The worker evolves one generation of its span and reports it; accepted?"""
    genomes = loop.ask()
    current = job.model_copy(update={"key": job.key.at(loop.generation)})
    ack = sched.settle(result(current, worker, genomes, digest=digest))
    loop.tell(fake_fitness(genomes))
    return ack.accepted and ack.reason == ""


def test_a_fast_worker_gets_the_whole_generation_as_a_span_that_matches_the_run() -> None:
    sched, clock = make_scheduler()
    sched.join("fast", speed=FAST)
    sched.add(1, RunLoop(CONFIG), running=True)
    assert sched.counts() == {"pending": 1, "leased": 0, "done": 0}
    job, loop = span_job(sched)
    assert (job.start, job.stop, job.span, job.key.generation) == (0, 8, CONFIG.generations, 0)
    assert job.genomes.tobytes() == RunLoop(CONFIG).ask().tobytes()
    written = []
    for generation in range(CONFIG.generations):
        clock.t += 1.0
        assert span_step(sched, job, loop)
        written += sched.take_told()
        sched.written(written[-1:])  # as the store does: else the run would wait for it
        if generation + 1 < CONFIG.generations:  # the lease moved on to the next generation
            assert sched.counts() == {"pending": 0, "leased": 1, "done": 0}
            assert sched.next_deadline() == clock.t + Policy().lease_min_s
            assert [w.state for w in sched.workers()] == ["busy"]
    same_generations(written, reference(CONFIG))
    assert sched.totals() == {"leased": 4, "done": 4, "requeued": 0, "duplicates_dropped": 0}


def test_the_last_generation_is_cut_per_worker_not_spanned() -> None:
    config = CONFIG.model_copy(update={"generations": 1})
    sched, _ = make_scheduler()
    sched.join("fast", speed=FAST)
    sched.join("fast2", speed=FAST)
    sched.add(1, RunLoop(config), running=True)
    assert sched.counts()["pending"] == 2


def test_spans_need_every_live_worker_fast() -> None:
    sched, _ = make_scheduler()
    sched.join("fast", speed=FAST)
    sched.join("new")  # no speed yet
    sched.add(1, RunLoop(CONFIG), running=True)
    assert sched.counts()["pending"] == 2
    sched.join("local", speed=FAST, spans=False)  # an in-process thread never spans
    sched.add(2, RunLoop(CONFIG), running=True)
    assert sched.counts()["pending"] == 2 + 3


def test_runs_as_many_as_workers_get_whole_generations_in_spans_however_slow() -> None:
    """A study on few workers: each worker evolves a run of its own, so generations far above
    span_below_s are leased whole, in spans; one run on two workers is still sliced."""
    medium = 400.0  # CONFIG's generation in 0.1 s: sliced, not spanned, while runs are few
    sched, _ = make_scheduler()
    sched.join("a", speed=medium)
    sched.join("b", speed=medium)
    sched.add(1, RunLoop(CONFIG), running=True)
    assert sched.counts()["pending"] == 2  # one run: a slice per worker
    sched.add(2, RunLoop(CONFIG), running=True)
    assert sched.counts()["pending"] == 2 + 1  # run 2 whole
    sliced = sched.lease("a")
    assert sliced is not None and sliced.key.run_id == 1 and sliced.span == 1
    assert (sliced.start, sliced.stop) == (0, 4)
    whole = sched.lease("b")
    assert whole is not None and whole.key.run_id == 2 and whole.state is not None
    assert (whole.start, whole.stop, whole.span) == (0, 8, CONFIG.generations)
    assert sched.settle(result(sliced, "a")).accepted
    rest = sched.lease("a")
    assert rest is not None and (rest.key.run_id, rest.start, rest.stop) == (1, 4, 8)
    assert sched.settle(result(rest, "a")).accepted
    following = sched.lease("a")  # run 1's generation 1, installed while crowded: whole
    assert following is not None and following.key == rest.key.at(1).model_copy(update={"index": 0})
    assert (following.start, following.stop, following.span) == (0, 8, CONFIG.generations - 1)


@pytest.mark.parametrize("bad", ["missing", "wrong"])
def test_a_span_generation_without_the_right_digest_is_an_error_and_ends_spans(bad: str) -> None:
    sched, _ = make_scheduler()
    sched.join("fast", speed=FAST)
    sched.add(1, RunLoop(CONFIG), running=True)
    job, loop = span_job(sched)
    assert span_step(sched, job, loop)  # generation 0 was asked by the server: counts
    genomes = loop.ask()
    current = job.model_copy(update={"key": job.key.at(1)})
    if bad == "wrong":
        genomes = genomes + 1.0  # its GA differs
    ack = sched.settle(result(current, "fast", genomes, digest=bad == "wrong"))
    assert ack.accepted and ack.reason == "error recorded"
    assert [w.told.generation for w in sched.take_told()] == [0]
    again = sched.lease("fast")
    assert again is not None and again.key.generation == 1
    assert again.span == 1 and again.state is None  # no more spans for it
    assert sched.settle(result(again, "fast")).accepted
    # the next generations are cut per worker for it, as for a slow one
    assert sched.counts()["pending"] == 1
    job2 = sched.lease("fast")
    assert job2 is not None and job2.span == 1


def test_pausing_ends_a_span_and_resuming_spans_from_the_recorded_generation() -> None:
    sched, _ = make_scheduler()
    sched.join("fast", speed=FAST)
    sched.add(1, RunLoop(CONFIG), running=True)
    job, loop = span_job(sched)
    assert span_step(sched, job, loop)
    sched.set_running(1, False)
    assert span_step(sched, job, loop)  # the generation leased before the pause completes
    assert not span_step(sched, job, loop)  # then the span ends
    assert sched.counts() == {"pending": 1, "leased": 0, "done": 0}
    assert sched.lease("fast") is None
    sched.set_running(1, True)
    resumed, loop = span_job(sched)
    assert (resumed.key.generation, resumed.span) == (2, 2)
    while not loop.done:
        assert span_step(sched, resumed, loop)
    same_generations(sched.take_told(), reference(CONFIG))


def test_a_span_result_of_several_generations_settles_each() -> None:
    sched, _ = make_scheduler()
    sched.join("fast", speed=FAST)
    sched.add(1, RunLoop(CONFIG), running=True)
    job, loop = span_job(sched)
    batch = span_message(job, loop, 3)
    assert sched.settle(batch).accepted
    assert [w.told.generation for w in sched.take_told()] == [0, 1, 2]
    assert not sched.settle(batch).accepted  # a duplicate batch counts nowhere
    assert sched.totals()["duplicates_dropped"] == 3
    assert span_step(sched, job, loop)
    assert [w.last for w in sched.take_told()] == [True]


@settings(max_examples=200, deadline=None)
@given(
    speed=st.floats(min_value=0.0, allow_nan=False)
    | st.sampled_from([0.0, 1e-300, 5e-324, 1e300, float("inf")]),
    robot_steps=st.integers(1, 10**12),
)
def test_no_speed_claim_gives_a_lease_outside_the_bounds(speed: float, robot_steps: int) -> None:
    policy = Policy(lease_min_s=10.0, lease_max_s=3600.0)
    assert SPEED_MIN <= clamp_speed(speed) <= SPEED_MAX
    assert policy.lease_min_s <= policy.lease_seconds(robot_steps, speed) <= policy.lease_max_s
    sched, clock = make_scheduler(policy)
    clock.t = 100.0
    sched.join("w", speed=speed)
    sched.add(1, RunLoop(CONFIG), running=True)
    job = sched.lease("w")
    assert job is not None
    assert policy.lease_min_s <= job.lease_s <= policy.lease_max_s
    deadline = sched.next_deadline()
    assert deadline is not None
    assert policy.lease_min_s <= deadline - clock.t <= policy.lease_max_s
    assert 1 <= job.span <= CONFIG.generations
    for w in sched.workers():
        assert w.robot_steps_per_s is not None
        assert SPEED_MIN <= w.robot_steps_per_s <= SPEED_MAX


# determinism under any interleaving --------------------------------------------------------------


class FakeWorker:
    """A worker as the scheduler sees it: asks, evaluates (fake fitness), reports; a span's
    generations it evolves itself from the GA state it was sent."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.job: Job | None = None
        self.loop: RunLoop | None = None
        self.in_span = 0
        self.last: Result | None = None

    def ask(self, sched: Scheduler) -> None:
        self.job = sched.lease(self.name)
        self.loop, self.in_span = None, 0
        if self.job is not None and self.job.span > 1:
            assert self.job.state is not None
            self.loop = RunLoop(self.job.config, GAState.from_arrays(self.job.state))

    def report(self, sched: Scheduler) -> None:
        job = self.job
        if job is None:
            return
        if self.loop is None:
            self.last = result(job, self.name)
            sched.settle(self.last)
            self.job = None
            return
        genomes = self.loop.ask()
        current = job.model_copy(update={"key": job.key.at(self.loop.generation)})
        self.last = result(current, self.name, genomes, digest=True)
        ack = sched.settle(self.last)
        self.loop.tell(fake_fitness(genomes))
        self.in_span += 1
        if not ack.accepted or self.in_span == job.span:
            self.job = self.loop = None


ACTIONS = st.lists(
    st.tuples(
        st.sampled_from(["join", "ask", "report", "duplicate", "leave", "tick"]),
        st.integers(0, 3),
        st.sampled_from([None, SLOW, FAST]),
    ),
    max_size=60,
)


def store(sched: Scheduler) -> list[Written]:
    """A store that keeps up: it writes what it takes at once, so the run never waits for it."""
    taken = sched.take_told()
    sched.written(taken)
    return taken


@settings(deadline=None)  # examples: the profile's (conftest.py; `make chaos` runs thousands)
@given(actions=ACTIONS)
@example(  # three leases, all reported, one more lease held while time passes
    actions=[
        ("ask", 0, SLOW),
        ("ask", 1, SLOW),
        ("ask", 2, None),
        ("report", 0, None),
        ("report", 1, SLOW),
        ("report", 2, None),
        ("ask", 0, SLOW),
    ]
)
def test_any_interleaving_tells_the_same_generations_bit_for_bit(
    actions: list[tuple[str, int, float | None]],
) -> None:
    # the drain worker below is live throughout and no job lapses on 10 credentials: the
    # referee, whose evaluation is not these workers' fake one, never takes a job (a lapsed
    # job never goes back to its credential: the drain worker takes it)
    policy = Policy(lease_min_s=10.0, lease_unknown_s=20.0, lease_max_s=1e9, max_attempts=10)
    sched, clock = make_scheduler(policy)
    sched.join("drain")
    workers = [FakeWorker(f"w{i}") for i in range(4)]
    sched.add(1, RunLoop(CONFIG), running=True)
    written: list[Written] = []
    for kind, i, speed in actions:
        worker = workers[i]
        if kind == "join":
            sched.join(worker.name, speed=speed)
        elif kind == "ask":
            worker.ask(sched)
        elif kind == "report":
            worker.report(sched)
        elif kind == "duplicate" and worker.last is not None:
            assert not sched.settle(worker.last).accepted
        elif kind == "leave":
            sched.leave(worker.name)
            worker.job = worker.loop = None
        elif kind == "tick":
            clock.t += 7.0
            sched.expire()
        written += store(sched)
    drain = FakeWorker("drain")
    for _ in range(1000):
        if written and written[-1].last:
            break
        drain.ask(sched)
        if drain.job is None:
            clock.t += 1e4  # whatever the others hold expires
            sched.expire()
        while drain.job is not None:
            drain.report(sched)
        written += store(sched)
    same_generations(written, reference(CONFIG))
    assert sched.take_failed() == {}


ERROR_ACTIONS = st.lists(
    st.tuples(st.sampled_from(["ask", "report", "error", "leave", "tick"]), st.integers(0, 3)),
    max_size=40,
)


@settings(deadline=None)
@given(actions=ERROR_ACTIONS)
def test_any_interleaving_with_error_results_tells_what_evolve_tells(
    actions: list[tuple[str, int]],
) -> None:
    """Issue 38, attack 1, as a property: whichever of four credentials err on whichever
    jobs, leave or let time pass, no run fails and it tells `evolve`'s generations (the jobs
    every live credential erred on are evaluated by the server's referee). Each generation's
    jobs check each other (`Job.checks`): no honest credential is ever quarantined."""
    sched, clock = make_scheduler(Policy(span_below_s=0, errors_quarantine=3, spot_checks=1))
    sched.add(1, RunLoop(CONFIG), running=True)
    held: dict[int, Job | None] = dict.fromkeys(range(4))
    written: list[Written] = []
    for kind, i in actions:
        name, job = f"w{i}", held[i]
        if kind == "ask":
            held[i] = sched.lease(name)
        elif kind in ("report", "error") and job is not None:
            sched.settle(run_job(job, name) if kind == "report" else error_result(job, name))
            held[i] = None
        elif kind == "leave":
            sched.leave(name)
            held[i] = None
        elif kind == "tick":
            clock.t += 7.0
            sched.expire()
        written += store(sched)

    def drained() -> bool:
        nonlocal written
        while (job := sched.lease("drain")) is not None:
            assert sched.settle(run_job(job, "drain")).accepted
            written += store(sched)
        clock.t += 1e4  # whatever the others hold expires; the referee's lease never does
        sched.expire()
        written += store(sched)
        return bool(written) and written[-1].last

    assert eventually(drained, WAIT)
    same_generations(written, reference(CONFIG, evaluate_population))
    assert sched.take_failed() == {}
    assert not [why for why in sched.quarantined().values() if "claimed" in why]
    sched.close()


@pytest.mark.parametrize(
    ("hosts", "threads", "first"),
    [
        (("pc", "pc"), 2, (0, 8)),  # one machine's cores, shared: slices would gain nothing
        (("pc", "pc"), 1, (0, 4)),  # a core each: the generation is cut in two
        (("pc-1", "pc-2"), 2, (0, 4)),  # two machines
    ],
)
def test_workers_sharing_a_hosts_cores_get_whole_generations(
    hosts: tuple[str, str], threads: int, first: tuple[int, int]
) -> None:
    sched, _ = make_scheduler()
    for name, host in zip(("a", "b"), hosts, strict=True):
        sched.join(name, host=host, threads=threads, speed=SLOW)
    sched.add(1, RunLoop(CONFIG), running=True)
    job = sched.lease("a")
    assert job is not None and (job.start, job.stop) == first


def test_a_run_whose_store_lags_leases_nothing_until_the_writes_are_in() -> None:
    """A store that blocks or refuses writes (or a writer that stopped) stops its runs: once
    a told generation has waited `store_lag_s` nothing is leased, and `written` lets the run
    go on."""
    config = RunConfig(population=4, generations=6, trials=1, steps=5, job_size=4)
    sched, clock = make_scheduler(Policy(store_lag_s=0.25, write_now=2, span_below_s=0))
    sched.add(1, RunLoop(config), running=True)
    for _ in range(2):
        job = sched.lease("w")
        assert job is not None and sched.settle(result(job, "w")).accepted
    assert sched.told_many.is_set()  # write_now told: the store is asked to write now
    clock.t += 0.25
    assert sched.has_pending()  # within store_lag_s: a store that keeps up costs nothing
    clock.t += 0.01
    assert sched.lease("w") is None and not sched.has_pending()
    woken: list[bool] = []
    sched.add_listener(lambda: woken.append(True))
    taken = sched.take_told()
    assert sched.lease("w") is None  # taken is not written: the store may still refuse it
    sched.written(taken)
    assert woken and sched.has_pending()
    job = sched.lease("w")
    assert job is not None and job.key.generation == 2


def test_a_span_ends_with_the_message_that_finds_its_store_lagging() -> None:
    """The generations a worker already evolved in one message all count; then its lease
    does not move on, so its next message is refused and the span ends."""
    config = RunConfig(population=8, generations=8, trials=1, steps=5, job_size=3)
    sched, clock = make_scheduler(Policy(store_lag_s=0.25))
    sched.join("fast", speed=FAST)
    sched.add(1, RunLoop(config), running=True)
    job, loop = span_job(sched)
    assert span_step(sched, job, loop)  # generation 0 told, not written
    clock.t += 0.3
    batch = span_message(job, loop, 2)
    assert sched.settle(batch).accepted
    assert sched.counts() == {"pending": 1, "leased": 0, "done": 0}  # the lease did not move on
    assert not span_step(sched, job, loop)  # the worker's next generation: refused
    told = sched.take_told()
    assert [w.told.generation for w in told] == [0, 1, 2]
    sched.written(told)
    following, _ = span_job(sched)  # the run goes on from the last recorded generation
    assert following.key.generation == 3


# spot-checks -----------------------------------------------------------------------------------

CHECKED = Policy(spot_checks=64)
"""Every individual of a result re-evaluated (at most 64 a result): a forgery cannot pass."""


def honest(job: Job, worker: str) -> Result:
    """What an honest worker returns: the real evaluation of the job's slice."""
    return run_job(job, worker)


def forged(job: Job, worker: str) -> Result:
    """An honest result with every claim replaced by `plausible_forgery`'s."""
    real = honest(job, worker)
    assert real.components is not None
    fitness, components = plausible_forgery(job.config, real.components)
    return real.model_copy(update={"fitness": fitness, "components": components})


def real_span(job: Job, k: int, worker: str, forge_from: int | None = None) -> Result:
    """`k` generations of a span evaluated for real, sent as one message; from generation
    `forge_from` on its fitness is forged (and the GA follows the forgery, as a rogue's)."""
    assert job.state is not None
    loop = RunLoop(job.config, GAState.from_arrays(job.state))
    fitness, components, descriptors, digests = [], [], [], []
    for i in range(k):
        genomes = loop.ask()
        f, c, d = evaluate_population(job.config, loop.generation, genomes)
        if forge_from is not None and i >= forge_from:
            f, c = plausible_forgery(job.config, c)
        fitness.append(f)
        components.append(c)
        descriptors.append(d)
        digests.append(genome_digest(genomes))
        loop.tell(f, c, d)
    return Result(
        key=job.key,
        worker=worker,
        start=0,
        stop=job.config.population,
        fitness=np.stack(fitness),
        components=np.stack(components),
        descriptors=np.stack(descriptors),
        digests=tuple(digests),
    )


def drain_honestly(sched: Scheduler, worker: str) -> list[Written]:
    """`worker` evaluates every job left; the generations told (stored at once)."""
    told: list[Written] = []
    while (job := sched.lease(worker)) is not None:
        assert sched.settle(honest(job, worker)).accepted
        taken = sched.take_told()
        sched.written(taken)
        told += taken
    return told


def test_an_honest_result_passes_its_spot_check() -> None:
    """One job of a generation: its result is checked as it arrives, here."""
    sched, _ = make_scheduler(Policy(spot_checks=1))
    sched.join("w", speed=1e6)  # one worker: the generation is one job
    sched.add(1, RunLoop(CONFIG), running=True)
    job = sched.lease("w")
    assert job is not None and (job.start, job.stop, job.checks) == (0, 8, None)
    assert sched.settle(honest(job, "w")).accepted
    steps = CONFIG.trials * (CONFIG.steps or 0)
    assert sched.spot_totals() == {
        "results_checked": 1,
        "individuals_checked": 1,
        "robot_steps_checked": steps,
        "mismatches": 0,
    }
    assert sched.quarantined() == {}


def test_a_generation_in_several_jobs_is_checked_by_its_workers_against_each_other(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Each job also evaluates an individual of the job before it (`Job.checks`, drawn with
    secrets); once all are in, each pair is compared bit for bit: the server evaluates
    nothing while the workers agree."""
    sched, _ = make_scheduler(Policy(spot_checks=1))
    sched.add(1, RunLoop(CONFIG), running=True)
    names = ["a", "b", "c"]
    jobs = [sched.lease(name) for name in names]
    assert all(job is not None and job.checks is not None for job in jobs)
    asked = RunLoop(CONFIG).ask()
    slots = [(0, 3), (3, 6), (6, 8)]
    for k, job in enumerate(jobs):
        assert job is not None and job.checks is not None and len(job.checks) == 1
        start, stop = slots[k - 1]
        assert any(np.array_equal(job.checks[0], g) for g in asked[start:stop])
    results = [honest(job, name) for job, name in zip(jobs, names, strict=True) if job]

    def server_evaluates(*args: object) -> None:
        raise AssertionError("the server evaluated while the workers agreed")

    monkeypatch.setattr("server.runs.evaluation.evaluate", server_evaluates)
    assert all(sched.settle(result).accepted for result in results)
    assert [w.told.generation for w in sched.take_told()] == [0]
    assert sched.spot_totals() == {
        "results_checked": 3,
        "individuals_checked": 3,
        "robot_steps_checked": 3 * CONFIG.trials * (CONFIG.steps or 0),
        "mismatches": 0,
    }


def test_a_worker_that_lies_about_anothers_individuals_is_the_one_quarantined() -> None:
    """The workers' checks disagree: the server's own evaluation finds the checker lied, so
    only it is quarantined; the job it checked stands, and the generation waits for its own."""
    sched, _ = make_scheduler(Policy(spot_checks=2))
    sched.add(1, RunLoop(CONFIG), running=True)
    jobs = [sched.lease(name) for name in ("a", "liar", "c")]
    assert all(jobs) and jobs[1] is not None
    results = [honest(job, name) for job, name in zip(jobs, ("a", "liar", "c"), strict=True) if job]
    lie = results[1]
    assert lie.fitness is not None and lie.components is not None and lie.checks == 2
    fitness, components = lie.fitness.copy(), lie.components.copy()
    forged_fitness, forged_components = plausible_forgery(CONFIG, components[:, -2:])
    fitness[:, -2:], components[:, -2:] = forged_fitness, forged_components  # job 0's two
    results[1] = lie.model_copy(update={"fitness": fitness, "components": components})
    assert all(sched.settle(result).accepted for result in results[:2])
    ack = sched.settle(results[2])
    assert ack.accepted
    assert set(sched.quarantined()) == {"liar"} and "claimed fitness" in sched.quarantined()["liar"]
    assert sched.counts() == {"pending": 1, "leased": 0, "done": 2}
    assert [w.told.generation for w in drain_honestly(sched, "a")][:1] == [0]


def forged_but_checked(job: Job, worker: str, checked: np.ndarray) -> Result:
    """A forger that knows which of its slot's individuals are checked (`checked`: their
    genomes, from a job it was leased): every other individual forged."""
    real = honest(job, worker)
    assert real.fitness is not None and real.components is not None
    n = job.stop - job.start
    known = [i for i, g in enumerate(job.genomes) if any(np.array_equal(g, c) for c in checked)]
    fitness, components = real.fitness.copy(), real.components.copy()
    fake_f, fake_c = plausible_forgery(job.config, components[:, :n])
    for i in set(range(n)) - set(known):
        fitness[:, i], components[:, i] = fake_f[:, i], fake_c[:, i]
    return real.model_copy(update={"fitness": fitness, "components": components})


@pytest.mark.parametrize("how", ["erred", "left"])
def test_a_credential_that_saw_its_slots_checks_is_checked_afresh_by_the_server(
    how: str,
) -> None:
    """A credential leased the job that carries slot 1's check rows, filled slot 1 forging
    every row but those, and dropped that job (an error, or that name's token vanished). Its checker agrees on them, but the server checks others it drew afresh:
    the forgery is caught, and the generation told is the true one."""
    config = CONFIG.model_copy(update={"population": 6})  # slots 0:3 and 3:6
    sched, _ = make_scheduler(Policy(spot_checks=1, span_below_s=0))
    first, second = ("L", "L") if how == "erred" else ("L.a", "L.b")
    for name in ("H", first, second):
        sched.join(name, speed=SLOW)
    sched.add(1, RunLoop(config), running=True)
    shown = sched.lease(first)
    assert shown is not None and shown.key.index == 0 and shown.checks is not None
    if how == "erred":
        error = Result(
            key=shown.key, worker=first, start=shown.start, stop=shown.stop, error="oops"
        )
        assert sched.settle(error).reason == "error recorded"
    slot1 = sched.lease(second)
    assert slot1 is not None and slot1.key.index == 1
    sched.settle(forged_but_checked(slot1, second, shown.checks))
    if how == "left":  # no error recorded against it at all
        assert sched.leave(first) == [shown.key]
    checker = sched.lease("H")
    assert checker is not None and checker.key.index == 0
    sched.settle(honest(checker, "H"))
    assert {name.partition(".")[0] for name in sched.quarantined()} == {"L"}
    told = drain_honestly(sched, "H")
    truth, _, _ = evaluate_population(config, 0, RunLoop(config).ask())
    assert told[0].told.generation == 0 and told[0].told.fitness.tobytes() == truth.tobytes()
    sched.close()


def test_a_result_without_its_jobs_checks_is_its_credentials_error() -> None:
    """Its job goes to others (here none is live: the server's referee), never back to it."""
    sched, _ = make_scheduler(Policy(spot_checks=1))
    sched.add(1, RunLoop(CONFIG), running=True)
    job = sched.lease("w")
    assert job is not None and job.checks is not None
    full = honest(job, "w")
    assert full.fitness is not None and full.components is not None and full.descriptors is not None
    n = job.stop - job.start
    bare = full.model_copy(
        update={
            "checks": 0,
            "fitness": full.fitness[:, :n],
            "components": full.components[:, :n],
            "descriptors": full.descriptors[:, :n],
        }
    )
    assert sched.settle(bare).reason == "error recorded"
    assert sched.counts()["pending"] == 2 and sched.quarantined() == {}
    again = sched.lease("w")
    assert again is not None and again.start != job.start
    sched.close()


def test_a_forged_result_quarantines_its_worker_and_requeues_its_generation() -> None:
    """The forgery completes its generation: the workers' checks disagree, the server's own
    evaluation says who lied, and the liar's results return to pending."""
    sched, _ = make_scheduler(CHECKED)
    sched.add(1, RunLoop(CONFIG), running=True)
    first, other, last = sched.lease("rogue"), sched.lease("honest"), sched.lease("rogue2")
    assert first is not None and other is not None and last is not None
    assert sched.settle(honest(first, "rogue")).accepted  # honest once
    assert sched.settle(honest(other, "honest")).accepted
    sched.leave("rogue2")  # the third slice returns, and goes to the rogue
    again = sched.lease("rogue")
    assert again is not None and (again.start, again.stop) == (6, 8)
    ack = sched.settle(forged(again, "rogue"))
    assert not ack.accepted and "spot-check" in ack.reason
    why = sched.quarantined()["rogue"]
    assert "run 1 generation 0 individual" in why and "claimed fitness" in why
    # its honest result of this generation is discarded too: slices 0:3 and 6:8 pending again
    assert sched.counts() == {"pending": 2, "leased": 0, "done": 1}
    assert sched.take_told() == []  # nothing of the generation was told
    assert sched.lease("rogue") is None  # no more jobs, ever
    assert not sched.settle(honest(first, "rogue")).accepted
    assert sched.spot_totals()["mismatches"] == 1
    told = drain_honestly(sched, "honest")
    expected = RunLoop(CONFIG)
    fitness, _, _ = evaluate_population(CONFIG, 0, expected.ask())
    assert told[0].told.fitness.tobytes() == fitness.tobytes()
    assert [w.name for w in sched.workers()] == ["honest", "rogue", "rogue2"]


def test_quarantine_outlives_gone_keep_and_the_worker_stays_listed() -> None:
    sched, clock = make_scheduler(Policy(spot_checks=3, gone_keep_s=1.0))
    sched.join("rogue", speed=SLOW)  # the generation is one job: checked as it arrives
    sched.add(1, RunLoop(CONFIG), running=True)
    job = sched.lease("rogue")
    assert job is not None and not sched.settle(forged(job, "rogue")).accepted
    sched.leave("rogue")
    clock.t += 10.0
    sched.expire()
    assert [w.name for w in sched.workers()] == ["rogue"] and "rogue" in sched.quarantined()
    sched.join("rogue")  # coming back changes nothing
    assert sched.lease("rogue") is None


def test_quarantine_covers_every_name_of_the_credential() -> None:
    """Roles let zenoh user `lab` act as `lab` and `lab.*`: a forgery by one of its names
    stops them all, discards their results in flight, and a new name under it gets nothing."""
    sched, _ = make_scheduler(CHECKED)
    sched.add(1, RunLoop(CONFIG), running=True)
    sibling, rogue, other = sched.lease("lab.pc-1"), sched.lease("lab.pc-2"), sched.lease("x")
    assert sibling is not None and rogue is not None and other is not None
    assert sched.settle(honest(sibling, "lab.pc-1")).accepted
    assert sched.settle(forged(rogue, "lab.pc-2")).accepted  # judged once all are in
    assert sched.settle(honest(other, "x")).accepted
    assert set(sched.quarantined()) == {"lab.pc-1", "lab.pc-2"}
    assert sched.counts()["done"] == 1  # the sibling's result is discarded too
    for name in ("lab", "lab.pc-1", "lab.new"):
        assert sched.lease(name) is None
    assert sched.lease("laboratory") is not None  # another credential


@pytest.mark.parametrize("what", ["components", "descriptors"])
def test_forged_components_or_descriptors_quarantine_as_forged_fitness_does(what: str) -> None:
    """Quality-diversity strategies select on descriptors: they are checked bit for bit too."""
    sched, _ = make_scheduler(CHECKED)
    sched.join("rogue", speed=SLOW)  # the generation is one job: checked as it arrives
    sched.add(1, RunLoop(CONFIG), running=True)
    job = sched.lease("rogue")
    assert job is not None
    real = honest(job, "rogue")
    claimed = getattr(real, what).copy()
    first = (0,) * claimed.ndim
    claimed[first] = 0.05 if claimed[first] != 0.05 else 0.1  # within the trial's physics
    ack = sched.settle(real.model_copy(update={what: claimed}))
    assert not ack.accepted and "spot-check" in ack.reason
    assert f"claimed {what}" in sched.quarantined()["rogue"]


@pytest.mark.parametrize("claim", [1.5, -0.25, np.nan, np.inf])
def test_descriptors_no_maze_gives_are_refused_as_forgery_with_spot_checks_off(
    claim: float,
) -> None:
    """Descriptors are fractions of the maze: a claim outside [0, 1] (or not a number) is a
    forgery like a fitness beyond physics, refused, counted and its credential quarantined."""
    sched, _ = make_scheduler(Policy(spot_checks=0))
    sched.add(1, RunLoop(CONFIG), running=True)
    job = sched.lease("rogue")
    assert job is not None
    real = honest(job, "rogue")
    assert real.descriptors is not None
    claimed = real.descriptors.copy()
    claimed[0, -1, 3] = claim
    ack = sched.settle(real.model_copy(update={"descriptors": claimed}))
    assert not ack.accepted and "a descriptor outside [0, 1]" in ack.reason
    assert "run 1 generation 0: a descriptor outside [0, 1]" in sched.quarantined()["rogue"]
    assert sched.spot_totals()["mismatches"] == 1
    assert sched.counts()["leased"] == 0  # its job is pending again, for others
    assert drain_honestly(sched, "honest")[0].told.generation == 0


def test_with_spot_checks_off_a_forgery_is_accepted() -> None:
    sched, _ = make_scheduler(Policy(spot_checks=0))
    sched.add(1, RunLoop(CONFIG), running=True)
    job = sched.lease("w")
    assert job is not None and sched.settle(forged(job, "w")).accepted
    assert sched.spot_totals()["results_checked"] == 0 and sched.quarantined() == {}


def test_the_servers_own_evaluators_are_not_spot_checked() -> None:
    sched, _ = make_scheduler(CHECKED)
    sched.join("local-0", spans=False, listed=False)
    sched.add(1, RunLoop(CONFIG), running=True)
    job = sched.lease("local-0")
    assert job is not None and sched.settle(forged(job, "local-0")).accepted
    assert sched.spot_totals()["results_checked"] == 0


def test_a_spans_later_generations_are_checked_before_any_is_told() -> None:
    config = CONFIG.model_copy(update={"generations": 6})
    sched, _ = make_scheduler(CHECKED)
    sched.join("fast", speed=FAST)
    sched.add(1, RunLoop(config), running=True)
    job = sched.lease("fast")
    assert job is not None and job.span > 2
    # honest for two generations, every individual checked: the GA on the claims is replayed
    assert sched.settle(real_span(job, 2, "fast")).accepted
    told = sched.take_told()
    assert [w.told.generation for w in told] == [0, 1]
    sched.written(told)
    following = sched.lease("fast")  # the span's lease moved on: asking again returns it
    assert following is not None and following.key.generation == 2 and following.span > 1
    ack = sched.settle(real_span(following, 3, "fast", forge_from=2))
    assert not ack.accepted and "generation 4" in sched.quarantined()["fast"]
    assert sched.take_told() == []  # generations 2 and 3 (honest) not told either
    assert sched.counts() == {"pending": 1, "leased": 0, "done": 0}


def test_a_span_message_is_checked_among_the_generations_it_can_complete() -> None:
    config = CONFIG.model_copy(update={"generations": 6})
    sched, _ = make_scheduler(CHECKED)
    sched.join("fast", speed=FAST)
    sched.add(1, RunLoop(config), running=True)
    job = sched.lease("fast")
    assert job is not None and job.span > 2
    sched.set_running(1, False)  # paused: generation 0 completes, the span ends there
    assert sched.settle(real_span(job, 2, "fast", forge_from=1)).accepted
    assert [w.told.generation for w in sched.take_told()] == [0]
    assert sched.quarantined() == {}  # generation 1 was dropped, never counted
    assert sched.spot_totals()["individuals_checked"] == config.population
