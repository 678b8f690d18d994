"""Watching a run without a browser: /metrics, /healthz, /history, TensorBoard files, videos, logs."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import time

import httpx
import numpy as np
import pytest
import torch
from fastapi.testclient import TestClient
from prometheus_client.parser import text_string_to_metric_families
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
from tiny import tiny_config, tiny_run

from nasa.train import Trainer
from services.evaluator.media import AutoencoderTap, EvalMedia
from services.learner.history import History, HistoryError
from services.learner.metrics import ACTOR_FIGURES, INFO, SCALARS, LearnerMetrics, run_gauge
from services.learner.status import StatusBoard
from services.learner.status_api import StoppedRunError, folder_app, make_app
from shared.agents import make_agent
from shared.service import Log
from shared.video import count_frames

STATUS = {
    "run_id": "r1", "algo": "nasa_td3", "task": "cartpole-balance", "device": "cpu", "config_digest": "abc",
    "steps_budget": 1000, "action_repeat": 8, "warmup_steps": 20, "updates": 321,
    "updates_target_per_env_step": 1,
    "updates_per_env_step": 0.987, "policy_version": 320,
    "eval": {"step": 300, "mean": 123.5, "std": 4.25},
    "intrinsic": {"novelty_mean": 0.31, "surprise_mean": 0.002, "scored": 300, "scored_at_first_sample": 2,
                  "zeroed": 1},
    "resumed": False, "wall_s": 61.5, "env_steps": 345, "env_steps_per_s": 12.5, "updates_per_s": 11.25,
    "replay": {"size": 345, "bytes": 123456, "done": False, "dropped": 1, "invalid_messages": 3,
               "limiter_inserts": 345, "limiter_samples": 321, "write_error": "OSError: disk full"},
    "nonfinite": {"skipped_updates": 2, "dropped_batches": 1, "dropped_rows": [5, 9],
                  "losses": {"critic_loss": {"count": 2, "last": "nan"}}},
    "a_field_added_later": {"count": 7},
    "actors": [
        {"id": 0, "incarnation": 1111, "alive": True, "env_steps": 170, "episodes": 4, "policy_version": 300,
         "steps_per_s": 6.5, "last_seen_s": 0.25, "refused": 2, "fault": "estop",
         "env_step_seconds": {"count": 170, "sum": 0.85, "le": {"0.001": 0, "0.005": 150, "+Inf": 170}}},
        {"id": 1, "incarnation": 2222, "alive": False, "env_steps": 175, "episodes": 4, "policy_version": 280,
         "steps_per_s": 6.0, "last_seen_s": 3.5, "refused": 0, "fault": None, "env_step_seconds": None},
    ],
    "policy_lag": {"mean": 14.5, "max": 41},
    "losses": {"critic_loss": 0.5, "actor_loss": -1.25, "ae_loss": 0.03, "ensemble_loss": 0.001},
    "invalid_messages": 2,
    "writes": {"failed": {"train.csv": 3, "checkpoint": 1}, "failing": ["train.csv"],
               "last_error": "train.csv: OSError: [Errno 28] No space left on device",
               "last_error_at": "2026-12-06T03:40:00Z"},
}


def samples(text: str) -> dict[tuple[str, tuple], float]:
    out = {}
    for family in text_string_to_metric_families(text):
        for s in family.samples:
            out[(s.name, tuple(sorted(s.labels.items())))] = s.value
    return out


def expected_samples(status: dict) -> dict[tuple[str, tuple], float]:
    """Every figure of /status as the sample it must be in /metrics."""
    want: dict[tuple[str, tuple], float] = {}
    for path, name, kind, _ in SCALARS:
        value = status
        for key in path.split("."):
            value = value[key]
        if kind == "counter":  # the run's figure in a gauge; the counter counts from this process's start
            want[(run_gauge(name), ())] = float(value)
            value = 0
        want[(name, ())] = float(value)
    for key, value in status["policy_lag"].items():
        want[("nasa_policy_lag_updates", (("stat", key),))] = float(value)
    for key, value in status["losses"].items():
        want[("nasa_loss", (("name", key),))] = float(value)
    for key in ("novelty", "surprise"):
        want[("nasa_intrinsic_mean", (("name", key),))] = float(status["intrinsic"][f"{key}_mean"])
    for a in status["actors"]:
        for key, name, _, _ in ACTOR_FIGURES:
            want[(name, (("actor", str(a["id"])),))] = float(a[key])
        label = (("actor", str(a["id"])),)
        if a["fault"] is not None:
            want[("nasa_actor_fault_state", (*label, ("state", a["fault"])))] = 1.0
        if (h := a["env_step_seconds"]) is not None:
            want[("nasa_actor_env_step_duration_seconds_count", label)] = float(h["count"])
            want[("nasa_actor_env_step_duration_seconds_sum", label)] = h["sum"]
            for le, n in h["le"].items():
                want[("nasa_actor_env_step_duration_seconds_bucket", (*label, ("le", le)))] = float(n)
    for key, entry in status["nonfinite"]["losses"].items():
        want[("nasa_nonfinite_losses_total", (("name", key),))] = float(entry["count"])
    want[("nasa_replay_write_failing", ())] = 1.0
    for key, count in status["writes"]["failed"].items():
        want[("nasa_write_failures_total", (("file", key),))] = float(count)
        want[("nasa_write_failing", (("file", key),))] = float(key in status["writes"]["failing"])
    want[("nasa_status_a_field_added_later_count", ())] = 7.0  # a field no table names yet
    return want


def leaves(d: dict, prefix: str = "") -> set[str]:
    out = set()
    for k, v in d.items():
        if isinstance(v, dict):
            out |= leaves(v, f"{prefix}{k}.")
        elif isinstance(v, list):
            out |= {f"{prefix}{k}[].{field}" if isinstance(item, dict) else f"{prefix}{k}[]"
                    for item in v for field in (item if isinstance(item, dict) else [None])}
        else:
            out.add(prefix + k)
    return out


def test_metrics_parse_and_hold_every_figure_of_status():
    metrics = LearnerMetrics(lambda: STATUS, start=STATUS)
    metrics.update_seconds.observe(0.02)
    metrics.batch_wait_seconds.observe(0.001)
    client = TestClient(make_app(lambda: STATUS, lambda: [], metrics=metrics.render))
    got = samples(client.get("/metrics").text)
    for key, value in expected_samples(STATUS).items():
        assert got.get(key) == pytest.approx(value), key
    info = {k: v for (name, labels), _ in got.items() if name == "nasa_run_info" for k, v in labels}
    assert info == {k: STATUS[k] for k in INFO}
    assert got[("nasa_update_duration_seconds_count", ())] == 1
    assert got[("nasa_scoring_duration_seconds_count", ())] == 0
    assert got[("nasa_batch_wait_seconds_bucket", (("le", "0.001"),))] == 1
    # Every figure of /status is covered: a new field without a metric fails here.
    covered = {path for path, *_ in SCALARS} | {"policy_lag.mean", "policy_lag.max"} \
        | {f"losses.{k}" for k in STATUS["losses"]} | {"intrinsic.novelty_mean", "intrinsic.surprise_mean"} \
        | {f"actors[].{key}" for key, *_ in ACTOR_FIGURES} | {"actors[].id"} | set(INFO) \
        | {"actors[].fault", "actors[].env_step_seconds"} \
        | {"nonfinite.losses.critic_loss.count", "nonfinite.losses.critic_loss.last", "replay.write_error",
           "a_field_added_later.count"} | {"nonfinite.dropped_rows[]"} \
        | {f"writes.failed.{k}" for k in STATUS["writes"]["failed"]} \
        | {"writes.failing[]", "writes.last_error", "writes.last_error_at"}
    assert leaves(STATUS) <= covered, leaves(STATUS) - covered
    # An actor whose environment reports no fault state (a suite task) has no fault series.
    assert not any(name == "nasa_actor_fault_state" and ("actor", "1") in labels for name, labels in got)
    # Counters end in _total; no series carries the run id.
    assert all(name.endswith("_total") for _, name, kind, _ in SCALARS if kind == "counter")
    assert not any(dict(labels).get("run_id") for (name, labels) in got if name != "nasa_run_info")


def test_healthz_gives_the_reasons():
    reasons: list[str] = []
    client = TestClient(make_app(lambda: STATUS, lambda: reasons))
    assert client.get("/healthz").status_code == 200
    reasons += ["stopping (SIGTERM)", "replay silent for 12 s"]
    r = client.get("/healthz")
    assert r.status_code == 503 and "stopping (SIGTERM)" in r.text and "replay silent" in r.text


def test_history_is_bounded_and_spans_the_run():
    h = History(capacity=8)
    for i in range(50):
        h.add(STATUS | {"env_steps": i})
    steps = [p["env_steps"] for p in h.points()]
    assert len(steps) < 8 and steps[0] == 0 and steps == sorted(steps) and steps[-1] >= 40
    assert h.every_s > 2.0


def test_dashboard_page_and_a_stopped_runs_folder(tmp_path):
    (tmp_path / "learner").mkdir()
    (tmp_path / "learner" / "status.json").write_text(json.dumps(STATUS))
    History().save(tmp_path)
    (tmp_path / "eval.csv").write_text("step,mean,std,return_0\n0,10.5,0,10.5\n300,123.5,4.25,123.5\n")
    client = TestClient(folder_app(tmp_path))
    page = client.get("/")
    assert page.status_code == 200 and "/static/uplot.iife.min.js" in page.text and "http" not in \
        page.text.replace("http-equiv", "")
    assert client.get("/static/uplot.iife.min.js").status_code == 200
    assert client.get("/static/LICENSE-uPlot").text.startswith("The MIT License")
    assert client.get("/static/..%2Fstatus_api.py").status_code == 404
    assert client.get("/status").json() == STATUS
    history = client.get("/history").json()
    assert history["evals"] == [{"step": 0, "mean": 10.5, "std": 0.0},
                                {"step": 300, "mean": 123.5, "std": 4.25}]
    assert client.get("/healthz").status_code == 503
    assert samples(client.get("/metrics").text)[("nasa_eval_return_mean", ())] == 123.5


def test_nasa_train_writes_tensorboard_scalars(tmp_path):
    config = tiny_config(steps=40, warmup_steps=15, eval_every=40, eval_episodes=1, batch_size=8)
    config.env.action_repeat = 25  # 40-step cartpole episodes
    Trainer.create(config, tmp_path / "run").run()
    acc = EventAccumulator(str(tmp_path / "run" / "tensorboard" / "train"))
    acc.Reload()
    tags = set(acc.Tags()["scalars"])
    want = {"eval/return_mean", "eval/return_std", "train/episode_return", "train/episode_length",
            "train/steps_per_s", "train/critic_loss", "train/actor_loss", "train/ae_loss",
            "train/novelty_mean"}
    assert want <= tags, want - tags
    assert [e.step for e in acc.Scalars("eval/return_mean")] == [0, 40]
    assert [e.step for e in acc.Scalars("train/episode_return")] == [40]


def _agent():
    run = tiny_run()
    spec = run.spec
    return make_agent("nasa_td3", spec.obs_shape, spec.action_dim, run.config.agent, torch.device("cpu"))


def test_evaluation_video_decodes_to_its_frame_count_and_the_autoencoder_view(tmp_path):
    source = _agent()
    tap = AutoencoderTap(_agent())
    tap.load_policy_state_dict(source.policy_state_dict())
    assert tap.autoencoder is None  # policy weights alone: no autoencoder to show
    with pytest.raises(ValueError, match="has none"):  # a decoder for an agent without one
        AutoencoderTap(make_agent("pixel_td3", (9, 32, 32), 1, tiny_run().config.agent,
                                  torch.device("cpu"))).load_policy_state_dict({"decoder.w": torch.zeros(1)})
    decoder = {f"decoder.{k}": v for k, v in source.decoder.state_dict().items()}
    tap.load_policy_state_dict(source.policy_state_dict() | decoder)
    assert tap.autoencoder == (tap.agent.encoder, tap.agent.decoder, "nasa_td3")  # the policy's encoder
    for name in ("encoder", "decoder", "actor"):
        for a, b in zip(getattr(tap.agent, name).parameters(), getattr(source, name).parameters(),
                        strict=True):
            assert torch.equal(a, b)
    tap.load_policy_state_dict(_agent().policy_state_dict())  # a new encoder, no decoder with it
    assert tap.autoencoder is None  # never an encoder shown with another message's decoder
    tap.load_policy_state_dict(source.policy_state_dict() | decoder)
    obs = np.random.default_rng(0).integers(0, 256, (23, 9, 32, 32), dtype=np.uint8)
    media = EvalMedia(tmp_path, frames=5)
    image = media.autoencoder_view(tap.autoencoder, obs, step=100, policy_version=7)
    assert image.ndim == 3 and image.shape[1] == 5 * 64 + 4 * 2
    path = media.video(tap.autoencoder, obs, [None] * len(obs), step=100, episode_return=3.0)
    media.close()
    assert count_frames(path) == len(obs)
    manifest = json.loads((tmp_path / "media" / "media.json").read_text())
    assert manifest["videos"] == [{"step": 100, "file": path.name, "frames": 23, "return": 3.0}]
    view = manifest["autoencoder"]
    assert len(view["novelty"]) == 5 and view["step"] == 100
    assert view["policy_version"] == view["autoencoder_version"] == 7
    acc = EventAccumulator(str(tmp_path / "tensorboard" / "evaluator"))
    acc.Reload()
    assert "autoencoder/view" in acc.Tags()["images"]


def test_structured_logs(monkeypatch, capsys):
    monkeypatch.setenv("NASA_RUN_ID", "run7")
    Log("actor 3")("hello")
    plain = capsys.readouterr().err.strip()
    assert plain.endswith("[actor 3] run=run7 hello") and plain[:4].isdigit()
    monkeypatch.setenv("NASA_LOG_JSON", "1")
    Log("actor 3")("hello")
    line = json.loads(capsys.readouterr().err)
    assert line["service"] == "actor" and line["actor_id"] == 3 and line["run_id"] == "run7"
    assert line["msg"] == "hello" and line["time"].endswith("Z")


@pytest.mark.parametrize("content", [b"{bad", b"\xff\xfe", b"[1, 2]"])
def test_a_damaged_last_status_is_named_not_a_traceback(tmp_path, capsys, content):
    from nasa.up import status as print_status

    (tmp_path / "learner").mkdir()
    (tmp_path / "learner" / "status.json").write_bytes(content)
    with pytest.raises(StoppedRunError, match="status.json is unreadable"):
        folder_app(tmp_path)
    dead = "http://127.0.0.1:9/status"  # the discard port: nothing answers
    with pytest.raises(SystemExit) as done:
        print_status(["--url", dead, "--data", str(tmp_path)])
    err = capsys.readouterr().err
    assert done.value.code == 1 and "status.json is unreadable" in err and "Traceback" not in err


def test_a_stopped_runs_status_is_printed_as_json(tmp_path, capsys):
    from nasa.up import status as print_status

    (tmp_path / "learner").mkdir()
    (tmp_path / "learner" / "status.json").write_text(json.dumps(STATUS))
    print_status(["--url", "http://127.0.0.1:9/status", "--data", str(tmp_path)])
    out, err = capsys.readouterr()
    assert json.loads(out) == STATUS and "the learner is not running at http://127.0.0.1:9/status" in err


def test_a_damaged_history_leaves_the_stopped_dashboard_up_without_its_series(tmp_path, capsys):
    (tmp_path / "learner").mkdir()
    (tmp_path / "learner" / "status.json").write_text(json.dumps(STATUS))
    (tmp_path / "learner" / "history.json").write_text('{"points": 3}')
    client = TestClient(folder_app(tmp_path))
    assert client.get("/status").json() == STATUS
    assert client.get("/history").json()["points"] == []
    assert "history.json is unreadable" in capsys.readouterr().err


@pytest.mark.parametrize("damage", [b"0,\xff,0\n", b'"' + b"x" * 200_000 + b"\n"])  # past csv's field limit
def test_a_damaged_eval_csv_leaves_the_history_without_evaluations(tmp_path, damage):
    (tmp_path / "learner").mkdir()
    (tmp_path / "learner" / "status.json").write_text(json.dumps(STATUS))
    (tmp_path / "eval.csv").write_bytes(b"step,mean,std\n" + damage)
    client = TestClient(folder_app(tmp_path))
    response = client.get("/history")
    assert response.status_code == 200 and response.json()["evals"] == []


def test_the_history_leaves_out_an_evaluation_row_being_written(tmp_path):
    (tmp_path / "learner").mkdir()
    (tmp_path / "learner" / "status.json").write_text(json.dumps(STATUS))
    # The row of 2000 cut short after its std's first digit: its std may be 5.25.
    (tmp_path / "eval.csv").write_bytes(b"step,updates,mean,std,min,max,return_0,return_1\n"
                                        b"1000,990,30,1,29,31,29,31\n2000,1990,305,5")
    response = TestClient(folder_app(tmp_path)).get("/history")
    assert response.json()["evals"] == [{"step": 1000, "mean": 30.0, "std": 1.0}]


@pytest.mark.parametrize("port", ["99999", "busy"])
def test_a_stopped_dashboard_on_a_port_it_cannot_have_is_one_line_and_exit_2(tmp_path, port):
    (tmp_path / "learner").mkdir()
    (tmp_path / "learner" / "status.json").write_text(json.dumps(STATUS))
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        if port == "busy":
            port = str(busy.getsockname()[1])
        done = subprocess.run([sys.executable, "-m", "nasa.cli", "status", "--data", str(tmp_path), "--serve",
                               "--port", port], capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1, done.stderr
    assert f"port {port} on 127.0.0.1 is in use" in done.stderr or "1-65535, got 99999" in done.stderr


def test_history_carries_on_the_series_an_earlier_learner_left(tmp_path):
    earlier = History(capacity=100)
    for wall in range(1, 11):
        earlier.add(STATUS | {"wall_s": float(wall)})
    earlier.every_s = 4.0
    earlier.save(tmp_path)
    resumed = History(capacity=100)
    resumed.restore(tmp_path, wall_s=5.0)  # the checkpoint's clock: later points run again
    resumed.add(STATUS | {"wall_s": 6.5})
    assert [p["wall_s"] for p in resumed.points()] == [1.0, 2.0, 3.0, 4.0, 5.0, 6.5]
    assert resumed.every_s == 4.0
    fresh = History()
    fresh.restore(tmp_path / "nothing-here", wall_s=5.0)
    assert fresh.points() == []
    (tmp_path / "learner" / "history.json").write_text('{"points": 3}')
    with pytest.raises(HistoryError, match="history.json is unreadable"):
        History().restore(tmp_path, wall_s=5.0)


def test_rates_fall_while_the_loop_takes_no_samples(monkeypatch):
    from types import SimpleNamespace

    from services.learner import status

    clock = [100.0]  # the board's own clock, so that a slow machine cannot change the rates
    monkeypatch.setattr(status, "time", SimpleNamespace(monotonic=lambda: clock[0]))
    board = StatusBoard()
    board.sample_rates(0)
    clock[0] += 0.6
    board.sample_rates(12)
    assert board.rates()[1] == pytest.approx(20.0)
    clock[0] += status.STALE_SAMPLE_S / 2  # between two samples: the rate holds
    assert board.rates()[1] == pytest.approx(20.0)
    clock[0] = 100.0 + 2.1  # the loop evaluates, or waits: no samples, no updates
    assert board.rates()[1] == pytest.approx(12 / 2.1)


@pytest.fixture
def live_status():
    """A status API on a free loopback port, answering STATUS."""
    from nasa.up import free_port
    from services.learner.status_api import StatusServer

    port = free_port()
    server = StatusServer(make_app(lambda: STATUS, lambda: []), "127.0.0.1", port)
    server.start()
    deadline = time.monotonic() + 20
    while True:
        try:
            if httpx.get(f"http://127.0.0.1:{port}/status", timeout=1).status_code == 200:
                break
        except httpx.HTTPError:
            pass
        assert time.monotonic() < deadline, "the status API never answered"
        time.sleep(0.05)
    yield f"http://127.0.0.1:{port}"
    server.stop()


def test_status_takes_the_apis_address_and_refuses_what_is_not_a_status(live_status, capsys):
    from nasa.up import status as print_status

    print_status(["--url", live_status])
    assert json.loads(capsys.readouterr().out) == STATUS
    with pytest.raises(SystemExit) as done:
        print_status(["--url", live_status + "/static/LICENSE-uPlot"])
    err = capsys.readouterr().err
    assert done.value.code == 1 and "not with JSON" in err and "Traceback" not in err


def test_status_of_a_folder_is_not_another_runs_live_status(live_status, tmp_path, capsys):
    from nasa.up import status as print_status

    (tmp_path / "learner").mkdir()
    (tmp_path / "learner" / "status.json").write_text(json.dumps(STATUS | {"run_id": "other"}))
    print_status(["--url", live_status, "--data", str(tmp_path)])
    out, err = capsys.readouterr()
    assert json.loads(out)["run_id"] == "other"
    assert "it serves run 'r1'" in err and "holds run 'other'" in err
    (tmp_path / "learner" / "status.json").write_text(json.dumps(STATUS))  # the same run: live
    print_status(["--url", live_status, "--data", str(tmp_path)])
    out, err = capsys.readouterr()
    assert json.loads(out) == STATUS and err == ""


def test_status_of_a_nasa_train_folder_says_what_it_is(tmp_path, capsys):
    from nasa.up import status as print_status

    (tmp_path / "eval.csv").write_text("step,mean,std,return_0\n0,10.5,0,10.5\n")
    with pytest.raises(SystemExit) as done:
        print_status(["--url", "http://127.0.0.1:9/status", "--data", str(tmp_path)])
    err = capsys.readouterr().err
    assert done.value.code == 1 and "a `nasa train` run" in err and "eval.csv" in err


def test_a_run_folder_with_no_status_yet_says_its_learner_has_written_no_checkpoint(tmp_path, capsys):
    from nasa.up import status as print_status

    (tmp_path / "learner").mkdir()  # a `nasa up` run whose learner died before its first checkpoint
    with pytest.raises(SystemExit) as done:
        print_status(["--url", "http://127.0.0.1:9/status", "--data", str(tmp_path)])
    err = capsys.readouterr().err
    assert done.value.code == 1 and "learner has written no checkpoint yet" in err
    assert "stopped cleanly" not in err  # it leaves one with each checkpoint, not only at a clean stop


def test_a_non_finite_figure_goes_out_as_null_not_as_json_no_browser_reads():
    status = STATUS | {"intrinsic": STATUS["intrinsic"] | {"novelty_mean": float("nan")},
                       "wall_s": float("inf")}
    client = TestClient(make_app(lambda: status, lambda: [], lambda: [{"novelty_mean": float("-inf")}]))
    text = client.get("/status").text
    assert "NaN" not in text and "Infinity" not in text
    body = json.loads(text)
    assert body["intrinsic"]["novelty_mean"] is None and body["wall_s"] is None
    assert body["intrinsic"]["surprise_mean"] == STATUS["intrinsic"]["surprise_mean"]
    assert json.loads(client.get("/history").text)["points"] == [{"novelty_mean": None}]


@pytest.mark.parametrize("first", [True, False])
def test_a_status_read_that_fails_does_not_end_the_series(first):
    failure = RuntimeError("dictionary changed size during iteration")
    reads = iter([failure] if first else [STATUS, failure])  # the first read at start, or a later one

    def status() -> dict:
        item = next(reads, STATUS)
        if isinstance(item, Exception):
            raise item
        return item

    history = History(every_s=0.02)
    history.start(status)
    deadline = time.monotonic() + 30
    while len(history.points()) < 4 and time.monotonic() < deadline:
        time.sleep(0.02)
    history.stop()
    assert len(history.points()) >= 4 and history.failed_reads == 1


def test_a_status_api_whose_port_is_taken_is_an_error_not_a_silent_thread():
    from services.learner.status_api import StatusServer
    from shared.faults import RunFolderError

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        with pytest.raises(RunFolderError, match=f"cannot listen on 127.0.0.1:{port}"):
            StatusServer(make_app(lambda: STATUS, lambda: []), "127.0.0.1", port).start()


@pytest.mark.parametrize("route", ["/static/", "/media/"])
def test_a_file_name_the_file_system_refuses_is_not_found_not_a_server_error(tmp_path, route):
    (tmp_path / "media").mkdir()
    client = TestClient(make_app(lambda: STATUS, lambda: [], data=tmp_path), raise_server_exceptions=False)
    response = client.get(route + "a" * 300)  # longer than a file name may be
    assert response.status_code == 404, response.text


@pytest.mark.parametrize("every_s", [1e6, 1e300])
def test_a_damaged_history_interval_does_not_stop_the_series(tmp_path, every_s):
    (tmp_path / "learner").mkdir()
    (tmp_path / "learner" / "history.json").write_text(json.dumps({"every_s": every_s, "points": []}))
    history = History(every_s=0.02)
    history.restore(tmp_path, wall_s=100.0)
    assert history.every_s == 0.02
    history.start(lambda: STATUS)
    deadline = time.monotonic() + 30
    while len(history.points()) < 3 and time.monotonic() < deadline:
        time.sleep(0.02)
    history.stop()
    assert len(history.points()) >= 3


@pytest.mark.parametrize("damage", [
    {"intrinsic": None}, {"actors": "none"}, {"updates": "many"}, {"updates": 10**400},
    {"losses": {"critic_loss": "x"}}, {"nonfinite": {"losses": {"critic_loss": 2}}},
    {"actors": [STATUS["actors"][0] | {"env_step_seconds": {"le": {"0.1": "x"}, "sum": 1}}, {"alive": 1}]},
])
def test_a_damaged_stopped_status_costs_its_own_figures_not_the_scrape(tmp_path, damage):
    (tmp_path / "learner").mkdir()
    (tmp_path / "learner" / "status.json").write_text(json.dumps(STATUS | damage))
    client = TestClient(folder_app(tmp_path), raise_server_exceptions=False)
    response = client.get("/metrics")
    assert response.status_code == 200, response.text
    got = samples(response.text)
    assert got[("nasa_run_env_steps", ())] == STATUS["env_steps"]


def test_idle_connections_cannot_take_the_status_apis_process(monkeypatch):
    from nasa.up import free_port
    from services.learner import status_api

    monkeypatch.setattr(status_api, "MAX_CONNECTIONS", 4, raising=False)
    monkeypatch.setattr(status_api, "REQUEST_HEAD_S", 0.5, raising=False)
    port = free_port()
    server = status_api.StatusServer(make_app(lambda: STATUS, lambda: []), "127.0.0.1", port)
    server.start()
    held = []
    try:
        for _ in range(3):  # connections that never send a request
            held.append(socket.create_connection(("127.0.0.1", port), timeout=30))
        half = socket.create_connection(("127.0.0.1", port), timeout=30)  # half of a request head
        half.sendall(b"GET /status HTTP/1.1\r\nHost: 127.0.0.1\r\n")
        held.append(half)
        with socket.create_connection(("127.0.0.1", port), timeout=30) as beyond:
            assert beyond.recv(1) == b""  # one more than the limit is closed on arrival
        for s in held:  # each closed once its request head is late
            assert s.recv(1) == b""
        assert httpx.get(f"http://127.0.0.1:{port}/status", timeout=30).json() == STATUS
    finally:
        for s in held:
            s.close()
        server.stop()


def test_a_stopped_runs_dashboard_has_the_same_connection_limits(tmp_path, monkeypatch):
    import uvicorn

    from nasa.up import free_port, serve_stopped
    from services.learner import status_api

    (tmp_path / "learner").mkdir()
    (tmp_path / "learner" / "status.json").write_text(json.dumps(STATUS))
    served: list[uvicorn.Config] = []
    monkeypatch.setattr(uvicorn.Server, "run", lambda self, *args, **kwargs: served.append(self.config))
    serve_stopped(tmp_path, "127.0.0.1", free_port())
    assert [config.http for config in served] == [status_api.GuardedH11Protocol]


def test_step_counts_the_wire_allows_make_a_valid_histogram():
    from shared import wire

    biggest = [2**62 - 1] * (len(wire.STEP_SECONDS_BUCKETS) + 1)  # each below the wire's bound
    heartbeat = wire.ActorStatus(3, 1, 40, 1, 7, 9.5, [], None, biggest, 1.0)
    board = StatusBoard()
    board.actor_status(wire.decode(wire.encode(heartbeat), wire.ActorStatus))
    h = board.snapshot()["actors"][0]["env_step_seconds"]
    cumulative = list(h["le"].values())
    assert cumulative == sorted(cumulative) and cumulative[0] > 0 and h["count"] == sum(biggest)


def test_heartbeats_of_ever_new_actor_ids_do_not_grow_the_board_without_bound(monkeypatch):
    from services.learner import status
    from shared import wire

    monkeypatch.setattr(status, "MAX_ACTORS", 4, raising=False)
    board = StatusBoard()

    def heartbeat(actor_id: int) -> None:
        board.actor_status(wire.ActorStatus(actor_id, 1, 40, 1, 7, 9.5, []))

    for actor_id in range(2):
        board.actor_alive(actor_id, 1, True)
    for actor_id in range(2, 50):  # heartbeats alone: no liveliness token
        heartbeat(actor_id)
    ids = [a["id"] for a in board.snapshot()["actors"]]
    assert ids == [0, 1, 48, 49]  # the live actors stay; the newest of the others take the rest
    for actor_id in range(2, 4):
        board.actor_alive(actor_id, 1, True)
    heartbeat(60)
    board.actor_alive(61, 1, True)
    assert [a["id"] for a in board.snapshot()["actors"]] == [0, 1, 2, 3]  # all alive: no room


def test_a_tensorboard_write_the_disk_refuses_is_raised_once_and_a_new_file_is_tried_later(
    tmp_path, monkeypatch
):
    from shared import scalars as scalars_module

    tb = scalars_module.Scalars(tmp_path / "tb")
    tb.add({"x": 1.0}, 1)
    tb.flush()  # on disk: the writer given up on is dropped unflushed, its file removed if pointless

    def refused(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(tb.writer, "add_scalar", refused)  # as its thread's error comes back
    with pytest.raises(OSError, match="No space"):
        tb.add({"x": 2.0}, 2)
    tb.add({"x": 3.0}, 3)  # dropped: the broken writer would raise the same error at every call
    monkeypatch.setattr(scalars_module, "RETRY_S", 0.0)  # the disk has room again
    tb.add({"x": 4.0}, 4)
    tb.close()
    acc = EventAccumulator(str(tmp_path / "tb"))
    acc.Reload()
    # Two event files: made within one second, their names need not sort in the order written.
    assert sorted(e.step for e in acc.Scalars("x")) == [1, 4]



def test_retries_on_a_disk_still_refusing_leave_no_event_file_each(tmp_path, monkeypatch):
    from types import SimpleNamespace

    from tensorboard.compat.tensorflow_stub.io import gfile

    from shared import scalars as scalars_module
    from tests.test_train import FullFile

    tb = scalars_module.Scalars(tmp_path / "tb")
    tb.add({"x": 1.0}, 1)
    tb.flush()
    first = sorted((tmp_path / "tb").iterdir())
    # The disk fills: every write of an event file fails (the file itself can still be made).
    real_io = gfile.io
    monkeypatch.setattr(gfile, "io", SimpleNamespace(open=lambda *a, **k: FullFile(open(*a, **k))))
    with pytest.raises(OSError, match="No space"):
        tb.add({"x": 2.0}, 2)
        tb.flush()
    monkeypatch.setattr(scalars_module, "RETRY_S", 0.0)  # a retry at every point, as over many minutes
    for step in range(3, 8):
        with pytest.raises(OSError, match="No space"):
            tb.add({"x": float(step)}, step)
    assert sorted((tmp_path / "tb").iterdir()) == first  # the one with a point stays; no empty ones
    monkeypatch.setattr(gfile, "io", real_io)  # the disk has room again
    tb.add({"x": 9.0}, 9)
    tb.close()
    assert len(list((tmp_path / "tb").iterdir())) == 2
    acc = EventAccumulator(str(tmp_path / "tb"))
    acc.Reload()
    assert sorted(e.step for e in acc.Scalars("x")) == [1, 9]


def test_a_resumed_runs_purge_marker_is_written_once_across_a_full_disk_spell(tmp_path, monkeypatch):
    """The marker hides every point from its step on: written again by the writer that follows a
    refused write, it would hide the points written between the resume and the full disk. A writer
    whose file kept no point took its marker with it: the next one writes it."""
    from types import SimpleNamespace

    from tensorboard.backend.event_processing.event_file_loader import EventFileLoader
    from tensorboard.compat.proto.event_pb2 import SessionLog
    from tensorboard.compat.tensorflow_stub.io import gfile

    from shared import scalars as scalars_module
    from tests.test_train import FullFile

    def markers() -> list[int]:
        return sorted(event.step for path in (tmp_path / "tb").iterdir()
                      for event in EventFileLoader(str(path)).Load()
                      if event.HasField("session_log") and event.session_log.status == SessionLog.START)

    real_io = gfile.io
    full = SimpleNamespace(open=lambda *a, **k: FullFile(open(*a, **k)))
    monkeypatch.setattr(scalars_module, "RETRY_S", 0.0)  # a retry at every point, as over many minutes
    tb = scalars_module.Scalars(tmp_path / "tb")
    tb.purge_step = 5  # resumed from a checkpoint at step 5
    monkeypatch.setattr(gfile, "io", full)  # full from the start: the first writer's file is dropped
    with pytest.raises(OSError, match="No space"):
        tb.add({"x": 5.0}, 5)
        tb.flush()
    monkeypatch.setattr(gfile, "io", real_io)
    tb.add({"x": 6.0}, 6)
    tb.flush()
    assert markers() == [5]  # the marker the dropped file lost
    monkeypatch.setattr(gfile, "io", full)  # the disk fills
    for step in (7, 8):
        with pytest.raises(OSError, match="No space"):
            tb.add({"x": float(step)}, step)
            tb.flush()
    monkeypatch.setattr(gfile, "io", real_io)  # room again
    tb.add({"x": 9.0}, 9)
    tb.close()
    assert markers() == [5]
    points = sorted(event.step for path in (tmp_path / "tb").iterdir()
                    for event in EventFileLoader(str(path)).Load() if event.HasField("summary"))
    assert points == [6, 9]


def _serve(app, monkeypatch, **limits):  # noqa: ANN001, ANN202 (a started StatusServer, its port)
    from nasa.up import free_port
    from services.learner import status_api

    for name, value in limits.items():
        monkeypatch.setattr(status_api, name, value, raising=False)
    port = free_port()
    server = status_api.StatusServer(app, "127.0.0.1", port)
    server.start()
    return server, port


def test_a_client_that_never_reads_its_response_is_dropped(monkeypatch):
    big = STATUS | {"padding": "x" * (32 << 20)}  # more than the kernel's buffers take
    server, port = _serve(make_app(lambda: big, lambda: []), monkeypatch, WRITE_STALL_S=0.5)
    connections = server.server.server_state.connections
    try:
        with socket.socket() as sleeper:
            sleeper.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
            sleeper.connect(("127.0.0.1", port))
            sleeper.sendall(b"GET /status HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")  # and never reads
            deadline = time.monotonic() + 60
            while not connections and time.monotonic() < deadline:
                time.sleep(0.02)
            assert connections, "the request never arrived"
            while connections and time.monotonic() < deadline:
                time.sleep(0.05)
            assert not connections, "the connection that reads nothing is still held"
        assert httpx.get(f"http://127.0.0.1:{port}/healthz", timeout=30).text == "ok\n"
    finally:
        server.stop()


def test_a_reader_with_a_small_window_is_served_whole(monkeypatch):
    big = STATUS | {"padding": "x" * (8 << 20)}
    server, port = _serve(make_app(lambda: big, lambda: []), monkeypatch, WRITE_STALL_S=2.0)
    try:
        with socket.socket() as reader:
            reader.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
            reader.connect(("127.0.0.1", port))
            reader.sendall(b"GET /status HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n")
            got = bytearray()
            while chunk := reader.recv(1 << 16):
                got += chunk
        head, _, body = bytes(got).partition(b"\r\n\r\n")
        assert head.startswith(b"HTTP/1.1 200") and json.loads(body)["padding"] == big["padding"]
    finally:
        server.stop()


def test_one_client_address_cannot_take_every_connection(monkeypatch):
    # A late request head closes a connection too: not within this test.
    server, port = _serve(make_app(lambda: STATUS, lambda: []), monkeypatch, MAX_PER_PEER=2,
                          REQUEST_HEAD_S=600.0)
    held = [socket.create_connection(("127.0.0.1", port), timeout=30) for _ in range(2)]
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=30) as beyond:
            assert beyond.recv(1) == b""  # a third from the same address: closed on arrival
        other = socket.create_connection(("127.0.0.1", port), timeout=30, source_address=("127.0.0.2", 0))
        with other:  # another address still gets in
            other.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n")
            assert other.recv(1 << 16).startswith(b"HTTP/1.1 200")
    finally:
        for s in held:
            s.close()
        server.stop()


def test_many_pollers_cost_one_render_and_the_next_interval_renders_anew(monkeypatch):
    from concurrent.futures import ThreadPoolExecutor

    calls = {"status": 0, "history": 0}

    def status() -> dict:
        calls["status"] += 1
        return STATUS | {"updates": calls["status"]}

    def history() -> list[dict]:
        calls["history"] += 1
        return [{"updates": calls["history"]}]

    server, port = _serve(make_app(status, lambda: [], history, render_every_s=600.0), monkeypatch)
    url = f"http://127.0.0.1:{port}"
    try:
        with ThreadPoolExecutor(8) as pool:  # eight pollers, five polls each, of both
            got = list(pool.map(lambda i: httpx.get(url + ("/status", "/history")[i % 2], timeout=30).json(),
                                range(80)))
        assert calls == {"status": 1, "history": 1}
        assert {g["updates"] for g in got if "updates" in g} == {1}
        assert {g["points"][0]["updates"] for g in got if "points" in g} == {1}
    finally:
        server.stop()
    client = TestClient(make_app(status, lambda: [], history, render_every_s=0.0))
    assert client.get("/status").json()["updates"] == 2  # a new interval: rendered again
    assert client.get("/status").json()["updates"] == 3


def test_counters_count_from_the_process_start_and_never_step_back():
    """A learner resumed from its checkpoint starts below the figures last scraped: its counters
    start at 0 (a reset Prometheus knows), the run's position goes in a gauge."""
    run = {"updates": 1000, "env_steps": 5000, "replay": {"limiter_samples": 900}}
    metrics = LearnerMetrics(lambda: run, start=run)

    def scrape() -> dict:
        return samples(metrics.render().decode())

    got = scrape()
    assert got[("nasa_updates_total", ())] == 0 and got[("nasa_run_updates", ())] == 1000
    assert got[("process_start_time_seconds", ())] > 0
    run.update(updates=1010, env_steps=5040)
    got = scrape()
    assert got[("nasa_updates_total", ())] == 10 and got[("nasa_env_steps_total", ())] == 40
    run["replay"]["limiter_samples"] = 600  # the limiter resynced lower: the counter holds
    assert scrape()[("nasa_replay_limiter_samples_total", ())] == 0
    run["replay"]["limiter_samples"] = 650
    got = scrape()
    assert got[("nasa_replay_limiter_samples_total", ())] == 50
    assert got[("nasa_run_replay_limiter_samples", ())] == 650
    run["updates"] = float("nan")  # no count for one scrape: the counter holds, and counts on after
    assert scrape()[("nasa_updates_total", ())] == 10
    run["updates"] = 1012
    assert scrape()[("nasa_updates_total", ())] == 12
    # The next learner resumes from a checkpoint at 1005 updates: its counter starts at 0, not 1005
    # below the 1010 last scraped.
    resumed = {"updates": 1005, "env_steps": 5040}
    after = samples(LearnerMetrics(lambda: resumed, start=resumed).render().decode())
    assert after[("nasa_updates_total", ())] == 0 and after[("nasa_run_updates", ())] == 1005


def test_healthz_answers_head_as_uptime_checkers_ask():
    reasons: list[str] = []
    client = TestClient(make_app(lambda: STATUS, lambda: reasons))
    assert client.head("/healthz").status_code == 200
    reasons.append("stopping (SIGTERM)")
    assert client.head("/healthz").status_code == 503
