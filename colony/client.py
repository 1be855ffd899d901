"""The REST client every `colony` command that talks to a server uses: one httpx client per
command, the server's error message and a non-zero exit on failure (docs/api.md). Tests
inject a transport with `app(args, obj={"transport": ...})`."""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Annotated, Any

import httpx
import typer

DEFAULT_SERVER = "http://127.0.0.1:8000"
TIMEOUT_S = 30.0
SHORT_SHA = 12
"""Tables show a sha256 by its first 12 hex digits, a prefix every sha option accepts."""

ServerOpt = Annotated[str, typer.Option("--server", help="server base URL")]
TokenOpt = Annotated[
    str | None,
    typer.Option("--token", envvar="COLONY_API_TOKEN", help="API bearer token [COLONY_API_TOKEN]"),
]
JsonOpt = Annotated[bool, typer.Option("--json", help="print the server's JSON")]


def open_client(ctx: typer.Context, server: str, token: str | None) -> httpx.Client:
    obj = ctx.find_root().obj
    transport = obj.get("transport") if isinstance(obj, dict) else None
    headers = {"Authorization": f"Bearer {token}"} if token else None
    # no redirects are followed, so a plain-http server never needs the CA bundle, whose
    # loading would cost every call ~20 ms
    verify = not server.startswith("http://")
    return httpx.Client(
        base_url=server.rstrip("/"),
        transport=transport,
        timeout=TIMEOUT_S,
        headers=headers,
        verify=verify,
    )


def checked(response: httpx.Response, invalid_exit: int = 1) -> httpx.Response:
    """The response, or the server's error message and exit status 1 (`invalid_exit` for a
    422)."""
    if response.is_error:
        try:
            detail = response.json().get("detail", response.text)
        except ValueError:
            detail = response.text
        typer.echo(f"error {response.status_code}: {detail}", err=True)
        raise typer.Exit(invalid_exit if response.status_code == 422 else 1)
    return response


def request(
    ctx: typer.Context,
    server: str,
    token: str | None,
    method: str,
    path: str,
    body: Any = None,
    *,
    invalid_exit: int = 1,
) -> httpx.Response:
    """One request; on failure the server's error message and exit status 1 (`invalid_exit`
    for a 422)."""
    try:
        with open_client(ctx, server, token) as client:
            response = client.request(method, path, json=body)
    except httpx.HTTPError as exc:
        typer.echo(f"error: cannot reach {server}: {exc}", err=True)
        raise typer.Exit(1) from exc
    return checked(response, invalid_exit)


@contextmanager
def fetching(ctx: typer.Context, server: str, token: str | None) -> Iterator[Callable[[str], Any]]:
    """GET path -> JSON over one connection (exports make many requests); failures exit 1."""
    with open_client(ctx, server, token) as client:

        def fetch(path: str) -> Any:
            try:
                response = client.get(path)
            except httpx.HTTPError as exc:
                typer.echo(f"error: cannot reach {server}: {exc}", err=True)
                raise typer.Exit(1) from exc
            return checked(response).json()

        yield fetch


def call_server(
    ctx: typer.Context,
    server: str,
    token: str | None,
    method: str,
    path: str,
    body: Any = None,
) -> Any:
    """One request's JSON; the server's error message and exit status 1 on failure."""
    return request(ctx, server, token, method, path, body).json()


def print_json(data: Any) -> None:
    typer.echo(json.dumps(data, indent=2))


def cell(value: Any) -> str:
    """A value as a table shows it: '-' for none, floats to 4 significant digits."""
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)
