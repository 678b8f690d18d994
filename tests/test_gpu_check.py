"""The GPU check's CPU-testable parts: the no-GPU exit, the setup's requirement check, the
pytest and status summaries, the time budget, bounded children, the JSON line."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import pytest

from bench import gpu

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "gpu-check.sh"


def run_script(path_dirs: list[Path]) -> subprocess.CompletedProcess:
    env = {**os.environ, "PATH": os.pathsep.join([*map(str, path_dirs), "/usr/bin", "/bin"])}
    return subprocess.run(["bash", str(SCRIPT)], env=env, capture_output=True, text=True, timeout=60)


def assert_says_it_needs_a_gpu(result: subprocess.CompletedProcess) -> None:
    assert result.returncode == 0
    lines = result.stdout.splitlines()
    assert len(lines) == 1 and "needs a machine with an NVIDIA GPU" in lines[0]
    assert "nothing was run" in lines[0] and result.stderr == ""
    assert not (ROOT / ".venv-gpu").exists()


@pytest.mark.skipif(
    any((Path(d) / "nvidia-smi").exists() for d in ("/usr/bin", "/bin")), reason="this machine has nvidia-smi"
)
def test_without_nvidia_smi_the_script_says_one_line_and_runs_nothing(tmp_path):
    assert_says_it_needs_a_gpu(run_script([tmp_path]))


def test_with_an_nvidia_smi_that_finds_no_gpu_the_script_runs_nothing(tmp_path):
    fake = tmp_path / "nvidia-smi"
    fake.write_text("#!/bin/sh\necho 'NVIDIA-SMI has failed' >&2\nexit 9\n")
    fake.chmod(0o755)
    assert_says_it_needs_a_gpu(run_script([tmp_path]))


def test_an_nvidia_smi_that_hangs_ends_the_script_in_its_time_with_one_line(tmp_path):
    # A stuck driver leaves nvidia-smi waiting for ever: the script must still end, and say why.
    fake = tmp_path / "nvidia-smi"
    fake.write_text("#!/bin/sh\nexec sleep 600\n")
    fake.chmod(0o755)
    env = {**os.environ, "PATH": f"{tmp_path}:/usr/bin:/bin", "SMI_TIMEOUT_S": "1"}
    result = subprocess.run(["bash", str(SCRIPT)], env=env, capture_output=True, text=True, timeout=60)
    assert result.returncode == 1 and result.stdout == ""
    assert result.stderr.splitlines() == [
        "gpu-check: nvidia-smi did not answer within 1 s (a stuck GPU driver?); nothing was run"]


def test_missing_requirements_names_the_pins_whose_module_does_not_import(tmp_path):
    pyproject = tmp_path / "pyproject.toml"
    pyproject.write_text(
        '[project]\nname = "x"\ndependencies = ["numpy>=1.26,<3", "surely-absent-pkg-x==1.0"]\n'
        '[project.optional-dependencies]\ndev = ["scikit-image==0.26.0", "absent-dev-tool==2.0"]\n'
    )
    assert gpu.missing_requirements(pyproject) == ["surely-absent-pkg-x==1.0", "absent-dev-tool==2.0"]
    assert gpu.missing_requirements(pyproject, extras=()) == ["surely-absent-pkg-x==1.0"]


def test_missing_requirements_leaves_out_what_the_check_never_imports(tmp_path):
    pyproject = tmp_path / "pyproject.toml"
    pyproject.write_text(
        '[project]\nname = "x"\ndependencies = ["surely-absent-pkg-x==1.0", "Absent-Camera-Lib==3"]\n'
    )
    unused = frozenset({"absent-camera-lib"})
    assert gpu.missing_requirements(pyproject, unused=unused) == ["surely-absent-pkg-x==1.0"]


def test_what_the_check_leaves_out_are_requirements_of_the_project_and_not_torch():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    names = {gpu.requirement_name(r).lower() for r in project["dependencies"]}
    names |= {gpu.requirement_name(r).lower() for r in project["optional-dependencies"]["dev"]}
    assert gpu.NOT_USED_BY_THE_CHECK <= names
    needed = {"torch", "mujoco", "dm-control", "eclipse-zenoh", "fastapi", "pytest"}
    assert not needed & gpu.NOT_USED_BY_THE_CHECK


def test_with_a_gpu_the_script_runs_the_check_with_the_python_it_is_given(tmp_path):
    """NASA_PYTHON (a Python with CUDA and every requirement) is used as it is: no setup."""
    smi = tmp_path / "nvidia-smi"
    smi.write_text("#!/bin/sh\necho 'GPU 0: Test GPU (UUID: GPU-0)'\n")
    python = tmp_path / "python"
    python.write_text(  # answers the script's probes; the check itself prints its JSON line
        "#!/bin/sh\n"
        'if [ "$1" = "-c" ]; then case "$2" in *version*) echo 9.9;; esac; exit 0; fi\n'
        'if [ "$3" = "missing" ]; then exit 0; fi\n'
        'echo "{\\"check\\": \\"gpu\\", \\"args\\": \\"$*\\"}"\n'
    )
    for f in (smi, python):
        f.chmod(0o755)
    env = {**os.environ, "PATH": f"{tmp_path}:/usr/bin:/bin", "NASA_PYTHON": str(python)}
    result = subprocess.run(["bash", str(SCRIPT)], env=env, capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    assert "setup" not in result.stdout and f"gpu-check: {python}, torch 9.9" in result.stdout
    last = json.loads(result.stdout.splitlines()[-1])
    assert last["check"] == "gpu" and "-m bench.gpu --budget-s" in last["args"]


def test_the_missing_command_prints_nothing_when_every_requirement_imports():
    result = subprocess.run(
        [sys.executable, "-m", "bench.gpu", "missing"], cwd=ROOT, capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 0 and result.stdout.strip() == ""


def test_requirement_names():
    assert gpu.requirement_name("eclipse-zenoh==1.10.2") == "eclipse-zenoh"
    assert gpu.requirement_name("numpy>=1.26,<3") == "numpy"
    assert gpu.requirement_name("uvicorn[standard]~=0.5") == "uvicorn"


def test_pytest_counts_from_the_summary_line():
    assert gpu.pytest_counts("....\n7 passed, 2 skipped, 1 deselected in 3.2s") == {
        "passed": 7, "skipped": 2, "deselected": 1,
    }  # fmt: skip
    assert gpu.pytest_counts("1 failed, 3 passed, 2 errors in 1s") == {"failed": 1, "passed": 3, "error": 2}


def test_the_budget_cuts_each_step_to_the_time_left():
    now = [100.0]
    budget = gpu.Budget(500, clock=lambda: now[0])
    assert budget.step_timeout(150, reserve=300) == 150
    now[0] += 300  # 200 s left
    assert budget.step_timeout(150, reserve=100) == 100
    now[0] += 250
    assert budget.step_timeout(150, reserve=0) == 0


def running(pid: int) -> bool:
    """The process exists and is not a zombie (killed, waiting for its parent to reap it)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return False
    return state != "Z"


