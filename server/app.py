"""The FastAPI application factory: engine, migrations, run manager and executors in a lifespan."""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse

from server.db import make_engine, upgrade
from server.executor import InProcessExecutor
from server.manager import RunManager
from server.routes import colony, controllers, runs
from server.settings import Settings


def validation_message(exc: RequestValidationError) -> str:
    """One line per error naming the field, e.g. `population: Input should be >= 4`."""
    parts = []
    for error in exc.errors():
        loc = [str(p) for p in error.get("loc", ()) if p != "body"]
        field = ".".join(loc) or "body"
        parts.append(f"{field}: {error.get('msg', 'invalid')}")
    return "; ".join(parts)


def create_app(settings: Settings | None = None) -> FastAPI:
    """The server; nothing touches the database until the lifespan starts."""
    settings = settings or Settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        engine = make_engine(settings.db_url)
        upgrade(engine)
        manager = RunManager(engine, settings)
        manager.start()
        executor = InProcessExecutor(manager, threads=settings.executors)
        executor.start()
        app.state.manager = manager
        try:
            yield
        finally:
            executor.stop()
            manager.stop()
            engine.dispose()

    app = FastAPI(
        title="EvoColony",
        summary="Evolve neural controllers for EvBots; runs, controllers and colony status.",
        lifespan=lifespan,
    )

    @app.exception_handler(RequestValidationError)
    async def _invalid(_request: Request, exc: RequestValidationError) -> JSONResponse:
        return JSONResponse(status_code=422, content={"detail": validation_message(exc)})

    app.include_router(runs.router)
    app.include_router(controllers.router)
    app.include_router(colony.router)
    return app
