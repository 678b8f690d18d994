"""The learner's HTTP face: the dashboard at /, and /status, /history, /healthz, /metrics, /media/.

- `/` is a static page (services/learner/dashboard/: HTML, CSS, JavaScript and
  the vendored uPlot; no build step, nothing fetched from the internet) that
  polls /status and /history.
- `/history`: the learner's bounded series of /status figures, the
  evaluations of eval.csv (at most eval_series.MAX_EVALS, evenly spaced), and
  the evaluator's media manifest (the autoencoder's view, evaluation videos), whose files are under /media/.
- `/healthz`: 200 "ok"; 200 "degraded: <reasons>" while the learner trains on past a fault (writes
  the disk refuses); or 503 "unhealthy: <reasons>".
- `/metrics`: Prometheus' text format, from prometheus-client (metrics.py).
- `POST /control/<name>`: the learner's controls (`checkpoint`, `stop`), which change its state.
  With a token configured (env NASA_API_TOKEN or the learner's --api-token-file) they answer 401
  unless the request carries `Authorization: Bearer <token>`; the read-only routes stay open.

`serve_folder` answers the same routes for a stopped run from its folder
(`nasa status --data DIR --serve`).
"""

from __future__ import annotations

import asyncio
import hmac
import ipaddress
import json
import math
import os
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import uvicorn
from fastapi import Depends, FastAPI, Header, HTTPException
from fastapi.responses import FileResponse, PlainTextResponse, Response
from uvicorn.protocols.http.h11_impl import H11Protocol, h11  # the h11 that uvicorn's protocol runs on

from services.learner import history as run_history
from services.learner.eval_series import EvalSeries
from services.learner.metrics import status_metrics
from shared.config import ConfigError
from shared.files import finite_only
from shared.run_config import read_json_object

DASHBOARD = Path(__file__).resolve().parent / "dashboard"
MEDIA_DIR = "media"
MEDIA_MANIFEST = "media.json"
PROMETHEUS_TEXT = "text/plain; version=0.0.4; charset=utf-8"
# The page's files are asked for again on each load (a 304 while unchanged): without this a browser
# keeps a copy it deems fresh from the file's age, and runs an older page against an upgraded learner.
REVALIDATE = {"Cache-Control": "no-cache"}
MAX_CONNECTIONS = 128
"""Connections the status API holds at once; one more is closed as soon as it is accepted."""
REQUEST_HEAD_S = 10.0
"""How long a connection may take to send a whole request line and headers."""
MAX_PER_PEER = 32
"""Connections one client address holds at once; one more from it is closed as soon as it is accepted."""
WRITE_STALL_S = 10.0
"""How long a response waiting to be sent may go without the client reading any of it."""
RENDER_EVERY_S = 1.0
"""/status, /history and /metrics: a body is rendered at most once in this long, however many clients
poll (the dashboard polls every 2 s)."""
CHECKPOINT_EVERY_S = 10.0
"""POST /control/checkpoint: the least time between the end of one asked-for checkpoint and the next."""


