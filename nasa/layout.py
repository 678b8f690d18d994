"""How `nasa up` lays the services out on this machine, where its flags do not say.

On a CPU the learner is the run's bottleneck: every env step costs G updates,
and an update costs far more CPU than an env step. So the cores go to the
learner's torch threads, and one actor is enough to keep it fed (the rate
limiter holds any other back). On a small machine the evaluator runs in its own
process at a low CPU priority: it evaluates in the time the learner leaves,
with the weights the learner sent when the eval step was reached (an
evaluation that starts late takes the newest eval step's), so the learner
never waits for it. (The learner can instead evaluate
between its updates, as `nasa train` does; then it stops learning while it
plays the episodes, where the evaluator's process fills the time the learner
leaves, so that is not the default.) Where the learner's threads share the
cores, they spin while they wait for each other and every other service's
threads sleep: the spinning takes only what the others leave. On a CPU the
learner also publishes its weights after every update, so the actor acts with
the newest policy as `nasa train` (and the reference) does: an update is slow
next to publishing, so that costs little. With a GPU the updates leave the
CPU, env steps become the cost, the spare cores go to actors, and the weights
go out every few updates (the learner's default), not at the GPU's update rate.

The rate limiter keeps G faithful in every layout: the layout only moves where
the CPU time goes. How far the actors may run ahead of the learner is the
limiter's slack plus what each actor has sent and the replay not yet taken.
With one actor on a CPU that lead is one env step (the limiter's slack one
step, each transition sent alone, one unacknowledged): the learner is the
bottleneck either way, so a longer lead only makes the actor act with older
weights, where `nasa train` acts with the policy of the update just made.
Elsewhere the services' defaults (the replay's slack of 2 x G x 16 + 8
samples, room for two 8-transition messages of two actors), so several actors
do not wait on each other.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from shared.replay.adder import SEND_BATCH

# Below this many cores the evaluator would take its CPU time from the learner.
SMALL_MACHINE_CORES = 4
# How the learner's OpenMP threads wait: `auto` chosen here, `passive` sleep, `active` spin,
# `default` the OpenMP runtime's own (spin a while, then sleep).
OmpWait = Literal["auto", "passive", "active", "default"]
# Where evaluations run: `process` the evaluator service, `learner` between the learner's updates
# (as `nasa train` does); `auto` chosen here.
EvalWhere = Literal["auto", "process", "learner"]
LOW_PRIORITY = 10
MAX_GPU_ACTORS = 8


@dataclass(frozen=True)
class Layout:
    actors: int
    learner_threads: int
    evaluator: bool
    evaluator_nice: int
    cores: int
    gpu: bool
    omp_passive: bool = False
    """OpenMP threads sleep rather than spin while they wait: on a machine the learner's threads share
    with the other services, spinning threads take the cores the others need."""
    learner_omp_wait: OmpWait = "default"
    """How the learner's own OpenMP threads wait (OmpWait, never `auto` here)."""
    eval_in_learner: bool = False
    """The learner evaluates between its updates, and no evaluator process runs."""
    publish_every: int = 0
    """The learner publishes weights every this many updates; 0: the learner's default."""
    actor_lead: int = 0
    """Env steps the actors may run ahead of the learner's schedule; 0: the services' defaults."""

    def omp_env(self, role: str) -> dict[str, str | None]:
        """OMP_WAIT_POLICY for one service's process (None: unset, the runtime's default); empty
        where the layout leaves the environment as it is."""
        if role == "learner":
            wait = self.learner_omp_wait
            return {"OMP_WAIT_POLICY": None if wait == "default" else wait.upper()}
        return {"OMP_WAIT_POLICY": "PASSIVE"} if self.omp_passive else {}

    def describe(self) -> str:
        evaluator = "off" if not self.evaluator else "between the learner's updates" if self.eval_in_learner \
            else "own process" + (f" at nice {self.evaluator_nice}" if self.evaluator_nice else "")
        gpu = "a GPU" if self.gpu else "no GPU"
        others = ", the other services' passive" if self.omp_passive else ""
        omp = f" (OpenMP waits {self.learner_omp_wait}{others})"
        weights = "the learner's default" if not self.publish_every else "every update" \
            if self.publish_every == 1 else f"every {self.publish_every} updates"
        lead = "the replay's default" if not self.actor_lead else f"{self.actor_lead} env step(s)"
        return (f"layout for {self.cores} core(s), {gpu}: {self.actors} actor(s), "
                f"learner {self.learner_threads} torch thread(s)"
                f"{omp}, weights published {weights}, actors' lead {lead}, evaluator {evaluator} "
                "(--actors, --learner-threads, --learner-omp-wait, --publish-every, --actor-lead, "
                "--evaluate-in, --evaluator-nice, --no-evaluator override)")

    def lead_argv(self, updates_per_step: int) -> dict[str, list[str]]:
        """The replay's and each actor's flags for `actor_lead` (none for 0, the defaults): the
        limiter's slack that many steps of G samples, and per actor at most that many transitions
        sent and not yet acknowledged."""
        if not self.actor_lead:
            return {"replay": [], "actor": []}
        send = min(self.actor_lead, SEND_BATCH)
        return {"replay": ["--error-buffer", str(self.actor_lead * updates_per_step)],
                "actor": ["--send-batch", str(send), "--max-in-flight", str(max(1, self.actor_lead // send))]}


CGROUP_ROOT = Path("/sys/fs/cgroup")
SELF_CGROUP = Path("/proc/self/cgroup")


def usable_cores() -> int:
    """Cores this process may use: those it may run on (a taskset's or cpuset's limit, not the
    host's count), and no more than its cgroup's CPU quota (a container's --cpus), which the
    affinity does not show: threads past the quota are only throttled."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        cores = os.cpu_count() or 1
    quota = cpu_quota()
    return cores if quota is None else max(1, min(cores, int(quota)))


def cpu_quota() -> float | None:
    """The CPUs this process's cgroup allows (quota / period; the tightest of its cgroup and the ones
    above it, cgroup v2 or v1); None where none is set or none can be read."""
    try:
        lines = SELF_CGROUP.read_text().splitlines()
    except OSError:
        return None
    limits = []
    for line in lines:
        if line.count(":") < 2:
            continue
        _, controllers, path = line.split(":", 2)
        if controllers == "":  # v2: the unified hierarchy, at the root or beside v1 ones
            bases, read = [CGROUP_ROOT, CGROUP_ROOT / "unified"], _v2_quota
        elif "cpu" in controllers.split(","):
            bases, read = [CGROUP_ROOT / controllers], _v1_quota
        else:
            continue
        own = Path(path.lstrip("/"))
        for base in bases:  # in a container the root may already be its own cgroup
            limits += [q for d in (own, *own.parents) if (q := read(base / d)) is not None]
    return min(limits, default=None)


def _v2_quota(folder: Path) -> float | None:
    try:
        quota, period = (folder / "cpu.max").read_text().split()
        return None if quota == "max" else int(quota) / int(period)
    except (OSError, ValueError):
        return None


def _v1_quota(folder: Path) -> float | None:
    try:
        quota = int((folder / "cpu.cfs_quota_us").read_text())
        period = int((folder / "cpu.cfs_period_us").read_text())
    except (OSError, ValueError):
        return None
    return None if quota <= 0 or period <= 0 else quota / period


def choose(cores: int, gpu: bool, actors: int = 0, learner_threads: int = 0, evaluator: bool = True,
           evaluator_nice: int | None = None, learner_omp_wait: OmpWait = "auto",
           evaluate_in: EvalWhere = "auto", publish_every: int = 0, actor_lead: int = 0) -> Layout:
    """The layout for `cores` and a GPU or not; a nonzero (or not None) argument is the user's choice
    and is kept as given."""
    small = cores < SMALL_MACHINE_CORES
    if not actors:
        actors = max(1, min(MAX_GPU_ACTORS, cores - 3)) if gpu else max(1, cores // 8)
    if not learner_threads:
        # A GPU learner needs a thread for its host-side work; a CPU one everything the actors leave,
        # and on a small machine all of it: the actors mostly wait on the rate limiter.
        learner_threads = 2 if gpu else cores if small else max(1, cores - actors - 1)
    if evaluator_nice is None:
        evaluator_nice = LOW_PRIORITY if small else 0
    shared = not gpu and learner_threads + actors + 1 > cores
    if learner_omp_wait == "auto":
        # Where the cores are shared, the learner's threads spin between parallel regions (they are
        # the bottleneck, and the rest need little CPU), and every other service's sleep.
        learner_omp_wait = "active" if shared else "default"
    if not publish_every and not gpu:
        publish_every = 1  # act with the newest policy, as nasa train does
    if not actor_lead and not gpu and actors == 1:
        actor_lead = 1  # nor act ahead on older weights: the learner sets the pace anyway
    return Layout(actors, learner_threads, evaluator, evaluator_nice, cores, gpu,
                  omp_passive=shared, learner_omp_wait=learner_omp_wait,
                  eval_in_learner=evaluator and evaluate_in == "learner", publish_every=publish_every,
                  actor_lead=actor_lead)
