"""nasa up's layout: chosen from the cores and the GPU, every choice overridable by a flag."""

from pathlib import Path

import pytest

from nasa.layout import LOW_PRIORITY, choose
from nasa.up import layout_of, omp_env, parse_up, service_argv
from shared.config import ConfigError
from shared.service import FlagError


def test_a_small_cpu_machine_gives_the_learner_every_core_and_one_actor():
    lay = choose(2, gpu=False)
    assert (lay.actors, lay.learner_threads, lay.evaluator, lay.evaluator_nice) == (1, 2, True, LOW_PRIORITY)
    assert lay.omp_passive  # the learner's threads share the cores with the other services
    assert not choose(16, gpu=False).omp_passive


def test_a_large_cpu_machine_keeps_cores_for_the_learner_and_a_normal_priority_evaluator():
    lay = choose(16, gpu=False)
    assert lay.actors == 2 and lay.learner_threads == 13 and lay.evaluator_nice == 0


def test_with_a_gpu_the_spare_cores_go_to_actors():
    assert choose(16, gpu=True).actors == 8
    assert choose(6, gpu=True).actors == 3
    assert choose(2, gpu=True).actors == 1


def test_flags_override_each_choice():
    cmd, _ = parse_up(["--actors", "3", "--learner-threads", "1", "--evaluator-nice", "0"])
    lay = layout_of(cmd, gpu=False, cores=2)
    assert (lay.actors, lay.learner_threads, lay.evaluator, lay.evaluator_nice) == (3, 1, True, 0)
    off, _ = parse_up(["--no-evaluator"])
    assert not layout_of(off, gpu=False, cores=2).evaluator
    default, _ = parse_up([])
    assert layout_of(default, gpu=False, cores=2) == choose(2, gpu=False)


def test_the_layout_says_what_it_chose_and_how_to_change_it():
    text = choose(2, gpu=False).describe()
    assert "1 actor(s)" in text and "learner 2 torch thread(s)" in text and f"nice {LOW_PRIORITY}" in text
    assert "--actors" in text and "--learner-threads" in text
    assert "weights published every update" in text and "--publish-every" in text
    assert "weights published the learner's default" in choose(8, gpu=True).describe()
    assert "every 5 updates" in choose(2, gpu=False, publish_every=5).describe()
    assert "actors' lead 1 env step(s)" in text and "--actor-lead" in text
    assert "actors' lead the replay's default" in choose(8, gpu=True).describe()


def test_one_cpu_actor_may_run_one_step_ahead_of_the_learner_and_several_keep_the_defaults():
    assert choose(2, gpu=False).actor_lead == 1
    assert choose(2, gpu=False, actors=2).actor_lead == 0  # several actors would wait on each other
    assert choose(16, gpu=True).actor_lead == 0
    assert choose(16, gpu=True, actor_lead=3).actor_lead == 3
    # The lead in the replay's flags (the limiter's slack, in samples: G per step) and the actors'.
    assert choose(2, gpu=False).lead_argv(2) == {
        "replay": ["--error-buffer", "2"], "actor": ["--send-batch", "1", "--max-in-flight", "1"]}
    assert choose(2, gpu=False, actor_lead=40).lead_argv(1) == {
        "replay": ["--error-buffer", "40"], "actor": ["--send-batch", "8", "--max-in-flight", "5"]}
    assert choose(2, gpu=False, actors=2).lead_argv(1) == {"replay": [], "actor": []}


def test_a_negative_count_is_refused_with_a_clear_error():
    for flag in ("--actors", "--learner-threads"):
        with pytest.raises(ConfigError, match="must be >= 0"):
            parse_up([flag, "-1"])