def test_each_step_keeps_back_only_what_the_steps_after_it_need():
    assert [gpu.reserve_after(step, set()) for step in gpu.STEPS] == [330.0, 270.0, 220.0, 0.0]
    # A skipped step keeps nothing back: the profile alone may use the whole budget.
    assert gpu.reserve_after("profile", {"tests", "learner", "up"}) == 0.0
    assert gpu.reserve_after("tests", {"up"}) == 110.0


def test_an_unknown_step_to_skip_is_refused_with_exit_2(capsys):
    with pytest.raises(SystemExit) as exit_info:
        gpu.parse_args(["--skip", "tests,bogus"])
    assert exit_info.value.code == 2 and "bogus" in capsys.readouterr().err
    assert gpu.parse_args(["--skip", "tests,up"]).skip == "tests,up"


def test_a_child_past_its_timeout_is_killed_with_its_whole_group(tmp_path):
    marker = tmp_path / "grandchild.pid"
    result = gpu.run_child(["sh", "-c", f"sleep 60 & echo $! > {marker}; wait"], timeout=1.0)
    assert result["rc"] is None and "timed out" in result["error"]
    pid = int(marker.read_text())
    for _ in range(100):  # SIGKILL is asynchronous: allow it a moment to land
        if not running(pid):
            break
        time.sleep(0.05)
    assert not running(pid)
    assert gpu.run_child(["true"], timeout=0)["error"] == "skipped: out of time"
    assert gpu.run_child(["sh", "-c", "echo hi"], timeout=30) | {"seconds": 0} == {
        "rc": 0, "seconds": 0, "output": "hi\n",
    }  # fmt: skip


