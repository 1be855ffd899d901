"""`colony db check`: verify every stored row of a colony's database against its checksum."""

from __future__ import annotations

from typing import Annotated

import typer

db_app = typer.Typer(help="Check a colony's database.", no_args_is_help=True)


@db_app.command("check")
def check_command(
    db: Annotated[str | None, typer.Option("--db", help="SQLAlchemy URL [COLONY_DB_URL]")] = None,
) -> None:
    """Read every generation and trace batch, verify its checksum and decode it; exit 1
    naming each damaged row (safe beside a running server: it only reads)."""
    from server.core.db import (
        StoreUnusableError,
        check_sqlite_file,
        make_engine,
        session_factory,
        sqlite_path,
    )
    from server.core.errors import ServerError
    from server.core.settings import Settings
    from server.runs import crud

    url = (Settings() if db is None else Settings(db_url=db)).db_url
    path = sqlite_path(url)
    try:
        if path is not None and not path.exists():
            raise StoreUnusableError(f"no database at {path}")
        check_sqlite_file(url)  # the file's pages, before its rows
        engine = make_engine(url)
        try:
            with session_factory(engine)() as session:
                found = crud.check_store(session)
        finally:
            engine.dispose()
    except ServerError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(1) from exc
    for problem in found.damaged:
        typer.echo(f"damaged: {problem}")
    typer.echo(
        f"checked {found.generations} generations ({found.generations_sealed} with checksums) "
        f"and {found.traces} trace batches ({found.traces_sealed} with checksums): "
        + (f"{len(found.damaged)} damaged" if found.damaged else "no damage")
    )
    if found.damaged:
        raise typer.Exit(1)
