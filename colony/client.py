"""The REST client every `colony` command that talks to a server uses: one httpx client per
command, the server's error message and a non-zero exit on failure (docs/api.md). Tests
inject a transport with `app(args, obj={"transport": ...})`."""

from __future__ import annotations

import json
import os
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Annotated, Any

import httpx
import typer
from rich.console import Console

DEFAULT_SERVER = "http://127.0.0.1:8000"
TIMEOUT_S = 30.0
SHORT_SHA = 12
"""Tables show a sha256 by its first 12 hex digits, a prefix every sha option accepts."""
PIPED_WIDTH = 1000
"""Columns of what goes to a pipe or a file: no table is squeezed to fit a terminal there is
not."""

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


def rich_console(*, stderr: bool = False) -> Console:
    """A rich console for tables and progress bars: a terminal's width on a terminal, COLUMNS
    when set, else PIPED_WIDTH (piped output keeps every table whole)."""
    stream = sys.stderr if stderr else sys.stdout
    piped = not stream.isatty() and not os.environ.get("COLUMNS")
    return Console(stderr=stderr, width=PIPED_WIDTH if piped else None)


def base_url_hint(server: str, status: int) -> str:
    """What to add to a 404 when the server URL ends in /api: every path the CLI asks
    already starts with /api, so it asked for /api/api/...; "" otherwise."""
    base = server.rstrip("/")
    if status != 404 or not base.endswith("/api"):
        return ""
    return f" (the server URL is the base, without /api: --server {base.removesuffix('/api')})"


def checked(
    response: httpx.Response,
    server: str,
    invalid_exit: int = 1,
    explain: Callable[[str], str] = str,
) -> httpx.Response:
    """The response, or the server's error message (`explain`ed) and exit status 1
    (`invalid_exit` for a 422)."""
    if response.is_error:
        try:
            detail = response.json().get("detail", response.text)
        except ValueError:
            detail = response.text
        hint = base_url_hint(server, response.status_code)
        typer.echo(f"error {response.status_code}: {explain(str(detail))}{hint}", err=True)
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
    explain: Callable[[str], str] = str,
) -> httpx.Response:
    """One request; on failure the server's error message (`explain`ed: the CLI may know
    better names) and exit status 1 (`invalid_exit` for a 422)."""
    try:
        with open_client(ctx, server, token) as client:
            response = client.request(method, path, json=body)
    except httpx.HTTPError as exc:
        typer.echo(f"error: cannot reach {server}: {exc}", err=True)
        raise typer.Exit(1) from exc
    return checked(response, server, invalid_exit, explain)


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
            return checked(response, server).json()

        yield fetch


def call_server(
    ctx: typer.Context,
    server: str,
    token: str | None,
    method: str,
    path: str,
    body: Any = None,
    *,
    explain: Callable[[str], str] = str,
) -> Any:
    """One request's JSON; the server's error message and exit status 1 on failure."""
    return request(ctx, server, token, method, path, body, explain=explain).json()


def print_json(data: Any) -> None:
    typer.echo(json.dumps(data, indent=2))


def cell(value: Any) -> str:
    """A value as a table shows it: '-' for none, floats to 4 significant digits."""
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)
