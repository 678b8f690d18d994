"""The learner's HTTP face: GET /status (JSON), /healthz, /metrics (Prometheus text format)."""

from __future__ import annotations

import threading
from collections.abc import Callable

import uvicorn
from fastapi import FastAPI
from fastapi.responses import PlainTextResponse


def make_app(status: Callable[[], dict], healthy: Callable[[], bool]) -> FastAPI:
    app = FastAPI(title="nasa-td3 learner", docs_url=None, redoc_url=None)

    @app.get("/status")
    def get_status() -> dict:
        return status()

    @app.get("/healthz")
    def get_healthz() -> PlainTextResponse:
        ok = healthy()
        return PlainTextResponse("ok\n" if ok else "unhealthy\n", status_code=200 if ok else 503)

    @app.get("/metrics")
    def get_metrics() -> PlainTextResponse:
        return PlainTextResponse(prometheus_text(status()), media_type="text/plain; version=0.0.4")

    return app


def _line(name: str, value: float | int | None, labels: dict[str, object] | None = None) -> str | None:
    if value is None:
        return None
    tags = ""
    if labels:
        tags = "{" + ",".join(f'{k}="{v}"' for k, v in labels.items()) + "}"
    return f"{name}{tags} {float(value):.17g}"


def prometheus_text(s: dict) -> str:
    """The status as Prometheus metrics (one gauge or counter per figure)."""
    base = {"run_id": s["run_id"]}
    intrinsic = s["intrinsic"]
    series: list[tuple[str, str, str, list[str | None]]] = [
        ("nasa_env_steps_total", "counter", "Environment steps stored by the replay",
         [_line("nasa_env_steps_total", s["env_steps"], base)]),
        ("nasa_updates_total", "counter", "Gradient updates of the learner",
         [_line("nasa_updates_total", s["updates"], base)]),
        ("nasa_env_steps_per_second", "gauge", "Environment steps per second (all actors)",
         [_line("nasa_env_steps_per_second", s["env_steps_per_s"], base)]),
        ("nasa_updates_per_second", "gauge", "Updates per second",
         [_line("nasa_updates_per_second", s["updates_per_s"], base)]),
        ("nasa_updates_per_env_step", "gauge", "Updates per env step after warm-up",
         [_line("nasa_updates_per_env_step", s["updates_per_env_step"], base)]),
        ("nasa_policy_version", "gauge", "Version of the newest published weights",
         [_line("nasa_policy_version", s["policy_version"], base)]),
        ("nasa_policy_lag_updates", "gauge",
         "Updates between the policy that collected a sampled transition and the learner's (mean, max)",
         [_line("nasa_policy_lag_updates", s["policy_lag"][k], {**base, "stat": k})
          for k in ("mean", "max")]),
        ("nasa_replay_size", "gauge", "Transitions in the replay",
         [_line("nasa_replay_size", s["replay"]["size"], base)]),
        ("nasa_replay_bytes", "gauge", "Replay memory in bytes",
         [_line("nasa_replay_bytes", s["replay"]["bytes"], base)]),
        ("nasa_invalid_messages_total", "counter", "Messages that failed validation",
         [_line("nasa_invalid_messages_total", s["invalid_messages"], base)]),
        ("nasa_eval_return_mean", "gauge", "Mean return of the newest evaluation",
         [_line("nasa_eval_return_mean", s["eval"]["mean"], base)]),
        ("nasa_actor_alive", "gauge", "1 if the actor's liveliness token is present",
         [_line("nasa_actor_alive", int(a["alive"]), {**base, "actor": a["id"]}) for a in s["actors"]]),
        ("nasa_actor_env_steps_total", "counter", "Env steps of the actor's current incarnation",
         [_line("nasa_actor_env_steps_total", a["env_steps"], {**base, "actor": a["id"]})
          for a in s["actors"]]),
        ("nasa_actor_env_steps_per_second", "gauge", "Env steps per second of the actor over ~10 s",
         [_line("nasa_actor_env_steps_per_second", a["steps_per_s"], {**base, "actor": a["id"]})
          for a in s["actors"]]),
        ("nasa_intrinsic_scored_total", "counter", "Transitions given an intrinsic reward",
         [_line("nasa_intrinsic_scored_total", intrinsic["scored"], base)]),
        ("nasa_intrinsic_scored_at_first_sample_total", "counter",
         "Transitions scored when a training batch first brought them, not on arrival",
         [_line("nasa_intrinsic_scored_at_first_sample_total", intrinsic["scored_at_first_sample"], base)]),
        ("nasa_intrinsic_mean", "gauge", "Running mean of each intrinsic reward",
         [_line("nasa_intrinsic_mean", intrinsic[f"{k}_mean"], {**base, "name": k})
          for k in ("novelty", "surprise")]),
        ("nasa_loss", "gauge", "Recent mean of each loss",
         [_line("nasa_loss", v, {**base, "name": k}) for k, v in s["losses"].items()]),
    ]
    out = []
    for name, kind, help_text, lines in series:
        lines = [x for x in lines if x is not None]
        if not lines:
            continue
        out += [f"# HELP {name} {help_text}", f"# TYPE {name} {kind}", *lines]
    return "\n".join(out) + "\n"


class StatusServer:
    """uvicorn in a daemon thread; stop() ends it."""

    def __init__(self, app: FastAPI, host: str, port: int) -> None:
        config = uvicorn.Config(app, host=host, port=port, log_level="warning", access_log=False)
        self.server = uvicorn.Server(config)
        self.thread = threading.Thread(target=self.server.run, name="status-api", daemon=True)

    def start(self) -> None:
        self.thread.start()

    def stop(self) -> None:
        self.server.should_exit = True
        self.thread.join(timeout=5.0)