def make_app(status: Callable[[], dict], health: Callable[[], list[str] | bool],
             history: Callable[[], list[dict]] | None = None, metrics: Callable[[], bytes] | None = None,
             data: Path | None = None, controls: dict[str, Callable[[], str]] | None = None,
             token: str | None = None, degraded: Callable[[], list[str]] | None = None,
             render_every_s: float | None = None) -> FastAPI:
    """The routes; `health` returns the reasons the learner is unhealthy (empty: healthy), `degraded`
    those it works on with a fault (writes the disk refuses).
    `controls`: name -> action (returns what it did), each at POST /control/<name>, behind `token`.
    `render_every_s` (default RENDER_EVERY_S): how long a rendered /status, /history or /metrics is
    served again."""
    app = FastAPI(title="nasa-td3 learner", docs_url=None, redoc_url=None)
    every_s = RENDER_EVERY_S if render_every_s is None else render_every_s
    status_body = Rendered(lambda: _json_bytes(status()), every_s)
    evals = EvalSeries(Path(data) / "eval.csv") if data is not None else list
    history_body = Rendered(lambda: _json_bytes({"points": history() if history else [],
                                                 "evals": evals(), "media": media(data)}), every_s)
    metrics_body = Rendered(metrics if metrics is not None else lambda: status_metrics(status()), every_s)
    for name, action in (controls or {}).items():
        _add_control(app, name, action, token)

    @app.get("/")
    def get_dashboard() -> FileResponse:
        return FileResponse(DASHBOARD / "index.html", media_type="text/html", headers=REVALIDATE)

    @app.get("/static/{name}")
    def get_static(name: str) -> FileResponse:
        return FileResponse(_inside(DASHBOARD, name), headers=REVALIDATE)

    @app.get("/status")
    def get_status() -> Response:
        return Response(status_body(), media_type="application/json")

    @app.get("/history")
    def get_history() -> Response:
        return Response(history_body(), media_type="application/json")

    @app.get("/media/{name}")
    def get_media(name: str) -> FileResponse:
        if data is None:
            raise HTTPException(404)
        return FileResponse(_inside(Path(data) / MEDIA_DIR, name))

    @app.api_route("/healthz", methods=["GET", "HEAD"])  # uptime checkers often ask with HEAD
    def get_healthz() -> PlainTextResponse:
        reasons = health()
        if isinstance(reasons, bool):  # a health callable of the older form: True when healthy
            reasons = [] if reasons else ["stopping"]
        faults = degraded() if degraded is not None else []
        if reasons:
            return PlainTextResponse("unhealthy: " + "; ".join(reasons + faults) + "\n", status_code=503)
        if faults:  # 200: it trains on, and a restart (a liveness probe's) would meet the same disk
            return PlainTextResponse("degraded: " + "; ".join(faults) + "\n")
        return PlainTextResponse("ok\n")

    @app.get("/metrics")
    def get_metrics() -> Response:
        return Response(metrics_body(), media_type=PROMETHEUS_TEXT)

    return app


def _add_control(app: FastAPI, name: str, action: Callable[[], str], token: str | None) -> None:
    @app.post(f"/control/{name}", dependencies=[Depends(bearer_guard(token))], status_code=202)
    def control() -> Response:
        return _json({"control": name, "done": action()}, status=202)


class CheckpointRequests:
    """POST /control/checkpoint's requests, for the update loop to act on. A request while one is
    pending (asked for, not yet written) joins it, and one within CHECKPOINT_EVERY_S of the last
    written is refused with 429: a client that posts in a loop would otherwise have the learner
    write checkpoints back to back instead of training."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._pending = False
        self._written_at: float | None = None

    def ask(self) -> str:
        """What the request did; HTTPException 429 (with Retry-After) when too soon after the last."""
        with self._lock:
            if self._pending:
                return "a checkpoint is already pending; this request joins it"
            now = time.monotonic()
            if self._written_at is not None and (wait := self._written_at + CHECKPOINT_EVERY_S - now) > 0:
                ago = now - self._written_at
                raise HTTPException(429, f"the last checkpoint asked for ended {ago:.1f} s ago; "
                                         f"ask again in {wait:.1f} s",
                                    headers={"Retry-After": str(math.ceil(wait))})
            self._pending = True
            return "a checkpoint is written at the next update"

    def pending(self) -> bool:
        return self._pending

    def written(self) -> None:
        """The loop wrote (or tried to write) the checkpoint asked for."""
        with self._lock:
            self._pending = False
            self._written_at = time.monotonic()


def bearer_guard(token: str | None) -> Callable[[str | None], None]:
    """A dependency that lets a request through only with `Authorization: Bearer <token>` (any request
    when `token` is None; the scheme's case is free, as HTTP's auth schemes are). The comparison
    takes the same time wherever the two first differ."""
    expected = (token or "").encode()

    def guard(authorization: str | None = Header(default=None)) -> None:
        if token is None:
            return
        scheme, _, given = (authorization or "").strip().partition(" ")
        if scheme.lower() != "bearer" or not hmac.compare_digest(given.strip().encode(), expected):
            raise HTTPException(401, "a bearer token is required", headers={"WWW-Authenticate": "Bearer"})

    return guard


def api_token(path: Path | None = None) -> str | None:
    """The control endpoints' token: env NASA_API_TOKEN, else the first line of `path`; None: open.
    ConfigError for a file that cannot be read or holds no token."""
    token = os.environ.get("NASA_API_TOKEN", "")
    if not token and path is not None:
        try:
            lines = Path(path).read_text().splitlines()
        except (OSError, UnicodeDecodeError) as err:
            raise ConfigError(f"--api-token-file {path} is unreadable: {err}") from err
        token = lines[0] if lines else ""
        if not token.strip():  # a file was given for a token: open controls would be a surprise
            raise ConfigError(f"--api-token-file {path} holds no token (its first line is empty)")
    return token.strip() or None


def is_loopback(host: str) -> bool:
    """Whether `host` (an address or `localhost`) is reachable from this host only."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


