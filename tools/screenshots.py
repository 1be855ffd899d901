"""`make screenshots`: the dashboard's pictures in docs/img (dashboard-runs, -studies, -archive,
-colony), taken by headless Chromium at 1920 x 1080 from a colony this script starts as a user
would: `colony server` with local workers, a study, the paper's experiment, a map-elites run, a
run still evolving, and virtual EvBots running the champion. Retaking them after a change to
the page keeps the docs showing the product as it is. Needs Debian's /usr/bin/chromium and
playwright (the dev extras); about two minutes on two cores.
"""

from __future__ import annotations

import argparse
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx

from colony.demo import Children, free_ports, wait_until

CHROMIUM = "/usr/bin/chromium"
VIEWPORT = {"width": 1920, "height": 1080}
TIMEOUT_S = 600.0
"""For the runs to evolve."""
PAGE_TIMEOUT_MS = 120_000
"""For a page to draw what it shows."""
ROBOTS = 3
EXPLORE_S = 15.0
"""How long the robots drive before the Colony page is taken: paths and stuck marks to draw."""
STUDY = {
    "name": "delays-vs-reactive",
    "base": {"population": 40, "generations": 60},
    "conditions": {"delays": {"network": "paper-best"}, "reactive": {"network": "reactive"}},
    "seeds": [1, 2, 3],
}
RUNS = [
    {"name": "paper experiment"},  # the paper's defaults: its champion is the one shown
    {"name": "archive", "strategy": "map-elites", "population": 50, "generations": 120},
]
LIVE = {"name": "still evolving", "generations": 100_000}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    root = Path(__file__).resolve().parents[1]
    parser.add_argument("--out", type=Path, default=root / "docs" / "img")
    out: Path = parser.parse_args().out
    children = Children()
    with tempfile.TemporaryDirectory() as tmp:
        try:
            take(Path(tmp), out, children)
        finally:
            children.stop()


def take(tmp: Path, out: Path, children: Children) -> None:
    http_port, zenoh_port = free_ports(0, 0)
    url = f"http://127.0.0.1:{http_port}"
    endpoint = f"tcp/127.0.0.1:{zenoh_port}"
    server = ["server", "--db", f"sqlite:///{tmp / 'colony.db'}", "--host", "127.0.0.1"]
    server += ["--port", url.rsplit(":", 1)[1], "--zenoh-listen", endpoint, "--workers", "2"]
    children.start("server", server, tmp / "server.log")

    def alive() -> None:
        for name, proc, _ in children.processes:
            if proc.poll() is not None:
                raise RuntimeError(f"{name} exited with status {proc.returncode}: see {tmp}")

    with httpx.Client(base_url=url, timeout=60.0) as client:

        def until(what: str, predicate: Callable[[], bool]) -> None:
            wait_until(predicate, TIMEOUT_S, what, alive)

        until("the server", lambda: healthy(client))
        study = post(client, "/api/studies", STUDY)["id"]
        paper, archive = (post(client, "/api/runs", body)["id"] for body in RUNS)
        until("the runs", lambda: all(r["status"] == "completed" for r in get(client, "/api/runs")))
        live = post(client, "/api/runs", LIVE)["id"]
        robots = [f"evbot-{k + 1}" for k in range(ROBOTS)]
        for k, robot in enumerate(robots):
            # the emulator's own poses: the map draws each robot where the simulator has it
            agent = ["agent", "--emulate", "--robot-id", robot, "--connect", endpoint]
            agent += ["--server", url, "--index", str(k), "--state-dir", str(tmp / robot)]
            children.start(robot, [*agent, "--log-level", "WARNING"], tmp / f"{robot}.log")
        until("the robots", lambda: all(r["online"] for r in robots_of(client, robots)))
        for robot in robots:
            post(client, f"/api/robots/{robot}/controller", {"run_id": paper})
        until(
            "the robots driving",
            lambda: all(r["steps"] > 10 * EXPLORE_S for r in robots_of(client, robots)),
        )
        shoot(url, out, paper, archive, study, robots[0])
        post(client, f"/api/runs/{live}/cancel", None)


def shoot(url: str, out: Path, paper: int, archive: int, study: int, robot: str) -> None:
    """The four pages, each once it has drawn what it shows."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=["--headless", "--no-sandbox"])
        page = browser.new_page(viewport=VIEWPORT)  # type: ignore[arg-type]
        page.set_default_timeout(PAGE_TIMEOUT_MS)
        for run, name in ((paper, "runs"), (archive, "archive")):
            page.goto(f"{url}/?run={run}")
            page.locator("[data-testid=run-robustness]").wait_for()
            for figure in ("network", "paths"):
                page.wait_for_function(f"document.querySelector('#{figure}-img').naturalWidth > 0")
            if run == archive:
                page.wait_for_function(
                    "Number(document.querySelector('#archive-map').dataset.elites) > 0"
                )
            page.screenshot(path=str(out / f"dashboard-{name}.png"), full_page=True)
        page.goto(f"{url}/#studies/{study}")
        page.wait_for_selector('#study-curve[data-series="2"] canvas')
        page.screenshot(path=str(out / "dashboard-studies.png"), full_page=True)
        page.goto(f"{url}/#colony")
        page.wait_for_function(
            f"Number(document.querySelector('#colony-map').dataset.robots) >= {ROBOTS}"
        )
        page.click(f"[data-testid=details-{robot}]")
        page.wait_for_function(
            "Number(document.querySelector('#robot-timeline').dataset.points) > 40"
        )
        page.screenshot(path=str(out / "dashboard-colony.png"), full_page=True)
        browser.close()
    for name in ("runs", "archive", "studies", "colony"):
        print(out / f"dashboard-{name}.png")


def healthy(client: httpx.Client) -> bool:
    try:
        return client.get("/healthz").status_code == 200
    except httpx.HTTPError:
        return False


def get(client: httpx.Client, path: str) -> Any:
    response = client.get(path)
    response.raise_for_status()
    return response.json()


def post(client: httpx.Client, path: str, body: object) -> Any:
    response = client.post(path, json=body)
    if response.is_error:
        raise RuntimeError(f"POST {path}: {response.status_code} {response.text}")
    return response.json()


def robots_of(client: httpx.Client, ids: list[str]) -> list[dict[str, Any]]:
    """The robots `ids` as the server lists them (missing ones as offline)."""
    known = {r["id"]: r for r in get(client, "/api/robots")}
    return [known.get(i, {"online": False, "steps": 0}) for i in ids]


if __name__ == "__main__":
    main()
