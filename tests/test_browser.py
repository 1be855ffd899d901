"""The dashboard in headless Chromium (Debian's, driven by Playwright): a run's curve grows live,
pause and resume work from the page, a click pushes a run's best controller to a virtual
robot that acknowledges it, the runs table fits windows from 1024 px up and figures open full
size. Screenshots go to $DASHBOARD_SCREENSHOTS when set, else to a temporary directory
(`make screenshots` takes the documentation's).

Real uvicorn, temporary SQLite, in-process evaluation; the robot side on a real zenoh router
(127.0.0.1, no multicast) with an agent over a BasicX emulator pty.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from server.app import create_app
from server.core.settings import Settings
from tests.helpers import (
    QUICK,
    Colony,
    Served,
    eventually,
    online,
    robot_link,
    serve,
    virtual_robot,
)

CHROMIUM = Path("/usr/bin/chromium")
ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]
LONG = {"population": 12, "generations": 2000, "steps": 300, "job_size": 4}
"""Runs for tens of seconds: it is paused, resumed and cancelled while the page watches."""
TIMEOUT_MS = 30_000

pytestmark = pytest.mark.skipif(
    not CHROMIUM.exists(), reason="needs Debian's chromium at /usr/bin/chromium (apt-get install)"
)


@pytest.fixture(scope="module")
def db_url(tmp_path_factory: pytest.TempPathFactory) -> str:
    return f"sqlite:///{tmp_path_factory.mktemp('browser') / 'colony.db'}"


@pytest.fixture(scope="module")
def served(db_url: str, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Served]:
    app = create_app(Settings(db_url=db_url, executors=1, zenoh=False))
    with serve(tmp_path_factory.mktemp("unused"), app) as s:
        yield s


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        chromium = p.chromium.launch(executable_path=str(CHROMIUM), args=ARGS)
        try:
            yield chromium
        finally:
            chromium.close()


@pytest.fixture
def shots(tmp_path: Path) -> Path:
    folder = Path(os.environ.get("DASHBOARD_SCREENSHOTS") or tmp_path)
    folder.mkdir(parents=True, exist_ok=True)
    return folder


@pytest.fixture
def page(browser: Any) -> Iterator[Any]:
    context = browser.new_context(viewport={"width": 1280, "height": 900})
    page = context.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.set_default_timeout(TIMEOUT_MS)
    try:
        yield page
        assert errors == [], f"JavaScript errors: {errors}"
    finally:
        context.close()


def points(page: Any) -> int:
    return int(page.get_attribute("#curve", "data-points"))


def test_curve_grows_live_and_controls_steer(served: Served, page: Any, shots: Path) -> None:
    with httpx.Client(base_url=served.url, timeout=30) as client:
        run_id = client.post("/api/runs", json=LONG).json()["id"]
        page.goto(f"{served.url}/?run={run_id}")
        page.wait_for_function("Number(document.querySelector('#curve').dataset.points) >= 2")
        before = points(page)
        page.wait_for_function(
            f"Number(document.querySelector('#curve').dataset.points) > {before}"
        )
        assert points(page) > before  # the chart grew from server-sent events alone
        assert page.locator(f'#runs-table tr[data-run="{run_id}"]').count() == 1
        page.wait_for_selector("#network-img:not([hidden])")
        page.wait_for_selector("#paths-img:not([hidden])")

        page.click("[data-testid=pause]")
        page.wait_for_selector("[data-testid=run-status]:text-is('paused')")
        assert client.get(f"/api/runs/{run_id}").json()["status"] == "paused"
        assert page.is_disabled("[data-testid=pause]") and page.is_enabled("[data-testid=resume]")
        page.click("[data-testid=resume]")
        page.wait_for_selector("[data-testid=run-status]:text-is('running')")
        grown = points(page)
        page.wait_for_function(f"Number(document.querySelector('#curve').dataset.points) > {grown}")
        page.screenshot(path=str(shots / "dashboard-runs.png"), full_page=True)
        assert (shots / "dashboard-runs.png").stat().st_size > 10_000
        page.click("[data-testid=cancel]")
        page.wait_for_selector("[data-testid=run-status]:text-is('cancelled')")
        assert client.get(f"/api/runs/{run_id}").json()["status"] == "cancelled"


WIDTHS = (1024, 1400, 1920)
"""Window widths the dashboard fits: a laptop's, a desktop's, a full-HD screen's."""

