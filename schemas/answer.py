"""Queries that expect exactly one answerer: the server.

zenoh's defaults route a query to the best-matching queryable and consolidate replies by
keeping the latest, so a second queryable on the server's keys could answer instead of the
server, or after it and win. Workers and robots therefore ask every matching queryable
(`QueryTarget.ALL`), keep every reply (`ConsolidationMode.NONE`), and accept an answer only
when all replies come from one answerer: a second answerer is an error in the log, never a
silent winner (docs/security.md).
"""

from __future__ import annotations

import logging

import zenoh

TARGET = zenoh.QueryTarget.ALL
"""`target` of every query to the server: every matching queryable hears it."""
CONSOLIDATION = zenoh.ConsolidationMode.NONE
"""`consolidation` of every query to the server: every reply is delivered."""


def one_answer(replies: zenoh.Handler[zenoh.Reply], key: str, log: logging.Logger) -> bytes | None:
    """The payload of the one answerer's successful reply; None, logged, on an error reply, no
    reply, or replies from more than one answerer (all are read, so this waits until the
    query is finished)."""
    answerers: set[str] = set()
    payload: bytes | None = None
    error: bytes | None = None
    for reply in replies:
        answerers.add(str(reply.replier_id))
        if reply.ok is not None and payload is None:
            payload = reply.ok.payload.to_bytes()
        elif reply.err is not None and error is None:
            error = reply.err.payload.to_bytes()[:200]
    if len(answerers) > 1:
        log.error(
            "refusing the answers on %s: %d answerers replied where only the server may (%s)",
            key,
            len(answerers),
            ", ".join(sorted(answerers)),
        )
        return None
    if payload is None and error is not None:
        log.warning("server error on %s: %s", key, error)
    return payload
