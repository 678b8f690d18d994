"""The dashboard in a real browser: the system on loopback, / opened in headless Chromium.

Chromium is Debian's package (scripts/setup.sh installs it), driven by
Playwright for Python with the system browser (executable_path): nothing is
downloaded. While the run goes on, the page's return curve and actors table
must show the learner's values; once it has stopped, the same page served from
the run folder (`nasa status --data DIR --serve`) must show the last /status
exactly. Screenshots are left in the test's tmp dir.
"""

from __future__ import annotations

import json
import math
import shutil
import socket
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx
import pytest
from prometheus_client.parser import text_string_to_metric_families
from system_harness import System, assert_eval_steps
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from nasa.up import free_port
from services.learner.status_api import StatusServer, folder_app
from shared.video import count_frames

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
pytestmark = pytest.mark.skipif(CHROMIUM is None, reason="no chromium (scripts/setup.sh installs it)")
STEPS, EVAL_EVERY = 300, 100
READY = """() => {
  const d = window.nasaDashboard;
  return d && d.state.polls > 0 && d.charts.eval.data[0].length >= 2
    && document.querySelectorAll('#actors tbody tr').length === 2;
}"""
SHOWN = """() => ({
  eval: window.nasaDashboard.charts.eval.data,
  latest: {...document.getElementById('eval-latest').dataset},
  actors: [...document.querySelectorAll('#actors tbody tr')].map(tr =>
    Object.fromEntries([...tr.cells].map(td => [td.dataset.key, td.dataset.value]))),
  polls: window.nasaDashboard.state.polls,
})"""


def _value(text: str) -> float | str:
    """A cell's value as a number where it is one (JavaScript writes 7.0 as "7")."""
    try:
        return float(text)
    except ValueError:
        return text


def shown_matches(shown: dict, status: dict, evals: list[dict], exact: bool) -> list[str]:
    """What differs between the page and the learner's /status (and /history's evaluations)."""
    diffs = []
    steps, means, reference = shown["eval"]
    if steps != [e["step"] for e in evals] or means != [e["mean"] for e in evals]:
        diffs.append(f"return curve {steps} {means} vs eval.csv {evals}")
    if reference != [evals[0]["mean"]] * len(evals) or evals[0]["step"] != 0:
        diffs.append(f"reference line {reference} vs the step-0 evaluation {evals[0]}")
    e = status["eval"]
    # The curve comes from eval.csv, which keeps fewer digits than /status.
    if steps[-1] != e["step"] or not math.isclose(means[-1], e["mean"], rel_tol=1e-5, abs_tol=1e-5) \
            or shown["latest"] != {"step": str(e["step"]), "mean": str(e["mean"])}:
        diffs.append(f"latest evaluation {steps[-1]}, {means[-1]}, {shown['latest']} vs /status {e}")
    keys = ["id", "incarnation", "alive"] + (["env_steps", "episodes", "steps_per_s", "policy_version",
                                               "last_seen_s"] if exact else [])
    table = [{k: _value(row[k]) for k in keys} for row in shown["actors"]]
    want = [{k: _value(str(a[k]).lower() if isinstance(a[k], bool) else str(a[k])) for k in keys}
            for a in status["actors"]]
    if table != want:
        diffs.append(f"actors table {table} vs /status {want}")
    return diffs


def check_page(page, url: str, exact: bool, timeout_s: float = 60.0) -> dict:  # noqa: ANN001
    """Wait until the page shows what /status says (the run moves on between two reads: retry)."""
    page.wait_for_function(READY, timeout=timeout_s * 1000)
    deadline, diffs = time.monotonic() + timeout_s, ["not compared"]
    while time.monotonic() < deadline:
        status = httpx.get(url + "/status", timeout=5).json()
        evals = httpx.get(url + "/history", timeout=5).json()["evals"]
        shown = page.evaluate(SHOWN)
        if not (diffs := shown_matches(shown, status, evals, exact)):
            return status
        time.sleep(0.5)
    raise AssertionError("the dashboard does not show /status: " + "; ".join(diffs))


