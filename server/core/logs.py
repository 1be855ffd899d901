"""Log setup for every `colony` process: plain text, or JSON lines for a log collector.

Context ids travel as `extra` fields (`run`, `job`, `robot`, `worker`): `context(log, run=3)`
gives a LoggerAdapter that adds them to every record, and both formats print them.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping
from datetime import UTC, datetime
from typing import Any, Literal, cast

LogFormat = Literal["text", "json"]
CONTEXT_FIELDS = ("run", "job", "robot", "worker")
"""The `extra` fields both formats print when a record carries them."""


class JsonFormatter(logging.Formatter):
    """One JSON object per line: time (UTC ISO 8601), level, logger, message, context ids."""

    def format(self, record: logging.LogRecord) -> str:
        entry: dict[str, Any] = {
            "time": datetime.fromtimestamp(record.created, UTC).isoformat(timespec="milliseconds"),
            "level": record.levelname,
            "logger": record.name,
            "message": record.getMessage(),
        }
        for name in CONTEXT_FIELDS:
            if hasattr(record, name):
                entry[name] = getattr(record, name)
        if record.exc_info:
            entry["exception"] = self.formatException(record.exc_info)
        return json.dumps(entry, default=str)


class TextFormatter(logging.Formatter):
    """`time level logger message [run=3 job=3/12/0]`."""

    def __init__(self) -> None:
        super().__init__("%(asctime)s %(levelname)s %(name)s %(message)s")

    def format(self, record: logging.LogRecord) -> str:
        text = super().format(record)
        ids = [f"{n}={getattr(record, n)}" for n in CONTEXT_FIELDS if hasattr(record, n)]
        return f"{text} [{' '.join(ids)}]" if ids else text


def as_format(text: str) -> LogFormat:
    """A `--log-format` value checked: text or json (ValueError otherwise)."""
    if text in ("text", "json"):
        return cast(LogFormat, text)
    raise ValueError(f"log format must be text or json, got {text!r}")


class ProcessIds(logging.Filter):
    """Stamps ids that hold for the whole process (a worker's or a robot's own id) on every
    record that does not carry its own, so every line of `colony worker` names its worker."""

    def __init__(self, ids: Mapping[str, object]) -> None:
        super().__init__()
        self._ids = dict(ids)

    def filter(self, record: logging.LogRecord) -> bool:
        for name, value in self._ids.items():
            if not hasattr(record, name):
                setattr(record, name, value)
        return True


def configure(
    level: str = "INFO", fmt: LogFormat = "text", *, ids: Mapping[str, object] | None = None
) -> None:
    """Root logger to stderr in `fmt` at `level`, replacing earlier handlers (uvicorn's too);
    `ids` (context fields, e.g. `{"worker": "w1"}`) go on every line."""
    if ids:
        _check_ids(ids)
    fmt = as_format(fmt)
    numeric = logging.getLevelName(level.upper())
    if not isinstance(numeric, int):
        raise ValueError(f"unknown log level {level!r}")
    handler = logging.StreamHandler()
    handler.setFormatter(JsonFormatter() if fmt == "json" else TextFormatter())
    if ids:
        handler.addFilter(ProcessIds(ids))
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(numeric)
    for name in ("uvicorn", "uvicorn.error", "uvicorn.access"):
        logger = logging.getLogger(name)
        logger.handlers.clear()
        logger.propagate = True


class ContextAdapter(logging.LoggerAdapter[logging.Logger]):
    """Merges its ids into each record's `extra` (a call's own extra wins)."""

    def process(self, msg: Any, kwargs: Any) -> tuple[Any, Any]:
        kwargs["extra"] = {**(self.extra or {}), **kwargs.get("extra", {})}
        return msg, kwargs


def context(logger: logging.Logger, **ids: Any) -> ContextAdapter:
    """`logger` with context ids, e.g. `context(log, run=3, job="3/12/0").info("leased")`."""
    _check_ids(ids)
    extra: Mapping[str, object] = ids
    return ContextAdapter(logger, extra)


def _check_ids(ids: Mapping[str, object]) -> None:
    unknown = set(ids) - set(CONTEXT_FIELDS)
    if unknown:
        raise ValueError(f"context ids must be among {CONTEXT_FIELDS}, got {sorted(unknown)}")