HIDDEN_HEADERS = """() => [...document.querySelectorAll('#runs-table thead th')].flatMap((th) => {
    // a header is whole when it lies inside the window and inside the table's scroll box,
    // and nothing else is drawn over its middle
    const box = th.getBoundingClientRect();
    const frame = th.closest('.runs-scroll').getBoundingClientRect();
    const top = document.elementFromPoint((box.left + box.right) / 2, (box.top + box.bottom) / 2);
    const inside = box.left >= 0 && box.right <= window.innerWidth &&
        box.left >= frame.left - 0.5 && box.right <= frame.right + 0.5;
    return inside && th.contains(top) ? [] : [th.textContent];
})"""


def test_runs_table_and_run_page_fit_every_width_and_print_no_null(
    served: Served, browser: Any, shots: Path
) -> None:
    """At 1024, 1400 and 1920 px every column header of the runs table is whole on screen and
    no cell runs past the table's box (a long name, a six-digit generation count), the page
    scrolls no sideways, and the run page of a run whose steps are left to the crossing rule
    gives the steps it trains with, and nowhere says null."""
    with httpx.Client(base_url=served.url, timeout=30) as client:
        wide = {**QUICK, "generations": 100_000, "name": "a long name that ends in an ellipsis"}
        client.post(f"/api/runs/{client.post('/api/runs', json=wide).json()['id']}/cancel")
        body = {"population": 8, "generations": 2, "job_size": 4, "name": "steps by crossings"}
        run_id = client.post("/api/runs", json=body).json()["id"]
        run = wait_completed(client, run_id)
    assert run["config"]["steps"] is None and run["trial_steps"] > 0
    for width in WIDTHS:
        context = browser.new_context(viewport={"width": width, "height": 900})
        page = context.new_page()
        errors: list[str] = []
        page.on("pageerror", lambda exc, errors=errors: errors.append(str(exc)))
        page.set_default_timeout(TIMEOUT_MS)
        try:
            page.goto(f"{served.url}/?run={run_id}")
            page.locator("[data-testid=run-validation]").filter(has_text="Champion").wait_for()
            page.wait_for_selector("#paths-img:not([hidden])")
            assert page.evaluate(HIDDEN_HEADERS) == [], width
            box = page.locator(".runs-scroll")
            assert box.evaluate("(e) => e.scrollWidth <= e.clientWidth"), width
            assert page.evaluate("document.documentElement.scrollWidth") <= width
            meta = page.inner_text("#run-meta")
            assert f"3 trials × {run['trial_steps']} steps" in meta, meta
            shown = page.inner_text("#tab-runs")
            for word in ("null", "undefined", "NaN"):
                assert word not in shown, (width, word)
            if width != 1400:
                page.screenshot(path=str(shots / f"dashboard-runs-{width}.png"), full_page=True)
            assert errors == [], f"JavaScript errors: {errors}"
        finally:
            context.close()


def test_run_figures_open_full_size_on_click(served: Served, page: Any) -> None:
    """The network and paths thumbnails open at full size (as much as the window holds) in a
    modal that a click closes."""
    with httpx.Client(base_url=served.url, timeout=30) as client:
        run_id = client.post("/api/runs", json=QUICK).json()["id"]
        wait_completed(client, run_id)
    page.goto(f"{served.url}/?run={run_id}")
    for figure in ("network", "paths"):
        thumbnail = page.locator(f"[data-testid={figure}-img]")
        thumbnail.wait_for()
        page.wait_for_function(f"document.querySelector('#{figure}-img').naturalWidth > 0")
        small = thumbnail.bounding_box()["width"]
        thumbnail.click()
        zoomed = page.locator("#zoom-img")
        page.wait_for_function("document.querySelector('#zoom').open")
        page.wait_for_function("document.querySelector('#zoom-img').complete")
        natural, shown = page.evaluate(
            "[document.querySelector('#zoom-img').naturalWidth, "
            "document.querySelector('#zoom-img').getBoundingClientRect().width]"
        )
        fits = 0.96 * 1280 - 20  # the modal's limit on this 1280 px window
        assert shown == pytest.approx(min(natural, fits), abs=2) and shown > small
        assert zoomed.get_attribute("src") == thumbnail.get_attribute("src")
        page.click("#zoom")
        page.wait_for_function("!document.querySelector('#zoom').open")