def test_the_learners_openmp_wait_is_a_choice_of_its_own(monkeypatch):
    monkeypatch.delenv("OMP_WAIT_POLICY", raising=False)
    # Cores shared: the learner's threads spin, the others' sleep.
    small = choose(2, gpu=False)
    assert small.omp_env("learner") == {"OMP_WAIT_POLICY": "ACTIVE"}
    assert small.omp_env("actor") == small.omp_env("evaluator") == {"OMP_WAIT_POLICY": "PASSIVE"}
    sleep = choose(2, gpu=False, learner_omp_wait="passive")
    assert sleep.omp_env("learner") == sleep.omp_env("replay") == {"OMP_WAIT_POLICY": "PASSIVE"}
    # `default`: the runtime's own policy, so the variable the others get is unset for the learner.
    assert choose(2, gpu=False, learner_omp_wait="default").omp_env("learner") == {"OMP_WAIT_POLICY": None}
    # Cores to spare: the others' environment as it is, the learner's threads wait the runtime's way.
    assert choose(16, gpu=False).omp_env("actor") == {}
    assert choose(16, gpu=False).omp_env("learner") == {"OMP_WAIT_POLICY": None}
    cmd, _ = parse_up(["--learner-omp-wait", "passive"])
    assert layout_of(cmd, gpu=False, cores=2).learner_omp_wait == "passive"
    assert "OpenMP waits passive" in layout_of(cmd, gpu=False, cores=2).describe()


def test_an_openmp_wait_policy_the_user_set_wins_except_over_the_learners_flag(monkeypatch):
    monkeypatch.setenv("OMP_WAIT_POLICY", "ACTIVE")
    auto, _ = parse_up([])
    lay = layout_of(auto, gpu=False, cores=2)
    assert omp_env(auto, lay, "learner") == omp_env(auto, lay, "actor") == {}
    flag, _ = parse_up(["--learner-omp-wait", "passive"])
    lay = layout_of(flag, gpu=False, cores=2)
    assert omp_env(flag, lay, "learner") == {"OMP_WAIT_POLICY": "PASSIVE"}
    assert omp_env(flag, lay, "replay") == {}
    # An explicit `default` means the runtime's own policy, on any machine: the user's variable unset.
    explicit, _ = parse_up(["--learner-omp-wait", "default"])
    assert omp_env(explicit, layout_of(explicit, gpu=False, cores=16), "learner") == {"OMP_WAIT_POLICY": None}
    with pytest.raises(FlagError, match="invalid choice 'spin' for argument '--learner-omp-wait'"):
        parse_up(["--learner-omp-wait", "spin"])


def test_evaluations_run_in_their_own_process_or_between_the_learners_updates():
    assert not choose(2, gpu=False).eval_in_learner and not choose(16, gpu=False).eval_in_learner
    inline = choose(2, gpu=False, evaluate_in="learner")
    assert inline.eval_in_learner and "evaluator between the learner's updates" in inline.describe()
    assert "--evaluate-in" in inline.describe()
    assert not choose(2, gpu=False, evaluator=False, evaluate_in="learner").eval_in_learner  # off is off
    cmd, _ = parse_up(["--evaluate-in", "learner"])
    argv = service_argv(cmd, Path("run"), layout_of(cmd, gpu=False, cores=2))
    assert "evaluator" not in argv and "--eval-between-updates" in argv["learner"]
    cmd, _ = parse_up([])
    argv = service_argv(cmd, Path("run"), layout_of(cmd, gpu=False, cores=2))
    assert "evaluator" in argv and "--eval-between-updates" not in argv["learner"]
    with pytest.raises(FlagError, match="invalid choice 'elsewhere'"):
        parse_up(["--evaluate-in", "elsewhere"])
    # A gripper behind a bridge is evaluated through a bridge of its own, by the evaluator process.
    with pytest.raises(ConfigError, match="--evaluate-in process"):
        parse_up(["--task", "gripper-valve", "--bridge", "stand-in", "--evaluate-in", "learner"])


