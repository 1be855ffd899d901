"""Server settings from flags or the environment (prefix COLONY_, e.g. COLONY_DB_URL)."""

from __future__ import annotations

import os

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict

from server.dispatch import DispatchSettings


class Settings(BaseSettings):
    """Everything an operator may tune; defaults serve a single lab machine."""

    model_config = SettingsConfigDict(env_prefix="COLONY_", extra="ignore")

    db_url: str = Field("sqlite:///colony.db", description="any SQLAlchemy URL")
    host: str = "127.0.0.1"
    port: int = Field(8000, ge=0, le=65535)
    zenoh: bool = Field(True, description="serve jobs to workers over zenoh (docs/protocol.md)")
    zenoh_listen: list[str] = Field(
        ["tcp/0.0.0.0:7447"], description="endpoints the server's zenoh router listens on"
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
    lease_seconds: float = Field(300.0, gt=0.0, description="a leased job returns after this")
    lease_min_seconds: float = Field(
        10.0, gt=0.0, description="shortest zenoh lease (lease = max(this, 10 x job time))"
    )
    lease_unknown_seconds: float = Field(
        120.0, gt=0.0, description="zenoh lease before a worker's speed is known (compiling)"
    )
    max_attempts: int = Field(3, ge=1, description="failed evaluations before a run fails")
    max_active_runs: int = Field(8, ge=1, description="runs evolving at once; the rest queue")
    housekeeping_seconds: float = Field(
        1.0, gt=0.0, description="period of lease expiry and queued-run promotion"
    )

    def local_workers(self) -> int:
        """Worker processes to start beside the server: none without zenoh."""
        if not self.zenoh:
            return 0
        if self.workers is not None:
            return self.workers
        return max(1, (os.cpu_count() or 1) - 1)

    def executor_threads(self) -> int:
        """In-process evaluators: off when zenoh workers evaluate, one in a zenoh-less server."""
        if self.executors is not None:
            return self.executors
        return 0 if self.zenoh else 1

    def dispatch_settings(self) -> DispatchSettings:
        """ValueError if zenoh has neither a listen nor a connect endpoint."""
        return DispatchSettings(
            listen=tuple(self.zenoh_listen),
            connect=tuple(self.zenoh_connect),
            lease_min_s=self.lease_min_seconds,
            lease_unknown_s=self.lease_unknown_seconds,
        )