def wait_completed(client: httpx.Client, run_id: int) -> dict[str, Any]:
    assert eventually(lambda: client.get(f"/api/runs/{run_id}").json()["status"] == "completed")
    run: dict[str, Any] = client.get(f"/api/runs/{run_id}").json()
    return run


def test_push_best_controller_to_a_robot_with_a_click(
    served: Served, db_url: str, page: Any, tmp_path: Path, shots: Path
) -> None:
    with httpx.Client(base_url=served.url, timeout=30) as client:
        run_id = client.post("/api/runs", json=QUICK).json()["id"]
        assert eventually(lambda: client.get(f"/api/runs/{run_id}").json()["status"] == "completed")
        best = client.get(f"/api/runs/{run_id}/best").json()
        page.goto(f"{served.url}/?run={run_id}")  # the champion's held-out test, then its choice
        shown = page.locator("[data-testid=run-validation]")
        gap = best["test"]["gap"]
        shown.filter(has_text=f"roaming {round(100 * gap['roaming']['value'])} %").wait_for()
        text = shown.inner_text()
        assert "held-out test" in text and "under the reality gap" in text
        assert f"rank {best['validation']['training_rank']}" in text
        robust = client.get(f"/api/controllers/{best['sha256']}/robustness").json()
        worst = min(min(row) for row in robust["roaming"])
        mapped = page.locator("[data-testid=run-robustness]")
        mapped.filter(has_text=f"worst cell {round(100 * worst)} %").wait_for()
        assert page.locator("#robustness-table td").count() == 49
        colony = Colony(served.url, db_url, run_id, served.app, tmp_path)
        with robot_link(colony) as link, virtual_robot("virt-1", link, tmp_path) as (agent, _):
            assert eventually(lambda: online(client, "virt-1"))
            page.goto(f"{served.url}/#colony")
            card = page.locator('[data-robot="virt-1"]')
            card.wait_for()
            page.select_option("[data-testid=push-run-virt-1]", str(run_id))
            page.click("[data-testid=push-virt-1]")  # no rank: the run's best, its champion
            result = page.locator("[data-testid=push-result-virt-1]")
            result.filter(has_text="acknowledged").wait_for()
            assert agent.controller is not None and agent.controller.sha256 == best["sha256"]
            assert best["sha256"][:12] in result.inner_text()
            # the card follows the robot: its controller's origin arrives over the stream (any
            # rank: a robot that got stuck meanwhile runs a replacement from the same run)
            card.locator('[data-field="origin"]').filter(has_text=f"run {run_id}, rank").wait_for()
            card.locator('[data-field="state"]').filter(has_text="running").wait_for()
            page.wait_for_function(
                """Number(document.querySelector('[data-robot="virt-1"] [data-field="steps"]')
                    .textContent) > 0"""
            )
            assert card.locator('[data-field="physics"]').inner_text() == "not calibrated"
            fit = {
                "whisker_range": [0.03, 0.04, 0.05, 0.06, 0.07],
                "motor_gain": [0.9, 1.1],
                "uncertainty": {"whisker_range": [0.001] * 4 + [0.02], "motor_gain": [0.01] * 2},
                "samples": 500,
                "residuals": {
                    "moving_steps": 400, "pose_rms_m": 0.0, "whisker_disagreements": [0] * 5
                },
                "bounded": [4],
            }  # fmt: skip
            posted = client.post("/api/robots/virt-1/calibration", json=fit)
            assert posted.status_code == 200, posted.text
            card.locator('[data-field="physics"]').filter(
                has_text="whiskers 30 40 50 60 50–90 mm, gains 0.900 / 1.100"
            ).wait_for()
            card.locator('[data-field="calibrated"]').filter(
                has_text="before calibration"
            ).wait_for()


