"""/metrics: the learner's /status in Prometheus' text format, through prometheus-client.

Every figure of /status is one sample: the table below names each one's
metric (Prometheus conventions: units in the name, `_total` for counters),
and a count of the run (env steps, updates, ...) is two: a counter `_total` of
what it grew by since this process started (0 at each start, never lower: a
learner resumed from a checkpoint restarts below the last value scraped,
which Prometheus would read as a reset followed by the whole run at once),
and a gauge `nasa_run_...` of the run's own figure (its position, which may
step back on a resume); `process_start_time_seconds` marks each start,
the actors' figures carry an `actor` label (an actor's fault state is a
gauge of 1 labelled with the state, its env step times a histogram), losses
and intrinsic means a `name` label, and the run's identity (run id, algorithm, task, device, config
digest) is one `nasa_run_info` sample rather than a label on every series.
The figures are read from /status when scraped, so nothing is computed in the
update loop; the loop only observes two histograms (update time, batch wait).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator

from prometheus_client import CollectorRegistry, Histogram, ProcessCollector, generate_latest
from prometheus_client.core import (
    CounterMetricFamily,
    GaugeMetricFamily,
    HistogramMetricFamily,
    InfoMetricFamily,
    Metric,
)

# (path in /status, metric name, kind, help)
SCALARS: tuple[tuple[str, str, str, str], ...] = (
    ("env_steps", "nasa_env_steps_total", "counter", "Environment steps stored by the replay (all actors)"),
    ("steps_budget", "nasa_env_steps_budget", "gauge", "The run's step budget (--steps)"),
    ("warmup_steps", "nasa_warmup_env_steps", "gauge", "Uniform random env steps before learning"),
    ("action_repeat", "nasa_action_repeat_frames", "gauge", "Simulator frames per env step"),
    ("updates", "nasa_updates_total", "counter", "Gradient updates of the learner"),
    ("updates_target_per_env_step", "nasa_updates_per_env_step_target", "gauge", "G, the target ratio"),
    ("updates_per_env_step", "nasa_updates_per_env_step", "gauge", "Updates per env step after warm-up"),
    ("env_steps_per_s", "nasa_env_steps_per_second", "gauge", "Env steps per second over ~10 s"),
    ("updates_per_s", "nasa_updates_per_second", "gauge", "Updates per second over ~10 s"),
    ("policy_version", "nasa_policy_version", "gauge", "Version of the newest published weights"),
    ("eval.step", "nasa_eval_env_step", "gauge", "Env step of the newest evaluation"),
    ("eval.mean", "nasa_eval_return_mean", "gauge", "Mean return of the newest evaluation"),
    ("eval.std", "nasa_eval_return_std", "gauge", "Standard deviation of the newest evaluation's returns"),
    ("intrinsic.scored", "nasa_intrinsic_scored_transitions_total", "counter",
     "Transitions given an intrinsic reward"),
    ("intrinsic.scored_at_first_sample", "nasa_intrinsic_scored_at_first_sample_transitions_total", "counter",
     "Transitions scored when a training batch first brought them, not on arrival"),
    ("intrinsic.zeroed", "nasa_intrinsic_zeroed_transitions_total", "counter",
     "Transitions whose intrinsic reward came out non-finite and was stored as 0"),
    ("resumed", "nasa_resumed", "gauge", "1 if the learner started from a checkpoint"),
    ("wall_s", "nasa_learner_wall_seconds", "gauge", "Seconds the learner has run (over restarts)"),
    ("replay.size", "nasa_replay_transitions", "gauge", "Transitions in the replay"),
    ("replay.bytes", "nasa_replay_bytes", "gauge", "The replay's memory in bytes"),
    ("replay.done", "nasa_replay_done", "gauge", "1 once the replay has stored the step budget"),
    ("replay.dropped", "nasa_replay_dropped_transitions_total", "counter",
     "Transitions the replay dropped (a batch that did not continue its episode)"),
    ("replay.invalid_messages", "nasa_replay_invalid_messages_total", "counter",
     "Messages the replay refused"),
    ("replay.limiter_inserts", "nasa_replay_limiter_inserts_total", "counter", "Rate limiter's inserts"),
    ("replay.limiter_samples", "nasa_replay_limiter_samples_total", "counter", "Rate limiter's samples"),
    ("invalid_messages", "nasa_invalid_messages_total", "counter", "Messages the learner refused"),
    ("nonfinite.skipped_updates", "nasa_nonfinite_skipped_updates_total", "counter",
     "Updates skipped for a non-finite loss or gradient"),
    ("nonfinite.dropped_batches", "nasa_nonfinite_dropped_batches_total", "counter",
     "Training batches dropped for non-finite values"),
)
# Figures of each entry of actors[], labelled actor="<id>".
ACTOR_FIGURES: tuple[tuple[str, str, str, str], ...] = (
    ("alive", "nasa_actor_alive", "gauge", "1 if the actor's liveliness token is present"),
    ("incarnation", "nasa_actor_incarnation", "gauge", "Start stamp of the actor's current incarnation"),
    ("env_steps", "nasa_actor_env_steps_total", "counter", "Env steps of the actor's current incarnation"),
    ("episodes", "nasa_actor_episodes_total", "counter", "Episodes of the actor's current incarnation"),
    ("policy_version", "nasa_actor_policy_version", "gauge", "Policy version the actor acts with"),
    ("steps_per_s", "nasa_actor_env_steps_per_second", "gauge", "Env steps per second of the actor"),
    ("last_seen_s", "nasa_actor_last_seen_seconds", "gauge", "Seconds since the actor's last heartbeat"),
    ("refused", "nasa_actor_refused_batches_total", "counter",
     "Batches of the actor's current incarnation the replay acknowledged without storing them"),
)
# Dicts of /status whose entries become one labelled gauge: (path, metric, label, help).
LABELLED: tuple[tuple[str, str, str, str], ...] = (
    ("policy_lag", "nasa_policy_lag_updates", "stat",
     "Updates between the policy that collected a sampled row and the learner's (mean, max)"),
    ("losses", "nasa_loss", "name", "Recent mean of each loss the agent reports"),
)
INTRINSIC_MEANS = ("novelty_mean", "surprise_mean")
INFO = ("run_id", "algo", "task", "device", "config_digest")
# Parts of /status given otherwise (the above, the info, the intrinsic means, the non-finite losses
# and the replay's write error below) or that are no figure (row indices of dropped batches).
HANDLED = {"actors", "policy_lag", "losses", "nonfinite.losses", "nonfinite.dropped_rows",
           "replay.write_error", "writes", *(f"intrinsic.{k}" for k in INTRINSIC_MEANS), *INFO}


def unnamed_figures(status: dict, prefix: str = "") -> list[tuple[str, float]]:
    """Numbers of /status the tables above do not name (a field added since): each becomes a
    gauge `nasa_status_<path>`, so /metrics never lacks a figure of /status."""
    named = {path for path, *_ in SCALARS}
    out = []
    for key, value in status.items():
        path = prefix + key
        if path in HANDLED or path in named:
            continue
        if isinstance(value, dict):
            out += unnamed_figures(value, path + ".")
        elif (number := figure(value)) is not None:
            out.append((path, number))
    return out


def lookup(status: dict, path: str) -> object:
    """The value at a dotted path, or None where /status has none (an older run's status.json)."""
    value: object = status
    for key in path.split("."):
        if not isinstance(value, dict) or key not in value:
            return None
        value = value[key]
    return value


def figure(value: object) -> float | None:
    """A value of /status as a sample's value, or None where it is no number: a stopped run's
    status.json is read from disk, and a damaged one must cost its own figures, not the scrape."""
    if not isinstance(value, bool | int | float):
        return None
    try:
        return float(value)
    except OverflowError:  # an integer beyond a float's range
        return math.inf if value > 0 else -math.inf


def _actors(status: dict) -> list[dict]:
    actors = lookup(status, "actors")
    return [a for a in actors if isinstance(a, dict) and "id" in a] if isinstance(actors, list) else []


def run_gauge(counter: str) -> str:
    """The gauge of a run-wide count beside its counter: nasa_updates_total -> nasa_run_updates."""
    return "nasa_run_" + counter.removeprefix("nasa_").removesuffix("_total")


class Growth:
    """How much each run-wide count grew while this process watched it, from its value at the start
    (`start`: a /status then; a count absent there starts at its first value seen). A count that
    falls (the replay restarted, the limiter resynced) adds nothing, and what it grows by after
    counts again."""

    def __init__(self, start: dict | None = None) -> None:
        self._last: dict[str, float] = {}
        self._grown: dict[str, float] = {}
        for path, _, kind, _ in SCALARS:
            value = figure(lookup(start, path)) if kind == "counter" and start is not None else None
            if value is not None and math.isfinite(value):
                self._last[path] = value

    def __call__(self, path: str, value: float) -> float:
        if not math.isfinite(value):  # no count (a damaged status): it must not stop the counting
            return self._grown.get(path, 0.0)
        last = self._last.setdefault(path, value)
        if value > last:
            self._grown[path] = self._grown.get(path, 0.0) + value - last
        self._last[path] = value
        return self._grown.get(path, 0.0)


def _family(kind: str, name: str, help_text: str, labels: list[str]) -> Metric:
    cls = CounterMetricFamily if kind == "counter" else GaugeMetricFamily
    return cls(name, help_text, labels=labels)


class StatusCollector:
    """Turns one /status into metric families at scrape time."""

    def __init__(self, status: Callable[[], dict], start: dict | None = None) -> None:
        self.status = status
        self.growth = Growth(start)

    def describe(self) -> list[Metric]:
        return []  # unknown until scraped: registering must not call status()

    def collect(self) -> Iterator[Metric]:
        s = self.status()
        info = InfoMetricFamily("nasa_run", "The run's identity")
        info.add_metric([], {k: str(s.get(k, "")) for k in INFO})
        yield info
        for path, name, kind, help_text in SCALARS:
            if (value := figure(lookup(s, path))) is None:
                continue
            if kind == "counter":
                family = GaugeMetricFamily(run_gauge(name), f"{help_text}, over the run")
                family.add_metric([], value)
                yield family
                value = self.growth(path, value)
                help_text += ", since this process started"
            family = _family(kind, name, help_text, [])
            family.add_metric([], value)
            yield family
        for path, name, label, help_text in LABELLED:
            family = GaugeMetricFamily(name, help_text, labels=[label])
            entries = lookup(s, path)
            for key, value in (entries.items() if isinstance(entries, dict) else ()):
                if (number := figure(value)) is not None:
                    family.add_metric([str(key)], number)
            yield family
        yield from self.collect_health(s)
        for path, value in unnamed_figures(s):
            family = GaugeMetricFamily("nasa_status_" + path.replace(".", "_"), f"/status field {path}")
            family.add_metric([], value)
            yield family
        family = GaugeMetricFamily("nasa_intrinsic_mean", "Running mean of each intrinsic reward",
                                   labels=["name"])
        for key in INTRINSIC_MEANS:
            if (value := figure(lookup(s, f"intrinsic.{key}"))) is not None:
                family.add_metric([key.removesuffix("_mean")], value)
        yield family
        for key, name, kind, help_text in ACTOR_FIGURES:
            family = _family(kind, name, help_text, ["actor"])
            for a in _actors(s):
                if (value := figure(a.get(key))) is not None:
                    family.add_metric([str(a["id"])], value)
            yield family
        yield from self.collect_actor_env(_actors(s))

    @staticmethod
    def collect_actor_env(actors: list[dict]) -> Iterator[Metric]:
        """What each actor's environment reports: its fault state (where it has one) and step times."""
        faults = GaugeMetricFamily(
            "nasa_actor_fault_state", "1 for the fault state the actor's environment reports (a robot "
            "bridge: ok, estop, overload, torque_off, held, bridge_lost, ...); absent where it reports none",
            labels=["actor", "state"])
        steps = HistogramMetricFamily(
            "nasa_actor_env_step_duration_seconds", "Time of one env step in the actor (its incarnation's)",
            labels=["actor"])
        for a in actors:
            if isinstance(a.get("fault"), str):
                faults.add_metric([str(a["id"]), a["fault"]], 1.0)
            if (buckets := _buckets(a.get("env_step_seconds"))) is not None:
                steps.add_metric([str(a["id"])], buckets=buckets[0], sum_value=buckets[1])
        yield faults
        yield steps

    @staticmethod
    def collect_health(s: dict) -> Iterator[Metric]:
        """The non-finite losses by name, whether the replay's writes fail, and the learner's own
        refused writes by file."""
        family = CounterMetricFamily("nasa_nonfinite_losses", "Non-finite values of each loss",
                                     labels=["name"])
        entries = lookup(s, "nonfinite.losses")
        for key, entry in (entries.items() if isinstance(entries, dict) else ()):
            if isinstance(entry, dict) and (count := figure(entry.get("count"))) is not None:
                family.add_metric([str(key)], count)
        yield family
        if (error := lookup(s, "replay.write_error")) is not None:
            family = GaugeMetricFamily("nasa_replay_write_failing", "1 while the replay cannot write")
            family.add_metric([], float(bool(error)))
            yield family
        counts, failing = lookup(s, "writes.failed"), lookup(s, "writes.failing")
        family = CounterMetricFamily("nasa_write_failures", "Writes of the run folder the disk refused "
                                     "(dropped: the learner goes on)", labels=["file"])
        for key, count in (counts.items() if isinstance(counts, dict) else ()):
            if (n := figure(count)) is not None:
                family.add_metric([str(key)], n)
        yield family
        family = GaugeMetricFamily("nasa_write_failing", "1 while the disk refuses this kind of write",
                                   labels=["file"])
        for key in (counts if isinstance(counts, dict) else ()):
            family.add_metric([str(key)], float(isinstance(failing, list) and key in failing))
        yield family


def _buckets(h: object) -> tuple[list[tuple[str, float]], float] | None:
    """An actor's env step histogram of /status (step_histogram's form) as (buckets, sum), or None."""
    if not isinstance(h, dict) or not isinstance(le := h.get("le"), dict):
        return None
    total = figure(h.get("sum"))
    buckets = [(str(bound), n) for bound, count in le.items() if (n := figure(count)) is not None]
    if total is None or len(buckets) != len(le) or not buckets or buckets[-1][0] != "+Inf":
        return None  # Prometheus' histogram ends with its +Inf bucket
    return buckets, total


class LearnerMetrics:
    """The learner's registry: /status's figures plus the update-time, scoring-time and batch-wait
    histograms."""

    def __init__(self, status: Callable[[], dict], start: dict | None = None) -> None:
        """`start`: the /status at this process's start, which the counters count from."""
        self.registry = CollectorRegistry(auto_describe=False)
        self.registry.register(StatusCollector(status, start))  # type: ignore[arg-type]
        ProcessCollector(registry=self.registry)  # process_start_time_seconds: each start shows
        buckets = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0)
        self.update_seconds = Histogram(
            "nasa_update_duration_seconds", "Time of one update (scoring owed rows, then agent.update)",
            buckets=buckets, registry=self.registry)
        self.scoring_seconds = Histogram(
            "nasa_scoring_duration_seconds",
            "Time of one update's scoring of owed rows (a part of nasa_update_duration_seconds)",
            buckets=buckets, registry=self.registry)
        self.batch_wait_seconds = Histogram(
            "nasa_batch_wait_seconds", "Time the learner waited for its next training batch",
            buckets=buckets, registry=self.registry)

    def render(self) -> bytes:
        return generate_latest(self.registry)


def status_metrics(status: dict) -> bytes:
    """The text a stopped run's /status gives (no histograms: nothing is being measured; the
    counters 0: nothing grows)."""
    registry = CollectorRegistry(auto_describe=False)
    registry.register(StatusCollector(lambda: status, start=status))  # type: ignore[arg-type]
    return generate_latest(registry)