@pytest.mark.parametrize(("flags", "named"), [
    (["--no-evaluator", "--evaluator-nice", "5"], "--no-evaluator with --evaluator-nice"),
    (["--evaluate-in", "learner", "--evaluator-nice", "5"], "--evaluate-in learner with --evaluator-nice"),
    (["--no-evaluator", "--evaluate-in", "learner"], "--no-evaluator with --evaluate-in learner"),
    (["--no-evaluator", "--evaluate-in", "process"], "--no-evaluator with --evaluate-in process"),
])
def test_evaluator_flags_that_contradict_each_other_are_refused(flags, named):
    # --no-evaluator means no evaluations at all: neither a process nor the learner plays them.
    with pytest.raises(ConfigError, match=named):
        parse_up(flags)


@pytest.mark.parametrize("version", ["v2", "v1"])
def test_the_cores_are_those_a_cgroups_cpu_quota_allows_where_it_is_below_the_affinity(
        tmp_path, monkeypatch, version):
    """A container limited to 1.5 CPUs on an 8-core host (docker --cpus): its affinity shows all 8,
    and 8 torch threads would only be throttled."""
    from nasa import layout

    monkeypatch.setattr(layout.os, "sched_getaffinity", lambda pid: set(range(8)))
    monkeypatch.setattr(layout, "CGROUP_ROOT", tmp_path)
    monkeypatch.setattr(layout, "SELF_CGROUP", tmp_path / "self")
    if version == "v2":
        (tmp_path / "self").write_text("0::/run.slice/nasa\n")
        (tmp_path / "run.slice" / "nasa").mkdir(parents=True)
        (tmp_path / "cpu.max").write_text("max 100000\n")
        (tmp_path / "run.slice" / "cpu.max").write_text("150000 100000\n")  # the parent's limit holds
        (tmp_path / "run.slice" / "nasa" / "cpu.max").write_text("max 100000\n")
    else:
        (tmp_path / "self").write_text("5:memory:/docker/x\n4:cpu,cpuacct:/docker/x\n")
        own = tmp_path / "cpu,cpuacct" / "docker" / "x"
        own.mkdir(parents=True)
        (own / "cpu.cfs_quota_us").write_text("150000\n")
        (own / "cpu.cfs_period_us").write_text("100000\n")
        (tmp_path / "cpu,cpuacct" / "cpu.cfs_quota_us").write_text("-1\n")  # none at the root
        (tmp_path / "cpu,cpuacct" / "cpu.cfs_period_us").write_text("100000\n")
    assert layout.usable_cores() == 1
    assert layout.choose(layout.usable_cores(), gpu=False).learner_threads == 1
    (tmp_path / "self").write_text("0::/\n")  # no quota: the affinity
    assert layout.usable_cores() == 8


def test_more_learner_threads_than_the_host_can_make_are_refused(monkeypatch):
    """Far past the cores, OpenMP cannot make the threads and the learner aborts at each restart: a
    flag's error (exit 2) before anything starts, not a learner that crash-loops."""
    from nasa import layout

    monkeypatch.setattr(layout, "usable_cores", lambda: 2)
    with pytest.raises(ConfigError, match=r"--learner-threads 20000 on 2 core\(s\): at most 16 on this host"):
        parse_up(["--learner-threads", "20000"])
    cmd, _ = parse_up(["--learner-threads", "16"])  # more threads than cores: the user's choice
    assert layout_of(cmd, gpu=False, cores=2).learner_threads == 16


@pytest.mark.parametrize("flags", [["--evaluate-in", "process"], ["--evaluator-nice", "5"]])
def test_flags_for_an_evaluator_are_refused_with_the_real_gripper_which_has_none(flags):
    """--bridge hardware has no evaluator (its one gripper is the actor's): a flag that asks for one,
    or sets its priority, would be dropped without a word."""
    hardware = ["--task", "gripper-valve", "--bridge", "hardware", "--bridge-config",
                str(Path(__file__).resolve().parents[1] / "services" / "robot_bridge" / "example.toml")]
    flag = " ".join(flags[:1] if flags[0] == "--evaluator-nice" else flags)
    with pytest.raises(ConfigError, match=f"--bridge hardware with {flag}.*no evaluator; leave {flag} out"):
        parse_up([*hardware, *flags])
    assert not layout_of(parse_up(hardware)[0], gpu=False, cores=2).evaluator