def positions(page: Any) -> dict[str, list[float]]:
    """Where the Colony page's map draws each robot now (metres), from its canvas."""
    found: dict[str, list[float]] = page.evaluate(
        "JSON.parse(document.querySelector('#colony-map').dataset.positions)"
    )
    return found


def test_robots_move_on_the_colony_map_push_to_all_and_policy_change(
    served: Served, db_url: str, page: Any, tmp_path: Path, shots: Path
) -> None:
    """Two virtual robots on the maze: a push to the selected one reaches it alone, Push to all
    runs a run's best on both, their dots move on the map, a card's policy select sets the robot's own replacement policy, and the
    robot's panel plots its whiskers and motors."""
    with httpx.Client(base_url=served.url, timeout=30) as client:
        run_id = client.post("/api/runs", json=QUICK).json()["id"]
        assert eventually(lambda: client.get(f"/api/runs/{run_id}").json()["status"] == "completed")
        best = client.get(f"/api/runs/{run_id}/best").json()["sha256"]
        colony = Colony(served.url, db_url, run_id, served.app, tmp_path)
        with (
            robot_link(colony) as link,
            virtual_robot("map-a", link, tmp_path / "a", seed=1) as (a, _),
            virtual_robot("map-b", link, tmp_path / "b", seed=2) as (b, _),
        ):
            assert eventually(lambda: online(client, "map-a") and online(client, "map-b"))
            page.goto(f"{served.url}/#colony")
            page.wait_for_function(  # robots of earlier tests may be drawn too
                """['map-a', 'map-b'].every((id) => id in
                    JSON.parse(document.querySelector('#colony-map').dataset.positions))"""
            )
            page.locator(f'#group-run option[value="{run_id}"]').wait_for(state="attached")
            page.select_option("[data-testid=group-run]", str(run_id))
            result = page.locator("[data-testid=group-message]")
            page.check("[data-testid=select-map-a]")  # a selection of one: rank 1 to map-a
            page.fill("[data-testid=group-rank]", "1")
            page.click("[data-testid=group-push]")
            result.locator('li[data-robot="map-a"]').filter(has_text="acknowledged").wait_for()
            assert result.locator("li").count() == 1
            assert a.controller is not None and a.controller.provenance["rank"] == 1
            assert b.controller is None
            page.fill("[data-testid=group-rank]", "")
            page.select_option("[data-testid=group-target]", "all")
            page.click("[data-testid=group-push]")
            for robot in ("map-a", "map-b"):
                result.locator(f'li[data-robot="{robot}"]').filter(
                    has_text="acknowledged"
                ).wait_for()
            assert result.locator("li").count() == 2  # offline robots of earlier tests: not pushed
            assert a.controller is not None and a.controller.sha256 == best
            assert b.controller is not None and b.controller.sha256 == best
            before = positions(page)
            page.wait_for_function(
                """(before) => {
                    const now = JSON.parse(document.querySelector('#colony-map').dataset.positions);
                    return ['map-a', 'map-b'].every((id) => now[id] &&
                        (now[id][0] !== before[id][0] || now[id][1] !== before[id][1]));
                }""",
                arg=before,
            )
            after = positions(page)
            assert {"map-a", "map-b"} <= set(after) and after != before
            maze = client.get("/api/colony/map").json()["maze"]
            for x, y in after.values():  # drawn inside the maze
                assert 0 < x < maze["width"] and 0 < y < maze["height"]

            page.select_option("[data-testid=policy-map-a]", "off")
            page.locator("[data-testid=policy-result-map-a]").filter(has_text="its own").wait_for()
            robot = client.get("/api/robots/map-a").json()
            assert (robot["replacement"], robot["replacement_source"]) == ("off", "robot")
            assert client.get("/api/robots/map-b").json()["replacement_source"] == "colony"

            page.click("[data-testid=details-map-b]")
            page.wait_for_function(
                "Number(document.querySelector('#robot-timeline').dataset.points) > 40"
            )
            page.wait_for_selector("#robot-timeline canvas")
            page.screenshot(path=str(shots / "dashboard-colony.png"), full_page=True)


