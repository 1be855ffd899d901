"""The server's lease, span and job-size policy: the scheduler's arithmetic, without its state.

`Policy` sizes leases from the speed the scheduler measured, spans and jobs from the speeds the
live workers claim (which they can only waste), and bounds retries; `clamp_speed` bounds every
reported speed first.
"""

from __future__ import annotations

from dataclasses import dataclass

from evorobotics.evaluate import robot_steps
from evorobotics.strategies import traits
from schemas.run import RunConfig
from server.core.settings import Settings

SPEED_MIN = 1.0
SPEED_MAX = 1e9
"""Robot-steps/s a worker may claim: clamped into this range, so no report gives a lease
beyond `lease_max_s` or a span beyond the run (numba reaches about 1e7 on one core)."""


@dataclass(frozen=True)
class Policy:
    """Lease, span, job-size and retry policy; the defaults serve a lab network."""

    lease_min_s: float = 10.0
    lease_max_s: float = 300.0
    lease_factor: float = 10.0
    """lease = lease_factor x the job's robot-steps / the worker's speed as the scheduler
    measured it (never as the worker claims it), clamped to the range."""
    lease_unknown_s: float = 120.0
    """Lease for a worker with no measured speed yet (its first job compiles the kernels)."""
    jobs_per_worker: int = 1
    """A generation is cut into this many jobs per live worker."""
    span_below_s: float = 0.02
    """A generation a worker evaluates faster than this runs in spans (0: never) while runs are
    fewer than workers: below it the round trip per generation costs more than parallel slices
    save (on 2 cores with one-thread workers, slices won from about 20 ms a generation:
    bench/dispatch.py --sweep). Workers sharing one host's cores are never sliced between
    (`Ledger.sliceable`): the scheduler counts them as crowded.
    With at least as many runs as workers (a study), every worker can evolve a run of its own:
    whole generations in spans then whatever a generation's length (bench/study.py)."""
    span_s: float = 5.0
    """A span covers about this much evaluation time, then its worker asks again."""
    max_attempts: int = 3
    """Credentials whose evaluation of a job may err before the server evaluates it itself
    (whose error alone fails the run)."""
    errors_quarantine: int = 3
    """Error results in a row, with none accepted between, that quarantine a credential."""
    gone_keep_s: float = 600.0
    """How long a departed worker stays listed as gone."""
    store_lag_s: float = 0.25
    """How long a told generation may wait for the store: past this its run leases nothing and
    a span ends with its current message, so a store that blocks or refuses writes (or a
    writer that stopped) stops its runs within that much evolution and one span message. The
    writer takes told generations every 0.05 s and writes them in milliseconds."""
    write_now: int = 4
    """Told generations of one run that make the store write at once (`told_many`)."""
    spot_checks: int = 0
    """Individuals of each result of a listed worker re-evaluated here (0: none). The server
    sets it from COLONY_SPOT_CHECKS (default 1); a bare scheduler trusts every result, so tests
    and benches may stand a fake evaluator in for the science."""

    def __post_init__(self) -> None:
        for name in ("lease_min_s", "lease_factor", "lease_unknown_s", "span_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if not self.lease_max_s >= self.lease_min_s:
            raise ValueError(f"lease_max_s must be >= lease_min_s, got {self.lease_max_s}")
        if self.span_below_s < 0 or self.gone_keep_s < 0 or self.spot_checks < 0:
            raise ValueError("span_below_s, gone_keep_s and spot_checks must be >= 0")
        if min(self.jobs_per_worker, self.max_attempts, self.errors_quarantine, self.write_now) < 1:
            raise ValueError(
                "jobs_per_worker, max_attempts, errors_quarantine and write_now must be >= 1"
            )
        if not self.store_lag_s > 0:
            raise ValueError(f"store_lag_s must be > 0, got {self.store_lag_s}")

    @classmethod
    def from_settings(cls, settings: Settings) -> Policy:
        """The server's policy from its settings (COLONY_LEASE_*, ...). ValueError if
        inconsistent."""
        return cls(
            lease_min_s=settings.lease_min_seconds,
            lease_max_s=settings.lease_max_seconds,
            lease_unknown_s=settings.lease_unknown_seconds,
            jobs_per_worker=settings.jobs_per_worker,
            span_below_s=settings.span_below_seconds,
            span_s=settings.span_seconds,
            max_attempts=settings.max_attempts,
            errors_quarantine=settings.errors_quarantine,
            spot_checks=settings.spot_checks,
        )

    def lease_seconds(self, robot_steps: int, speed: float | None) -> float:
        """The lease of a job of `robot_steps` for a worker measured at `speed` robot-steps/s
        (None: not measured yet)."""
        if speed is None:
            return self.lease_unknown_s
        wanted = self.lease_factor * robot_steps / clamp_speed(speed)
        return min(max(self.lease_min_s, wanted), self.lease_max_s)

    def span_generations(self, config: RunConfig, speed: float | None, *, crowded: bool) -> int:
        """Generations of `config` a worker of `speed` evolves in one span (1: no span);
        `crowded`: runs are at least as many as workers (no slices needed to keep all busy)."""
        if speed is None or self.span_below_s == 0:
            return 1
        seconds = robot_steps(config, config.population) / clamp_speed(speed)
        if seconds >= self.span_below_s and not crowded:
            return 1
        return max(1, int(self.span_s / seconds))

    def job_size(
        self, config: RunConfig, generation: int, speeds: list[float | None], *, crowded: bool
    ) -> int:
        """Individuals per job of `config`'s `generation` for live workers claiming `speeds`
        (None: unknown, or it takes no spans): one job per live worker (`jobs_per_worker` each,
        at least the run's `job_size`), or the whole generation when runs are `crowded` or
        whoever leases it will get a span: a whole generation leased to one worker would
        otherwise keep the others idle."""
        if not speeds:
            return config.job_size
        if crowded:
            return config.population
        if (
            generation + 1 < config.generations
            and traits(config).in_state  # a worker evolves only the paper's GA itself
            and all(s is not None for s in speeds)
        ):
            slowest = min(s for s in speeds if s is not None)
            if self.span_generations(config, slowest, crowded=False) > 1:
                return config.population
        jobs = len(speeds) * self.jobs_per_worker
        return max(config.job_size, -(-config.population // jobs))


def clamp_speed(speed: float) -> float:
    """A reported speed within [SPEED_MIN, SPEED_MAX] (NaN counts as the minimum)."""
    return min(max(speed, SPEED_MIN), SPEED_MAX) if speed == speed else SPEED_MIN