@contextmanager
def serving_folder(data: Path) -> Iterator[str]:
    """A stopped run's dashboard served from its folder (`nasa status --data DIR --serve`): its URL."""
    port = free_port()
    server = StatusServer(folder_app(data), "127.0.0.1", port)
    server.start()
    try:
        url = f"http://127.0.0.1:{port}"
        wait_listening(url)
        yield url
    finally:
        server.stop()


def with_stopped_status(data: Path) -> Path:
    """A stopped run's folder holding only its last status (the observability tests' STATUS)."""
    from tests.test_observability import STATUS

    (data / "learner").mkdir()
    (data / "learner" / "status.json").write_text(json.dumps(STATUS))
    return data


@contextmanager
def chromium_page() -> Iterator:
    """A page of a headless Chromium (playwright's Page), closed after."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox"], headless=True)
        try:
            yield browser.new_page()
        finally:
            browser.close()


def wait_listening(url: str, timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            httpx.get(url + "/healthz", timeout=2)
            return
        except httpx.HTTPError:
            time.sleep(0.2)
    raise AssertionError(f"nothing answers on {url}")


def metric_values(url: str) -> dict[tuple[str, tuple], float]:
    text = httpx.get(url + "/metrics", timeout=5).text
    return {(s.name, tuple(sorted(s.labels.items()))): s.value
            for family in text_string_to_metric_families(text) for s in family.samples}


@pytest.mark.timeout(600)
def test_dashboard_shows_the_run_in_chromium(tmp_path):
    from playwright.sync_api import sync_playwright

    data = tmp_path / "run"
    system = System(data, actors=2, steps=STEPS,
                    extra=["--eval-every", str(EVAL_EVERY), "--eval-episodes", "1"])
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox"], headless=True)
        page = browser.new_page(viewport={"width": 1280, "height": 1600})
        try:
            system.wait_for("an evaluation after step 0 and both actors stepping",
                            lambda s: (s["eval"]["step"] or 0) >= EVAL_EVERY and len(s["actors"]) == 2
                            and all(a["env_steps"] > 0 for a in s["actors"]), timeout=300)
            page.goto(system.url + "/")
            status = check_page(page, system.url, exact=False)
            page.screenshot(path=str(tmp_path / "dashboard-live.png"), full_page=True)
            metrics = metric_values(system.url)
            assert metrics[("nasa_actor_alive", (("actor", "0"),))] == 1.0
            assert metrics[("nasa_run_updates", ())] >= status["updates"]
            assert metrics[("nasa_updates_total", ())] >= status["updates"]  # one learner since step 0
            assert metrics[("nasa_update_duration_seconds_count", ())] > 0
            system.wait_exit(timeout=240)
            assert all(c.exited == 0 for c in system.sup.children.values()), system.logs()
        finally:
            system.close()

        # The stopped run, from its folder: the same page shows the learner's last status exactly,
        # at a phone's width too.
        try:
            with serving_folder(data) as url:
                page.goto(url + "/")
                final = check_page(page, url, exact=True)
                assert final == json.loads((data / "learner" / "status.json").read_text())
                assert final["eval"]["step"] == STEPS
                page.wait_for_function("() => document.getElementById('ae-image').naturalWidth > 0")
                assert page.locator("#videos a").count() >= 1
                page.screenshot(path=str(tmp_path / "dashboard-stopped.png"), full_page=True)
                page.set_viewport_size({"width": 390, "height": 844})
                page.wait_for_timeout(500)
                width = page.evaluate("document.documentElement.scrollWidth")
                assert width <= 390, f"the page is {width} px wide at a phone's 390 px"
                page.screenshot(path=str(tmp_path / "dashboard-phone.png"), full_page=True)
        finally:
            browser.close()

    # What else the run left: the learner's TensorBoard scalars, the evaluator's view and video.
    acc = EventAccumulator(str(data / "tensorboard" / "learner"))
    acc.Reload()
    tags = set(acc.Tags()["scalars"])
    assert {"eval/return_mean", "train/episode_return", "rates/updates_per_s", "policy_lag/mean",
            "ratio/updates_per_env_step", "replay/bytes", "intrinsic/novelty_mean"} <= tags, tags
    assert_eval_steps([e.step for e in acc.Scalars("eval/return_mean")], STEPS, EVAL_EVERY)
    media = json.loads((data / "media" / "media.json").read_text())
    assert media["autoencoder"]["step"] == STEPS and len(media["autoencoder"]["novelty"]) > 0
    first = media["videos"][0]
    assert first["step"] == 0 and count_frames(data / "media" / first["file"]) == first["frames"] > 0
    assert (tmp_path / "dashboard-stopped.png").stat().st_size > 10_000


def test_the_dashboard_writes_figures_as_a_person_reads_them(tmp_path):
    with serving_folder(with_stopped_status(tmp_path)) as url, chromium_page() as page:
        page.goto(url + "/")
        page.wait_for_function("() => window.nasaDashboard && window.nasaDashboard.fmt")
        shown = page.evaluate("() => [999.7, 1234.5, 12.345, 0.001234, 5, null]"
                              ".map(v => window.nasaDashboard.fmt(v))")
    assert shown == ["1,000", "1,235", "12.3", "0.00123", "5", "–"]


def test_a_non_finite_novelty_in_the_media_leaves_the_page_drawing(tmp_path):
    with_stopped_status(tmp_path)
    (tmp_path / "media").mkdir()
    # What the evaluator writes for an autoencoder that diverged: json.dumps' NaN, served as null.
    view = {"step": 100, "policy_version": 5, "autoencoder_version": 5, "novelty": [math.nan, 0.5],
            "image": "autoencoder.png"}
    (tmp_path / "media" / "media.json").write_text(json.dumps({"autoencoder": view, "videos": []}))
    with serving_folder(tmp_path) as url, chromium_page() as page:
        page.goto(url + "/")
        page.wait_for_function("() => document.getElementById('state').textContent !== 'connecting…'")
        shown = page.evaluate("() => [window.nasaDashboard.state.polls, document.getElementById('state')"
                              ".textContent, document.getElementById('ae-novelty').textContent]")
    assert shown[0] > 0 and not shown[1].startswith("no answer"), shown
    assert shown[2] == "novelty: –  0.500"


def test_a_learner_that_stops_answering_is_shown_as_not_answering(tmp_path):
    port = free_port()
    server = StatusServer(folder_app(with_stopped_status(tmp_path)), "127.0.0.1", port)
    server.start()
    url = f"http://127.0.0.1:{port}"
    with chromium_page() as page, socket.socket() as hung:
        try:
            wait_listening(url)
            page.goto(url + "/")
            page.wait_for_function("() => window.nasaDashboard.state.polls > 0")
            # The learner's process stops (SIGSTOP, a hang): its port still accepts, nothing answers.
            server.stop()
            hung.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            hung.bind(("127.0.0.1", port))
            hung.listen(64)
            page.wait_for_function("() => document.getElementById('state').textContent"
                                   ".startsWith('no answer')", timeout=60_000)
            state = page.evaluate("() => document.getElementById('state').textContent")
            polls = page.evaluate("() => window.nasaDashboard.state.polls")
            hung.close()  # the learner comes back (restarted): the page carries on
            server = StatusServer(folder_app(tmp_path), "127.0.0.1", port)
            server.start()
            page.wait_for_function(f"() => window.nasaDashboard.state.polls > {polls}", timeout=60_000)
        finally:
            server.stop()
    assert "no answer in" in state, state


def test_an_upgraded_dashboard_is_loaded_not_a_cached_one(tmp_path, monkeypatch):
    import os

    from services.learner import status_api

    page_files = tmp_path / "dashboard"
    shutil.copytree(status_api.DASHBOARD, page_files)
    month_ago = time.time() - 30 * 86400  # an installed package's files: a browser deems them fresh
    for f in page_files.iterdir():
        os.utime(f, (month_ago, month_ago))
    monkeypatch.setattr(status_api, "DASHBOARD", page_files)
    with serving_folder(with_stopped_status(tmp_path)) as url, chromium_page() as page:
        page.goto(url + "/")
        page.wait_for_function("() => window.nasaDashboard.state.polls > 0")
        script = page_files / "dashboard.js"  # the learner is upgraded: a new page script
        script.write_text(script.read_text() + "\nwindow.nasaDashboard.upgraded = true;\n")
        page.goto(url + "/")
        page.wait_for_function("() => window.nasaDashboard && window.nasaDashboard.state")
        upgraded = page.evaluate("() => window.nasaDashboard.upgraded === true")
    assert upgraded