def test_an_archive_is_mapped_and_an_elite_pushed_to_a_robot_with_a_click(
    served: Served, db_url: str, page: Any, tmp_path: Path, shots: Path
) -> None:
    """A map-elites run's page maps its archive; a click on an elite picks it, and Push elite
    sends that controller to the chosen robot."""
    with httpx.Client(base_url=served.url, timeout=30) as client:
        run_id = client.post("/api/runs", json={**QUICK, "strategy": "map-elites"}).json()["id"]
        assert eventually(lambda: client.get(f"/api/runs/{run_id}").json()["status"] == "completed")
        cells = client.get(f"/api/runs/{run_id}/archive").json()["cells"]
        colony = Colony(served.url, db_url, run_id, served.app, tmp_path)
        with robot_link(colony) as link, virtual_robot("virt-qd", link, tmp_path) as (agent, _):
            assert eventually(lambda: online(client, "virt-qd"))
            page.goto(f"{served.url}/?run={run_id}")
            page.wait_for_function(
                f"document.querySelector('#archive-map').dataset.elites === '{len(cells)}'"
            )
            page.locator("[data-testid=run-robustness]").wait_for()  # the layout is complete
            canvas = page.locator("#archive-map")
            box = canvas.bounding_box()
            x, y = cells[0]["descriptors"]
            # relative to the canvas where it is when clicked: immune to lines appearing above
            w, h = box["width"], box["height"]
            at = {"x": min(max(x * w, 1.0), w - 1.0), "y": min(max((1 - y) * h, 1.0), h - 1.0)}
            canvas.click(position=at)
            message = page.locator("[data-testid=archive-message]")
            message.filter(has_text="elite 0:").wait_for()
            page.locator('#archive-table tr.picked[data-elite="0"]').wait_for()
            page.locator('#archive-robot option[value="virt-qd"]').wait_for(state="attached")
            page.select_option("[data-testid=archive-robot]", "virt-qd")
            page.click("[data-testid=archive-push]")
            message.filter(has_text="virt-qd acknowledged").wait_for()
            assert agent.controller is not None
            assert agent.controller.sha256 == cells[0]["sha256"]
            page.screenshot(path=str(shots / "dashboard-archive.png"), full_page=True)


def test_with_a_token_the_page_steers_only_once_the_token_is_entered(
    tmp_path: Path, page: Any
) -> None:
    settings = Settings(
        db_url=f"sqlite:///{tmp_path / 'colony.db'}",
        executors=1,
        zenoh=False,
        api_token="s3cret-token",
        read_open=False,
    )
    with serve(tmp_path, create_app(settings)) as served:
        headers = {"Authorization": "Bearer s3cret-token"}
        with httpx.Client(base_url=served.url, timeout=30, headers=headers) as client:
            run_id = client.post("/api/runs", json=LONG).json()["id"]
            page.goto(f"{served.url}/?run={run_id}")
            assert page.locator(f'#runs-table tr[data-run="{run_id}"]').count() == 0  # closed
            page.fill("[data-testid=token]", "s3cret-token")
            page.dispatch_event("[data-testid=token]", "change")
            page.wait_for_selector(f'#runs-table tr[data-run="{run_id}"]')  # stream with token
            page.wait_for_selector("[data-testid=run-status]:text-is('running')")
            page.click("[data-testid=pause]")
            page.wait_for_selector("[data-testid=run-status]:text-is('paused')")
            assert client.get(f"/api/runs/{run_id}").json()["status"] == "paused"
            client.post(f"/api/runs/{run_id}/cancel")