def test_a_child_that_ignores_sigint_is_killed_after_the_grace():
    proc = subprocess.Popen(
        [sys.executable, "-c", "import signal, time; signal.signal(signal.SIGINT, signal.SIG_IGN); "
         "print('up', flush=True); time.sleep(60)"],
        stdout=subprocess.PIPE, text=True, start_new_session=True,
    )  # fmt: skip
    assert proc.stdout.readline().strip() == "up"
    assert gpu.stop_group(proc, grace_s=0.5) == -signal.SIGKILL


def test_last_json_finds_the_final_object():
    assert gpu.last_json('log line\n{"a": 1}\n{"b": 2}\n') == {"b": 2}
    assert gpu.last_json("no json here") is None


def test_up_summary_from_status_and_gpu_samples():
    samples = [
        {"env_steps": 500, "updates": 0, "updates_per_s": 0.0, "env_steps_per_s": 90.0,
         "updates_per_env_step": 0},
        {"env_steps": 2000, "updates": 100, "updates_per_s": 40.0, "env_steps_per_s": 80.0,
         "updates_per_env_step": 0.1, "replay": {"size": 2000}},
        {"env_steps": 3000, "updates": 900, "updates_per_s": 60.0, "env_steps_per_s": 70.0,
         "updates_per_env_step": 0.45, "replay": {"size": 3000}},
    ]  # fmt: skip
    gpu_samples = [{"memory_used_mib": 900.0, "utilization_pct": 20.0},
                   {"memory_used_mib": 2500.0, "utilization_pct": 60.0}]  # fmt: skip
    s = gpu.summarize_up(samples, gpu_samples)
    assert s["updates_per_s"] == 60.0 and s["env_steps_per_s"] == 70.0 and s["updates_per_env_step"] == 0.45
    assert s["max_updates_per_s"] == 60.0 and s["median_updates_per_s"] == 50.0
    assert s["max_env_steps_per_s"] == 80.0  # samples before the first update are left out
    assert s["gpu_memory_max_mib"] == 2500.0 and s["gpu_utilization_mean_pct"] == 40.0
    assert s["replay_size"] == 3000 and s["status_samples"] == 3
    assert gpu.summarize_up([], []) == {"status_samples": 0}


def test_the_json_line_is_ok_only_when_no_step_failed():
    good = gpu.assemble("NVIDIA H200", {"tests": {"passed": 9}, "up": {"updates_per_s": 50.0}}, 412.34)
    assert good["ok"] and good["gpu"] == "NVIDIA H200" and good["seconds"] == 412.3
    assert json.loads(json.dumps(good)) == good
    bad = gpu.assemble("NVIDIA H200", {"tests": {"passed": 9}, "up": {"error": "no /status answered"}}, 1.0)
    assert not bad["ok"]


