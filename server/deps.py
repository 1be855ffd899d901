"""Annotated dependencies of the routes: the manager and a read session per request."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Annotated

from fastapi import Depends, Request
from sqlalchemy.orm import Session

from server.manager import RunManager


def get_manager(request: Request) -> RunManager:
    manager: RunManager = request.app.state.manager
    return manager


def get_session(request: Request) -> Iterator[Session]:
    manager: RunManager = request.app.state.manager
    with manager.sessions() as session:
        yield session


ManagerDep = Annotated[RunManager, Depends(get_manager)]
SessionDep = Annotated[Session, Depends(get_session)]