class Rendered:
    """A response body rendered at most once per `every_s`: the first request after that renders it
    (the others meanwhile wait for it), and every request until then gets the same bytes. Each
    render costs the learner's process CPU and interpreter lock, which its updates need; N clients
    polling cost one render, not N."""

    def __init__(self, render: Callable[[], bytes], every_s: float) -> None:
        self.render, self.every_s = render, every_s
        self._lock = threading.Lock()
        self._body: bytes | None = None
        self._at = 0.0
        self.renders = 0

    def __call__(self) -> bytes:
        with self._lock:
            if self._body is None or time.monotonic() - self._at >= self.every_s:
                self._body = self.render()
                self._at = time.monotonic()
                self.renders += 1
            return self._body


def _json_bytes(body: dict) -> bytes:
    """JSON straight from json.dumps: FastAPI's encoder walks every value first, which costs the
    learner's process more than the encoding for a long history. A non-finite number (which
    JSON has no word for, and a browser refuses) goes out as null."""
    try:
        text = json.dumps(body, allow_nan=False)
    except ValueError:
        text = json.dumps(finite_only(body), allow_nan=False)
    return text.encode()


def _json(body: dict, status: int = 200) -> Response:
    return Response(_json_bytes(body), status_code=status, media_type="application/json")


def _inside(folder: Path, name: str) -> Path:
    """A file directly in `folder` (no path tricks), or 404."""
    path = folder / name
    if "/" in name or name.startswith("."):
        raise HTTPException(404)
    try:
        found = path.is_file()
    except OSError:  # a name the file system refuses (longer than it allows, ...) names no file
        found = False
    if not found:
        raise HTTPException(404)
    return path


def media(data: Path | None) -> dict | None:
    """The evaluator's media manifest (<data>/media/media.json), or None."""
    path = Path(data) / MEDIA_DIR / MEDIA_MANIFEST if data is not None else None
    if path is None or not path.exists():
        return None
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


class StoppedRunError(ValueError):
    """A run folder whose learner left no readable last status."""


def read_final_status(data: Path) -> dict:
    """The last /status the learner left in <data>/learner/status.json."""
    saved = Path(data) / "learner" / "status.json"
    if not Path(data).is_dir():
        raise StoppedRunError(f"there is no run folder {data}")
    if not saved.exists():
        if not saved.parent.exists() and (Path(data) / "eval.csv").exists():
            raise StoppedRunError(
                f"{data} is a `nasa train` run (no learner/ folder): it has no status API; its "
                f"evaluations are in {Path(data) / 'eval.csv'} (`nasa plot {data}`), its losses in "
                f"{Path(data) / 'tensorboard'}")
        # The learner writes it with each checkpoint (its stop's too) and as it resumes from one.
        raise StoppedRunError(f"there is no {saved}: this run's learner has written no checkpoint yet "
                              "(or the disk refused the file: see the learner's log)")
    return read_json_object(saved, StoppedRunError, "a status")


def folder_app(data: Path) -> FastAPI:
    """The dashboard of a stopped run: its last status, history, evaluations and media."""
    final = read_final_status(data)
    try:
        points = run_history.load(data)
    except run_history.HistoryError as err:
        # The status and evaluations still tell the run; only the series' charts stay empty.
        print(f"nasa status: {err}; the dashboard shows no series", file=sys.stderr, flush=True)
        points = []
    return make_app(lambda: final, lambda: ["the run has stopped"], lambda: points, data=data)