@pytest.mark.skipif(__import__("torch").cuda.is_available(), reason="this machine has CUDA")
def test_the_check_without_cuda_fails_with_one_json_line():
    result = subprocess.run(
        [sys.executable, "-m", "bench.gpu"], cwd=ROOT, capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 1
    line = json.loads(result.stdout.strip().splitlines()[-1])
    assert line["ok"] is False and line["cuda"]["error"] == "torch sees no CUDA device"


def test_the_up_steps_window_opens_once_the_learner_updates_with_time_left_and_closes_after_it(
        monkeypatch, tmp_path):
    from bench import up_profile

    clock = [100.0]
    snaps = []

    def snapshot(url, pids):  # noqa: ANN001, ANN202
        snaps.append(clock[0])
        return {"t": clock[0], "cpu": {n: clock[0] for n in pids}, "hist": {}, "env_steps": 10 * len(snaps),
                "updates": 50 * len(snaps), "g": 5}

    monkeypatch.setattr(gpu.time, "monotonic", lambda: clock[0])
    monkeypatch.setattr(up_profile, "snapshot", snapshot)
    monkeypatch.setattr(up_profile, "service_pids", lambda launcher: {"learner": 7, "replay": 8})
    monkeypatch.setattr(up_profile, "gil_recording",
                        lambda pid, s, f: up_profile.GilProfileError(f"pid {pid}"))
    short = gpu.UpWindow(1, 9, tmp_path, seconds=45)
    short.tick(left_s=50)  # not enough time left for the window
    assert short.result()["error"].startswith("skipped")
    window = gpu.UpWindow(1, 9, tmp_path, seconds=45)
    window.tick(left_s=100)
    clock[0] += 20
    window.tick(left_s=80)  # still inside the window
    assert snaps == [100.0]
    clock[0] += 30
    window.tick(left_s=50)
    assert snaps == [100.0, 150.0]
    out = window.result()
    assert out["updates_per_s"] == 1.0 and out["cpu_s"] == {"launcher+router": 50.0, "learner": 50.0,
                                                              "replay": 50.0}
    assert out["learner_gil"] == {"error": "pid 7"} and "wire" not in out


def test_a_check_stopped_by_sigterm_kills_the_step_it_runs(tmp_path):
    # The step's child runs in a session of its own: no signal to the check reaches it but through it.
    marker = tmp_path / "grandchild.pid"
    script = (
        "import sys\nfrom bench import gpu, processes\n"
        "with processes.stopped_cleanly('python -m bench.gpu'):\n"
        f"    gpu.run_child(['sh', '-c', 'sleep 60 & echo $! > {marker}; wait'], timeout=120)\n"
    )
    check = subprocess.Popen([sys.executable, "-c", script], cwd=ROOT, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60
    while not (marker.exists() and marker.read_text().strip()):
        assert time.monotonic() < deadline and check.poll() is None, "the step never started"
        time.sleep(0.1)
    pid = int(marker.read_text())
    check.send_signal(signal.SIGTERM)
    _, err = check.communicate(timeout=60)
    for _ in range(100):
        if not running(pid):
            break
        time.sleep(0.05)
    left = running(pid)
    if left:
        os.kill(pid, signal.SIGKILL)
    assert not left, "the step's child was left running"
    assert check.returncode == 143 and "stopped (SIGTERM)" in err and "Traceback" not in err


def test_a_step_that_raises_is_an_error_in_the_json_line(monkeypatch, capsys):
    import torch

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "get_device_name", lambda _i=0: "a GPU")

    def broken(budget, reserve):  # noqa: ANN001, ANN202
        raise RuntimeError("nvidia-smi vanished")

    monkeypatch.setattr(gpu, "step_tests", broken)
    with pytest.raises(SystemExit) as exit_:
        gpu.main(["--skip", "learner,profile,up"])
    assert exit_.value.code == 1
    line = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert line["ok"] is False and line["tests"] == {"error": "RuntimeError: nvidia-smi vanished"}


def test_the_json_line_comes_when_the_gpu_cannot_be_named_after_the_steps(monkeypatch, capsys):
    # A step that takes the GPU down (an Xid) leaves the driver refusing the check's own last call
    # into CUDA; the line must still come, with the steps' results.
    import torch

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)

    def lost(_i=0):  # noqa: ANN001, ANN202
        raise RuntimeError("CUDA error: unspecified launch failure")

    monkeypatch.setattr(torch.cuda, "get_device_name", lost)
    monkeypatch.setattr(gpu, "step_tests", lambda budget, reserve: {"rc": 0, "passed": 3})
    with pytest.raises(SystemExit) as exit_:
        gpu.main(["--skip", "learner,profile,up"])
    assert exit_.value.code == 1
    line = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert line["tests"] == {"rc": 0, "passed": 3} and line["ok"] is False
    assert line["gpu"] is None and "unspecified launch failure" in line["gpu_error"]
