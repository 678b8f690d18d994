"""bench.up_profile's arithmetic: the histograms it reads back and the shares it reports."""

import os
import subprocess
import sys

import pytest
from prometheus_client import CollectorRegistry, Histogram, generate_latest

from bench.processes import Drain
from bench.up_profile import histogram_sums, measure, service_pids, wait_learning
from nasa.up import free_port

# A launcher that says what a reader waits for, then far more than a pipe holds, then why it ends.
LOUD = """
import sys
print("nasa up: preset cpu-small", flush=True)
print("nasa up: 1 actor", flush=True)
for i in range(20000):
    print(f"nasa up: actor-0 was killed by SIGKILL: restarting it ({i})")
print("nasa up: learner refused its input: bad checkpoint; not restarted")
sys.exit(2)
"""


def loud() -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", LOUD], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, errors="replace")


def test_histogram_sums_read_prometheus_text():
    registry = CollectorRegistry()
    h = Histogram("nasa_update_duration_seconds", "x", registry=registry)
    for v in (0.1, 0.2, 0.3):
        h.observe(v)
    sums = histogram_sums(generate_latest(registry).decode())
    assert sums["nasa_update_duration_seconds"][0] == 0.1 + 0.2 + 0.3
    assert sums["nasa_update_duration_seconds"][1] == 3


def test_measure_splits_the_window():
    a = {"t": 0.0, "cpu": {"learner": 10.0, "actor": 1.0}, "env_steps": 100, "updates": 100, "g": 1,
         "hist": {"nasa_update_duration_seconds": (5.0, 50), "nasa_batch_wait_seconds": (1.0, 50),
                  "nasa_scoring_duration_seconds": (1.0, 50)}}
    b = {"t": 10.0, "cpu": {"learner": 25.0, "actor": 3.0}, "env_steps": 150, "updates": 160, "g": 1,
         "hist": {"nasa_update_duration_seconds": (12.0, 110), "nasa_batch_wait_seconds": (2.0, 110),
                  "nasa_scoring_duration_seconds": (3.0, 110)}}
    r = measure(a, b, {"per_sampled_batch_s": 0.01, "per_frame_s": 0.001, "batch_bytes": 9}, cores=2)
    assert r["cpu_s"] == {"learner": 15.0, "actor": 2.0}
    assert r["cpu_share_of_cores"] == {"learner": 0.75, "actor": 0.1}
    assert r["unused_share_of_cores"] == 0.15
    assert r["learner_wall_share"] == {"updating": 0.7, "waiting_for_batch": 0.1, "other": 0.2,
                                       "scoring_in_updating": 0.2}
    assert (r["env_steps_per_s"], r["updates_per_s"], r["updates_per_env_step"]) == (5.0, 6.0, 1.2)
    assert r["wire"]["cpu_s_in_window"] == 0.65  # 60 batches and 50 frames


def test_a_services_own_children_are_not_counted_as_services():
    launcher = 2**22 + 12345  # no such process: only the variable ties these to it
    env = {**os.environ, "NASA_PARENT_PID": str(launcher)}
    sleep = "import time; time.sleep(30)"
    # As /proc shows them: a service (`-m services.<role>`) and a child it spawned (ffmpeg, say).
    service = subprocess.Popen([sys.executable, "-c", sleep, "-m", "services.replay"], env=env)
    child = subprocess.Popen([sys.executable, "-c", sleep], env=env)
    try:
        assert service_pids(launcher) == {"replay": service.pid}
    finally:
        for p in (service, child):
            p.kill()
            p.wait()


def test_drain_reads_a_childs_output_to_its_end_and_keeps_its_last_lines():
    proc = loud()
    try:
        head = [proc.stdout.readline()]
        output = Drain(proc.stdout, head, keep=3)
        # Unread, the child would wait for good on its full pipe, long after the lines looked for.
        assert proc.wait(timeout=120) == 2
    finally:
        proc.kill()
        proc.wait()
    assert output.lines() == ["nasa up: actor-0 was killed by SIGKILL: restarting it (19998)\n",
                              "nasa up: actor-0 was killed by SIGKILL: restarting it (19999)\n",
                              "nasa up: learner refused its input: bad checkpoint; not restarted\n"]
    assert Drain(iter(["one\n", "two\n"]), ["zero\n"]).lines() == ["zero\n", "one\n", "two\n"]


def test_up_profile_says_why_a_launcher_that_printed_much_ended(capsys):
    # bench.up_profile reads nasa up's first two lines, then waits for the learner's first update:
    # a launcher printing on meanwhile must still end, and its last line be the reason given.
    proc = loud()
    try:
        head = [proc.stdout.readline() for _ in range(2)]
        with pytest.raises(SystemExit) as ended:
            wait_learning(f"http://127.0.0.1:{free_port()}", proc, 120, Drain(proc.stdout, head))
    finally:
        proc.kill()
        proc.wait()
    assert ended.value.code == 2  # its input refused: so is the benchmark's
    assert capsys.readouterr().err.strip() == ("bench.up_profile: nasa up ended (exit 2) before its first "
                                               "update: nasa up: learner refused its input: bad checkpoint; "
                                               "not restarted")