class GuardedH11Protocol(H11Protocol):
    """uvicorn's HTTP/1.1 with the limits it lacks. It holds a connection that sends no request (or
    half of one), or that never reads its response, for ever (a close waits for the unsent bytes),
    so such clients could take every connection slot and file descriptor of the learner's process:
    its checkpoint and log writes would fail, and no other client be served. Here a connection that
    has not sent a whole request head within REQUEST_HEAD_S is closed; one whose unsent response
    shrinks by nothing for WRITE_STALL_S is dropped (its unsent bytes with it); and one beyond
    MAX_CONNECTIONS at once, or beyond MAX_PER_PEER from one client address, is closed on arrival."""

    _head_timer: asyncio.TimerHandle | None = None
    _write_timer: asyncio.TimerHandle | None = None

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        peer = self.client[0] if self.client else None
        same_peer = sum(1 for c in self.connections if c.client is not None and c.client[0] == peer)
        if len(self.connections) > MAX_CONNECTIONS or (peer is not None and same_peer > MAX_PER_PEER):
            transport.close()
            return
        # Writing pauses as soon as the kernel's buffer holds no more, so the stall check below sees
        # every response the client leaves unread, however small.
        transport.set_write_buffer_limits(high=0)
        self._await_head()

    def pause_writing(self) -> None:
        super().pause_writing()
        self._watch_writes(self.transport.get_write_buffer_size())

    def resume_writing(self) -> None:
        self._writes_drained()
        super().resume_writing()

    def _watch_writes(self, unsent: int) -> None:
        """While writing is paused no more is written, so the unsent bytes only shrink as the client
        reads: none read in WRITE_STALL_S is a client that stopped reading."""
        self._writes_drained()
        self._write_timer = self.loop.call_later(WRITE_STALL_S, self._write_check, unsent)

    def _write_check(self, before: int) -> None:
        self._write_timer = None
        unsent = self.transport.get_write_buffer_size()
        if unsent >= before > 0:
            self.transport.abort()
        elif unsent > 0:
            self._watch_writes(unsent)

    def _writes_drained(self) -> None:
        if self._write_timer is not None:
            self._write_timer.cancel()
            self._write_timer = None

    def data_received(self, data: bytes) -> None:
        super().data_received(data)
        if self.conn.their_state is h11.IDLE:  # part of a request head: it must come whole in time
            self._await_head()
        else:
            self._head_received()

    def connection_lost(self, exc: Exception | None) -> None:
        self._head_received()
        self._writes_drained()
        super().connection_lost(exc)

    def _await_head(self) -> None:
        if self._head_timer is None:
            self._head_timer = self.loop.call_later(REQUEST_HEAD_S, self._head_late)

    def _head_received(self) -> None:
        if self._head_timer is not None:
            self._head_timer.cancel()
            self._head_timer = None

    def _head_late(self) -> None:
        self._head_timer = None
        if self.conn.their_state is h11.IDLE and not self.transport.is_closing():
            self.transport.close()


class StatusServer:
    """uvicorn in a daemon thread; stop() ends it."""

    def __init__(self, app: FastAPI, host: str, port: int) -> None:
        config = uvicorn.Config(app, host=host, port=port, log_level="warning", access_log=False,
                                http=GuardedH11Protocol)
        self.server = uvicorn.Server(config)
        self.thread = threading.Thread(target=self._serve, name="status-api", daemon=True)

    def _serve(self) -> None:
        try:
            self.server.run()
        except SystemExit:  # uvicorn's way out when it cannot bind: start() says why
            pass

    def start(self, timeout_s: float = 30.0) -> None:
        """Serve, once the port is bound; RunFolderError if it cannot be (another process has it:
        uvicorn's thread would end with a log line, and the run go on with no status API)."""
        from shared.faults import RunFolderError

        self.thread.start()
        deadline = time.monotonic() + timeout_s
        while not self.server.started:
            if not self.thread.is_alive():
                config = self.server.config
                raise RunFolderError(f"the status API cannot listen on {config.host}:{config.port} "
                                     "(in use by another process?); choose another --port")
            if time.monotonic() > deadline:
                return  # slow to start, not refused: it goes on starting
            time.sleep(0.02)

    def stop(self) -> None:
        self.server.should_exit = True
        self.thread.join(timeout=5.0)
