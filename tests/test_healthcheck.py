"""deploy/healthcheck.py against odd answers on loopback: redirects, another server's 200, a listener
on one address."""

from __future__ import annotations

import importlib.util
import socket
import threading
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import pytest
from system_harness import REPO


def _load():  # noqa: ANN202 (the module)
    spec = importlib.util.spec_from_file_location("healthcheck", REPO / "deploy" / "healthcheck.py")
    module = importlib.util.module_from_spec(spec)  # type: ignore[arg-type]
    spec.loader.exec_module(module)  # type: ignore[union-attr]
    return module


healthcheck = _load()
ANSWERS = {"/healthz": (200, b"ok\n")}


class Handler(BaseHTTPRequestHandler):
    def do_GET(self) -> None:  # noqa: N802 (http.server's name)
        status, body = ANSWERS.get(self.path, (200, b"<html>a page</html>"))
        self.send_response(status)
        if 300 <= status < 400:
            self.send_header("Location", "/elsewhere")
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, *args: object) -> None:
        pass


@pytest.fixture
def server(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    monkeypatch.setenv("NASA_STATUS_PORT", str(httpd.server_address[1]))
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    yield
    httpd.shutdown()
    httpd.server_close()


@pytest.mark.parametrize(("answer", "healthy"), [
    ((200, b"ok\n"), True), ((503, b"unhealthy: stopping\n"), False),
    ((200, b"degraded: writes failing: train.csv (last: ...)\n"), True),
    ((302, b""), False), ((200, b"<html>another server</html>"), False), ((200, b""), False)])
def test_the_learner_is_healthy_only_on_its_own_ok(server: None, monkeypatch: pytest.MonkeyPatch,
                                                    answer: tuple[int, bytes], healthy: bool) -> None:
    monkeypatch.setitem(ANSWERS, "/healthz", answer)
    assert healthcheck.learner() is healthy


def test_a_router_listening_on_one_address_is_checked_there(monkeypatch: pytest.MonkeyPatch) -> None:
    """Not on 127.0.0.1, where a router bound to another address never answers."""
    with socket.socket() as listener:
        listener.bind(("127.0.0.2", 0))
        listener.listen()
        monkeypatch.setenv("NASA_ZENOH_LISTEN", f"tcp/127.0.0.2:{listener.getsockname()[1]}")
        assert healthcheck.router()
        monkeypatch.setenv("NASA_ZENOH_LISTEN", f"tcp/0.0.0.0:{listener.getsockname()[1]}")
        assert not healthcheck.router()  # nothing on 127.0.0.1 at that port


@pytest.mark.parametrize("suffix", ["?prio=1-7", "#iface=lo", "?rel=1#iface=lo"])
def test_an_endpoint_with_metadata_or_config_is_checked_at_its_address(monkeypatch: pytest.MonkeyPatch,
                                                                       suffix: str) -> None:
    """Zenoh's endpoints carry `?metadata` and `#config` after the address: neither is the port."""
    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen()
        port = listener.getsockname()[1]
        monkeypatch.setenv("NASA_ZENOH_LISTEN", f"tcp/127.0.0.1:{port}{suffix}")
        monkeypatch.setenv("NASA_ZENOH_CONNECT", f"tcp/127.0.0.1:{port}{suffix},tcp/10.0.0.9:7447")
        assert healthcheck.router()
        assert healthcheck.reaches_router()


def test_a_learner_listening_on_one_address_is_checked_there(monkeypatch: pytest.MonkeyPatch) -> None:
    """Not on 127.0.0.1, where a status API bound to another address (NASA_STATUS_HOST) never answers."""
    httpd = ThreadingHTTPServer(("127.0.0.2", 0), Handler)
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    try:
        monkeypatch.setenv("NASA_STATUS_PORT", str(httpd.server_address[1]))
        monkeypatch.setenv("NASA_STATUS_HOST", "127.0.0.2")
        assert healthcheck.learner()
        monkeypatch.setenv("NASA_STATUS_HOST", "0.0.0.0")
        assert not healthcheck.learner()  # nothing on 127.0.0.1 at that port
    finally:
        httpd.shutdown()
        httpd.server_close()
