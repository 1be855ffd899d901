"""Server settings from flags or the environment (prefix COLONY_, e.g. COLONY_DB_URL)."""

from __future__ import annotations

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict


class Settings(BaseSettings):
    """Everything an operator may tune; defaults serve a single lab machine."""

    model_config = SettingsConfigDict(env_prefix="COLONY_", extra="ignore")

    db_url: str = Field("sqlite:///colony.db", description="any SQLAlchemy URL")
    host: str = "127.0.0.1"
    port: int = Field(8000, ge=0, le=65535)
    executors: int = Field(1, ge=0, le=64, description="in-process evaluation threads")
    lease_seconds: float = Field(300.0, gt=0.0, description="a leased job returns after this")
    max_attempts: int = Field(3, ge=1, description="failed evaluations before a run fails")
    max_active_runs: int = Field(8, ge=1, description="runs evolving at once; the rest queue")
    housekeeping_seconds: float = Field(
        1.0, gt=0.0, description="period of lease expiry and queued-run promotion"
    )
