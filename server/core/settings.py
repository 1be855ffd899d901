"""Server settings from flags or the environment (prefix COLONY_, e.g. COLONY_DB_URL)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Literal

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from evorobotics.errors import MazeError
from evorobotics.maze import load_maze
from schemas.robots import DEFAULT_REPLACEMENT, ReplacementPolicy
from schemas.security import (
    MAX_BODY_BYTES,
    MAX_GENERATION_STEPS,
    MAX_POPULATION_WEIGHTS,
    MAX_RUN_STEPS,
    MAX_ZENOH_MESSAGE,
    ZenohRoles,
    ZenohRouterAuth,
)

CHECKPOINT_EVERY = 50
"""Generations between stored populations: a paper run keeps 7 and takes about 1.2 MB, and any
other generation rebuilds in tens of milliseconds (bench/store.py)."""


class Settings(BaseSettings):
    """What an operator sets (first), then the job path's tuning; defaults serve one lab machine."""

    model_config = SettingsConfigDict(env_prefix="COLONY_", extra="ignore")

    db_url: str = Field("sqlite:///colony.db", description="any SQLAlchemy URL")
    host: str = Field("127.0.0.1", description="HTTP bind address")
    port: int = Field(8000, ge=0, le=65535, description="HTTP port")
    zenoh: bool = Field(True, description="serve jobs to workers over zenoh (docs/protocol.md)")
    zenoh_listen: list[str] = Field(
        ["tcp/127.0.0.1:7447"],
        description="endpoints the server's zenoh router listens on (off loopback: users and roles)",
    )
    zenoh_connect: list[str] = Field(
        [], description="routers to join, e.g. a lab's zenohd at tcp/HOST:7447"
    )
    workers: int | None = Field(
        None, ge=0, le=256, description="local worker processes (default: one per spare core)"
    )
    executors: int | None = Field(
        None, ge=0, le=64, description="in-process evaluation threads (default: 0 with zenoh, 1)"
    )
    max_active_runs: int = Field(8, ge=1, description="runs evolving at once; the rest queue")
    checkpoint_every: int = Field(
        CHECKPOINT_EVERY,
        ge=1,
        le=1_000_000,
        description="store a run's genomes every N generations and its last; the others are "
        "replayed from the one before (docs/api.md)",
    )
    log_level: str = Field(
        "INFO", pattern="^(DEBUG|INFO|WARNING|ERROR)$", description="DEBUG, INFO, WARNING or ERROR"
    )
    log_format: Literal["text", "json"] = Field(
        "text", description="text, or json: one JSON object per line with run/job/robot ids"
    )
    tensorboard_dir: Path | None = Field(
        None, description="write TensorBoard event files of each run under DIR/run-ID"
    )
    maze: str = Field(
        "paper",
        description="the lab's maze the Colony page draws robots in: a shipped name, "
        "gen:SIZE:SEED, or a maze text file",
    )
    replacement: ReplacementPolicy = Field(
        DEFAULT_REPLACEMENT,
        description="what a stuck robot gets unless it has its own policy: off (nothing, it "
        "escapes and resumes), rank (the next rank of its controller's run)",
    )

    # security (docs/security.md)
    api_token: str | None = Field(
        None, repr=False, description="bearer token for mutating requests (and reads if closed)"
    )
    read_open: bool = Field(True, description="GET endpoints without the token")
    allowed_hosts: list[str] = Field(
        [],
        description="Host names requests may use besides loopback and --host ('*': any)",
    )
    max_body_bytes: int = Field(MAX_BODY_BYTES, ge=1, description="larger bodies get 413")
    max_population_weights: int = Field(
        MAX_POPULATION_WEIGHTS, ge=1, description="population x weights of a run (memory)"
    )
    max_generation_steps: int = Field(
        MAX_GENERATION_STEPS, ge=1, description="population x trials x steps (CPU per generation)"
    )
    max_run_steps: int = Field(
        MAX_RUN_STEPS,
        ge=1,
        description="population x trials x steps x generations (CPU of a whole run)",
    )
    server_key: Path | None = Field(
        None, description="Ed25519 key signing robot pushes (default: beside the SQLite file)"
    )
    zenoh_users_file: Path | None = Field(
        None, description="user:password lines; zenoh clients must present one of them"
    )
    zenoh_roles_file: Path | None = Field(
        None, description="JSON {workers: [...], robots: [...]}: what each zenoh user may do"
    )
    zenoh_user: str | None = Field(
        None, description="credentials for local workers and for --zenoh-connect routers"
    )
    zenoh_password: str | None = Field(None, repr=False, description="password of zenoh_user")
    zenoh_tls_certificate: Path | None = Field(None, description="PEM for tls/ listen endpoints")
    zenoh_tls_private_key: Path | None = Field(None, description="its private key (PEM)")
    zenoh_tls_root_ca: Path | None = Field(None, description="CA for tls/ connect endpoints")
    zenoh_max_message: int = Field(
        MAX_ZENOH_MESSAGE, ge=1 << 16, description="largest zenoh message the router accepts"
    )

    # tuning of the job path (docs/protocol.md); the defaults serve a lab network
    jobs_per_worker: int = Field(
        1, ge=1, le=64, description="jobs per live worker and generation (more: finer balance)"
    )
    span_below_seconds: float = Field(
        0.02,
        ge=0.0,
        description="a generation a worker evaluates faster than this runs in spans (0: never)",
    )
    span_seconds: float = Field(
        5.0, gt=0.0, description="evaluation time of one span, then its worker asks again"
    )
    lease_min_seconds: float = Field(
        10.0, gt=0.0, description="shortest lease (lease = 10 x the job's time, clamped)"
    )
    lease_max_seconds: float = Field(300.0, gt=0.0, description="longest lease")
    lease_unknown_seconds: float = Field(
        120.0, gt=0.0, description="lease before a worker's speed is known (compiling)"
    )
    max_attempts: int = Field(
        3,
        ge=1,
        description="worker credentials that may err on a job before the server evaluates it "
        "itself (only the server's own evaluation failing fails a run)",
    )
    errors_quarantine: int = Field(
        3, ge=1, description="error results in a row that quarantine a worker credential"
    )
    spot_checks: int = Field(
        1,
        ge=0,
        le=64,
        description="individuals of each worker result evaluated again (by the worker of "
        "another job of the same generation, else by the server) and compared bit for bit; a "
        "mismatch quarantines the worker (0: off)",
    )
    housekeeping_seconds: float = Field(
        1.0, gt=0.0, description="period of lease expiry and queued-run promotion"
    )

    @field_validator("maze")
    @classmethod
    def _maze_loads(cls, value: str) -> str:
        """A maze the map can draw, or one clear error at start-up."""
        try:
            load_maze(value)
        except (MazeError, OSError, UnicodeDecodeError) as exc:
            raise ValueError(f"maze: {exc}") from None
        return value

    @field_validator("api_token", "zenoh_user", "zenoh_password")
    @classmethod
    def _blank_is_unset(cls, value: str | None) -> str | None:
        """An empty COLONY_API_TOKEN= means no token, never the empty token."""
        return value if value and value.strip() else None

    def server_key_path(self) -> Path | None:
        """The signing key's file: the setting, else beside a SQLite file, else
        ~/.evocolony/server-key.pem; None (a key in memory) for an in-memory database."""
        if self.server_key is not None:
            return self.server_key
        if self.db_url.startswith("sqlite:"):
            path = self.db_url.removeprefix("sqlite:").removeprefix("///")
            if path in ("", "//", ":memory:") or path.startswith(":memory:"):
                return None
            return Path(path).parent / "server-key.pem"
        return Path.home() / ".evocolony" / "server-key.pem"

    def zenoh_router_auth(self) -> ZenohRouterAuth:
        """ValueError when a certificate comes without its key, a user without a password, a
        users file without a roles file, or a roles file that cannot be read."""
        roles = self.zenoh_roles_file
        return ZenohRouterAuth(
            dictionary_file=self.zenoh_users_file,
            roles=None if roles is None else ZenohRoles.from_file(roles),
            certificate=self.zenoh_tls_certificate,
            private_key=self.zenoh_tls_private_key,
            root_ca=self.zenoh_tls_root_ca,
            user=self.zenoh_user,
            password=self.zenoh_password,
            max_message_size=self.zenoh_max_message,
        )

    def local_workers(self) -> int:
        """Worker processes to start beside the server: none without zenoh."""
        if not self.zenoh:
            return 0
        if self.workers is not None:
            return self.workers
        return max(1, (os.cpu_count() or 1) - 1)

    def local_worker_threads(self) -> int:
        """Threads each local worker evaluates on: every core this process may use. A run of
        short generations goes to one worker in spans, which then has them all; a study's
        spans share them (bench/dispatch.py, bench/study.py)."""
        return len(os.sched_getaffinity(0))

    def executor_threads(self) -> int:
        """In-process evaluators: off when zenoh workers evaluate, one in a zenoh-less server."""
        if self.executors is not None:
            return self.executors
        return 0 if self.zenoh else 1
