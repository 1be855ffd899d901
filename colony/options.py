"""Options shared by several commands: zenoh and logs (`colony worker`, `colony agent`), the
ideal world (`colony evolve`, `colony run start`)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

ZenohUserOpt = Annotated[
    str | None, typer.Option(envvar="COLONY_ZENOH_USER", help="zenoh usrpwd user")
]
ZenohPasswordOpt = Annotated[
    str | None,
    typer.Option(envvar="COLONY_ZENOH_PASSWORD", help="its password (prefer the env var)"),
]
ZenohRootCaOpt = Annotated[
    Path | None,
    typer.Option(envvar="COLONY_ZENOH_ROOT_CA", help="CA (PEM) of the router's TLS cert"),
]
LogLevelOpt = Annotated[
    str, typer.Option(envvar="COLONY_LOG_LEVEL", help="DEBUG, INFO, WARNING or ERROR")
]
LogFormatOpt = Annotated[
    str,
    typer.Option(
        envvar="COLONY_LOG_FORMAT",
        help="text, or json: one JSON object per line carrying this process's id",
    ),
]
NominalOpt = Annotated[
    bool,
    typer.Option(
        "--nominal",
        help="evolve in the ideal world (reality_gap off) instead of under the paper's gap",
    ),
]
