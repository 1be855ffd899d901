"""The FastAPI application factory: store, run manager, zenoh router and workers in a lifespan.

Start order: database, run manager, the zenoh session (router mode, one per server), the
dispatcher on it, extra zenoh services (e.g. robots), the queue's wake-up listener, local workers,
in-process executors. Shutdown runs it backwards with the zenoh part in the promised order:
local workers (each delivers its job), dispatcher, other zenoh users, then the session.
"""

from __future__ import annotations

import logging
import os
from collections.abc import AsyncIterator, Callable, Sequence
from contextlib import AsyncExitStack, asynccontextmanager
from typing import Any

import zenoh
from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from sqlalchemy.exc import OperationalError

from schemas.api import ErrorOut
from server.core import metrics
from server.core.auth import SecurityMiddleware
from server.core.db import Checkpointer, is_sqlite, make_engine, upgrade
from server.core.errors import BusyError, ServerError
from server.core.settings import Settings
from server.robots import signing
from server.robots.service import robot_service
from server.robots.signing import Signer
from server.routes import (
    colony,
    controllers,
    dashboard,
    images,
    robots,
    runs,
    studies,
    workers,
)
from server.runs.dispatch import Dispatcher, DispatchSettings
from server.runs.executor import InProcessExecutor
from server.runs.lifecycle import RunManager
from server.runs.policy import Policy
from server.studies.evaluation import Evaluations
from worker.local import LocalWorkers, local_endpoint

log = logging.getLogger(__name__)

REF_TEMPLATE = "#/components/schemas/{model}"

ZenohService = Callable[[FastAPI, zenoh.Session], Callable[[], None]]
"""Started on the server's zenoh session after the dispatcher; returns its close function,
called after the dispatcher closes and before the session does."""


def validation_message(exc: RequestValidationError) -> str:
    """One line per error naming the field, e.g. `population: Input should be >= 4`."""
    parts = []
    for error in exc.errors():
        loc = [str(p) for p in error.get("loc", ()) if p != "body"]
        field = ".".join(loc) or "body"
        parts.append(f"{field}: {error.get('msg', 'invalid')}")
    return "; ".join(parts)


def error_model_for_validation(schema: dict[str, Any]) -> dict[str, Any]:
    """Make the OpenAPI schema's 422 responses promise what `_invalid` sends: `ErrorOut`
    (`{"detail": "population: Input should be >= 4"}`), not FastAPI's list of errors."""
    components = schema.setdefault("components", {}).setdefault("schemas", {})
    components.pop("HTTPValidationError", None)
    components.pop("ValidationError", None)
    components["ErrorOut"] = ErrorOut.model_json_schema(ref_template=REF_TEMPLATE)
    for operations in schema.get("paths", {}).values():
        for operation in operations.values():
            response = operation.get("responses", {}).get("422")
            if response is not None:
                response["description"] = "Invalid request: one `field: problem` per error"
                response["content"] = {
                    "application/json": {"schema": {"$ref": REF_TEMPLATE.format(model="ErrorOut")}}
                }
    return schema


def create_app(
    settings: Settings | None = None, services: Sequence[ZenohService] | None = None
) -> FastAPI:
    """The server; nothing touches the database or the network until the lifespan starts.

    `services` run on the server's zenoh session; by default the robot service.
    """
    settings = settings or Settings()
    Policy.from_settings(
        settings
    )  # a ValueError now, before the lifespan opens the store or binds a port
    services = (robot_service(),) if services is None else tuple(services)
    dispatch = DispatchSettings.from_settings(settings) if settings.zenoh else None
    endpoint = (
        local_endpoint(dispatch.listen, dispatch.connect)
        if dispatch is not None and settings.local_workers()
        else None
    )

    if endpoint is not None and settings.zenoh_user and settings.zenoh_password:
        # local workers are spawned `colony worker` processes: they read these (security.md)
        os.environ["COLONY_ZENOH_USER"] = settings.zenoh_user
        os.environ["COLONY_ZENOH_PASSWORD"] = settings.zenoh_password

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        async with AsyncExitStack() as stack:
            engine = make_engine(settings.db_url, background_checkpoint=True)
            stack.callback(engine.dispose)
            if is_sqlite(engine):
                stack.callback(Checkpointer(engine).close)
            upgrade(engine)
            key_path = settings.server_key_path()
            app.state.signer = Signer.from_file(key_path)
            log.info("robot pushes signed with the key in %s", key_path or "memory")
            manager = RunManager(engine, settings)
            manager.start()
            stack.callback(manager.stop)
            app.state.manager = manager
            app.state.evaluations = Evaluations(manager.scheduler)
            app.state.zenoh = None
            app.state.dispatcher = None
            if dispatch is not None:
                session = zenoh.open(dispatch.zenoh_config())
                stack.callback(session.close)
                dispatcher = Dispatcher(dispatch, manager.scheduler, session=session)
                closers = [service(app, session) for service in services]
                for close in closers:
                    stack.callback(close)
                stack.callback(dispatcher.close)
                app.state.zenoh = session
                app.state.dispatcher = dispatcher
                if endpoint is not None:
                    threads = settings.local_worker_threads()
                    local = LocalWorkers(settings.local_workers(), endpoint, threads=threads)
                    stack.callback(local.stop)
            executor = InProcessExecutor(manager.scheduler, threads=settings.executor_threads())
            executor.start()
            stack.callback(executor.stop)
            app.state.executor = executor
            yield

    app = FastAPI(
        title="EvoColony",
        summary="Evolve neural controllers for EvBots; runs, controllers and colony status.",
        lifespan=lifespan,
        docs_url=None,  # served from local files by the dashboard router
        redoc_url=None,
    )

    @app.exception_handler(RequestValidationError)
    async def _invalid(_request: Request, exc: RequestValidationError) -> JSONResponse:
        return JSONResponse(status_code=422, content={"detail": validation_message(exc)})

    @app.exception_handler(OperationalError)
    async def _store_refused(_request: Request, exc: OperationalError) -> JSONResponse:
        # a full disk, a locked or unreachable database: nothing the client can fix
        reason = (str(exc.orig).strip().splitlines() or ["unknown"])[0]
        return JSONResponse(status_code=503, content={"detail": f"database unavailable: {reason}"})

    @app.exception_handler(ServerError)
    async def _server_error(_request: Request, exc: ServerError) -> JSONResponse:
        # not found, impossible transition, robot offline: each class carries its status
        headers = {"Retry-After": str(exc.retry_after_s)} if isinstance(exc, BusyError) else None
        return JSONResponse(
            status_code=exc.status_code, content={"detail": str(exc)}, headers=headers
        )

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            app.openapi_schema = error_model_for_validation(FastAPI.openapi(app))
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]
    metrics.install(app)
    app.include_router(runs.router)
    app.include_router(studies.router)
    app.include_router(controllers.router)
    app.include_router(colony.router)
    app.include_router(workers.router)
    app.include_router(robots.router)
    app.include_router(images.router)
    app.include_router(dashboard.router)
    app.include_router(signing.router)
    app.add_middleware(
        SecurityMiddleware,
        token=settings.api_token,
        read_open=settings.read_open,
        max_body_bytes=settings.max_body_bytes,
        bind_host=settings.host,
        extra_hosts=settings.allowed_hosts,
    )
    return app