STUDY = {
    "name": "browser-study",
    "base": {
        "population": 8,
        "generations": 12,
        "steps": 20,
        "trials": 1,
        "job_size": 4,
        "validation": {"poses": 3, "steps": 60, "candidates": 3},
    },
    "conditions": {"delays": {"network": "paper-best"}, "reactive": {"network": "reactive"}},
    "seeds": [1, 2, 3],
}
"""Six short runs (a few seconds in all): two conditions with three seeds give comparisons."""


def test_studies_page_drills_into_a_run_and_runs_overlay(
    served: Served, page: Any, shots: Path
) -> None:
    with httpx.Client(base_url=served.url, timeout=30) as client:
        reply = client.post("/api/studies", json=STUDY)
        assert reply.status_code == 201, reply.text
        study_id = reply.json()["id"]
        assert eventually(
            lambda: client.get(f"/api/studies/{study_id}").json()["status"] == "completed", 120
        )
        assert eventually(  # the champions' exploration figures come from jobs afterwards
            lambda: all(
                None not in r["metrics"].values()
                for r in client.get(f"/api/studies/{study_id}").json()["runs"]
            ),
            120,
        )
        study = client.get(f"/api/studies/{study_id}").json()
    assert study["comparisons"] and study["verdicts"]

    page.goto(f"{served.url}/#studies")
    row = page.locator(f'#studies-table tr[data-study="{study_id}"]')
    row.filter(has_text="6 / 6").wait_for()  # name, status, runs done / total
    assert "browser-study" in row.inner_text() and "completed" in row.inner_text()
    row.click()
    page.wait_for_selector('#study-curve[data-series="2"] canvas')
    points = int(page.get_attribute("#study-curve", "data-points"))
    assert points == len(study["summary"][0]["generations"]) == 12
    table = page.locator("#comparisons-table tbody tr")
    assert table.count() == len(study["comparisons"])
    first = study["comparisons"][0]
    assert table.first.inner_text().split("\t")[:3] == [first["a"], first["b"], first["metric"]]
    page.locator("#verdicts li").filter(has_text=study["verdicts"][0]).wait_for()
    page.screenshot(path=str(shots / "dashboard-studies.png"), full_page=True)

    run = study["runs"][-1]
    page.click(f'#study-runs-table tr[data-run="{run["run_id"]}"]')  # drill down to the run
    page.wait_for_selector(f"#run-title:text-is('Run {run['run_id']}: {run['name']}')")
    assert page.evaluate("location.hash") == "#runs"
    page.wait_for_function("Number(document.querySelector('#curve').dataset.points) == 12")
    cells = page.locator(f'#runs-table tr[data-run="{run["run_id"]}"] td').all_inner_texts()
    assert cells[2:7] == [
        run["name"],
        "reactive",
        "paper",
        str(run["seed"]),
        f"browser-study / {run['condition']}",
    ]

    a, b = study["runs"][0]["run_id"], study["runs"][3]["run_id"]  # one of each condition
    assert page.is_disabled("[data-testid=overlay]")
    page.check(f"[data-testid=check-{a}]")
    page.check(f"[data-testid=check-{b}]")
    page.click("[data-testid=overlay]")
    page.wait_for_selector('#overlay-curve[data-series="2"] canvas')
    legend = page.locator("#overlay-curve .u-legend").inner_text()
    assert f"{a} browser-study/" in legend and f"{b} browser-study/" in legend


def test_api_docs_render_offline(served: Served, page: Any) -> None:
    """Swagger UI draws every operation with requests to this server only (a lab network is
    often offline)."""
    hosts: set[str] = set()
    page.on("request", lambda request: hosts.add(request.url.split("/")[2]))
    page.goto(f"{served.url}/docs")
    page.locator(".opblock-summary-path", has_text="/api/runs").first.wait_for()
    assert page.locator(".opblock").count() >= 20
    assert hosts == {served.url.split("/")[2]}
