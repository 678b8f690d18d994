"""The learner service: Zenoh plumbing around `LearnerCore`.

- Batches: a `Prefetcher` keeps sample requests in flight to the replay (paced
  by its rate limiter), so the compute thread finds the next batch ready.
- Intrinsic rewards (collect timing): the core's scorer scores the oldest
  unscored rows before each update and writes the scores back (a thread fetches
  them while the previous update runs, `--no-score-ahead` asks before each).
- Weights: version = the update count; published every `publish_every`
  updates (latest wins) and served on `learner/weights/latest` for processes
  that just started. The evaluator's weights go out on `learner/eval_weights`
  (and `.../latest`) once per evaluation period, when its eval step is
  reached, with the decoder: it plays each evaluation with the weights of its
  step and takes in nothing else.
- Records: evaluations from the evaluator become eval.csv rows (or, with
  --eval-between-updates, the learner plays them itself between updates),
  episodes the actors report become train.csv rows; a checkpoint every checkpoint_every env
  steps, at the end and on SIGTERM/SIGINT; with each one written, the /status of that moment is
  left in <data>/learner/status.json, and a learner that resumes from its checkpoint leaves that
  checkpoint's there as it starts.
- The run ends when the replay's step budget is reached and the learner has
  done the schedule's updates (shared.schedule.total_updates: G * (steps - warmup),
  and the warm-up burst's beyond G with it) or the limiter allows no more; it then
  scores the last arrivals, waits for the last evaluation, checkpoints and
  publishes Stop.
- One learner per run: before serving it looks for the run's learner token and
  exits 2 if another process holds it (shared.faults.claim_role).
"""

from __future__ import annotations

import json
import queue
import time
from collections.abc import Callable
from contextlib import ExitStack
from pathlib import Path

import torch
import zenoh

from services.learner.core import LearnerCore
from services.learner.evaluation import BetweenUpdates
from services.learner.health import LearnerArgs, degraded_reasons, health_reasons
from services.learner.history import History, HistoryError
from services.learner.metrics import LearnerMetrics
from services.learner.status_api import CheckpointRequests
from shared import envs, faults, run_config, wire
from shared.config import ConfigError
from shared.device import resolve_device
from shared.evaluation import newest_eval_step
from shared.files import replace_text
from shared.prefetch import DevicePrefetcher, PrefetchError
from shared.replay.client import Prefetcher, ZenohReplayClient
from shared.service import Log, StopFlag

BLOCK = zenoh.CongestionControl.BLOCK
STATUS_FILE = "learner/status.json"
# At the end, how long the learner waits for an evaluator to (re)appear before it stops waiting for
# the last evaluation: a restarted evaluator takes a while to join the run.
EVALUATOR_GRACE_S = 30.0


class Learner:
    def __init__(self, args: LearnerArgs, session: zenoh.Session, stop: StopFlag,
                 run: run_config.RunConfig) -> None:
        self.args, self.session, self.stop = args, session, stop
        self.keys = wire.Keys(args.run_id)
        self.log = Log("learner")
        self.bounds = wire.Bounds.of(run.spec, steps=run.config.steps)
        if args.threads > 0:
            torch.set_num_threads(args.threads)
        self.client = ZenohReplayClient(session, self.keys, run.spec, self.log, steps=run.config.steps)
        self.core = LearnerCore(run, args.data, self.client, resolve_device(run.config.device))
        self._evals: queue.Queue[wire.EvalResult] = queue.Queue()
        self._episodes: queue.Queue[tuple[float, int]] = queue.Queue()
        self._latest: dict[str, bytes] = {}  # the newest message of each weights key, for `.../latest`
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._published: int | None = None  # the update count of the actors' weights last published
        self.wall_s = self.core.counters.wall_s
        self.metrics = LearnerMetrics(self.status, start=self.status())  # counters from here
        self.history = History()  # read by its own thread, never the update loop
        self._scalars_at = 0.0
        self._checkpoint_asked = CheckpointRequests()  # POST /control/checkpoint; the loop writes it
        self.between = (BetweenUpdates(self.core.config, self.core.agent, self.core.eval["step"],
                                       self.core.restored_eval_draws)
                        if args.eval_between_updates else None)
        if self.between is not None:
            self.core.eval_draws = self.between.draws
        self._evaluators: set[str] = set()  # liveliness keys of the run's evaluators
        if self.core.resumed:
            self.log(f"resumed from checkpoint: {self.core.agent.num_updates} updates, "
                     f"env step {self.core.env_steps}")

    # -- Zenoh callbacks: decode, hand over, return ------------------------------------

    def _decoded(self, sample: zenoh.Sample, cls: type[wire.M], what: str) -> wire.M | None:
        try:
            return wire.decode(sample.payload.to_bytes(), cls, self.bounds)
        except Exception as err:  # noqa: BLE001 -- a message never kills a callback
            self._invalid(what, err)
            return None

    def _invalid(self, what: str, err: object) -> None:
        n = self.core.board.count_invalid()
        self.log.every("invalid", 5.0, f"invalid message ({n} so far): {what}: {err}")

    def _on_stats(self, sample: zenoh.Sample) -> None:
        if (s := self._decoded(sample, wire.ReplayStats, "replay stats")) is not None:
            self.core.board.replay_stats(s)

    def _on_actor_status(self, sample: zenoh.Sample) -> None:
        if (s := self._decoded(sample, wire.ActorStatus, "actor status")) is None:
            return
        try:  # the values were checked on decode; this guards against what no check foresaw
            self.core.board.actor_status(s)
            for ret, length in s.episode_returns:
                self._episodes.put((float(ret), int(length)))
        except Exception as err:  # noqa: BLE001
            self._invalid("actor status", err)

    def _on_alive(self, sample: zenoh.Sample) -> None:
        try:
            role, ident, inc = self.keys.parse_alive(str(sample.key_expr))
            if role == "actor" and inc is not None:
                self.core.board.actor_alive(int(ident), inc, sample.kind == zenoh.SampleKind.PUT)
        except Exception as err:  # noqa: BLE001
            self._invalid("liveliness key", err)

    def _on_evaluator_alive(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        if sample.kind == zenoh.SampleKind.PUT:
            self._evaluators.add(key)
        else:
            self._evaluators.discard(key)

    def _on_eval(self, sample: zenoh.Sample) -> None:
        if (r := self._decoded(sample, wire.EvalResult, "eval result")) is None:
            return
        if (why := self.core.eval_problem(r)) is not None:
            return self._invalid("eval result", why)
        # Its writes the disk refused: /status, /metrics and /healthz show them beside the learner's.
        self.core.board.writes.report("evaluator", r.write_failures, r.writes_failing, r.write_error)
        self._evals.put(r)

    def _on_stop(self, sample: zenoh.Sample) -> None:
        if (m := self._decoded(sample, wire.Stop, "stop")) is not None:
            self.stop.set("stop message: " + m.reason)

    def _latest_answer(self, which: str, key: str) -> Callable[[zenoh.Query], None]:
        def answer(query: zenoh.Query) -> None:
            if (msg := self._latest.get(which)) is not None:
                query.reply(key, msg)
            query.drop()
        return answer

    # -- the HTTP controls (POST /control/<name>) ----------------------------------------

    def controls(self) -> dict[str, Callable[[], str]]:
        def stop() -> str:
            # The run's own Stop message: every service ends as at the end of the budget, this one too.
            self.session.put(self.keys.stop, wire.encode(wire.Stop("stop requested over HTTP")),
                             congestion_control=BLOCK)
            return "the run is stopping (checkpoint, then every service exits)"

        return {"checkpoint": self._checkpoint_asked.ask, "stop": stop}

    # -- the loop ----------------------------------------------------------------------

    def publish_weights(self, evaluation: bool = False) -> None:
        msg = self.core.weights_message(self.core.epoch, evaluation)
        if msg is not None:  # never non-finite weights: the actors keep the last good ones
            which = "evaluation" if evaluation else "policy"
            self._latest[which] = msg
            self._publishers[which].put(msg)
            if not evaluation:
                self._published = self.core.agent.num_updates

    def publish_due_weights(self) -> None:
        """The actors' weights every `publish_every` updates, once per update count: a dropped batch
        leaves the count where it was, and the same weights would otherwise go out again."""
        n = self.core.agent.num_updates
        if n % self.args.publish_every == 0 and n != self._published:
            self.publish_weights()

    def publish_eval_weights(self, final: bool = False) -> None:
        """The evaluator's weights, once an eval step is reached (none when the learner evaluates);
        `final`: the run's updates are over, so the budget's step waits no more."""
        if self.between is None and self.core.eval_weights_due(final):
            self.publish_weights(evaluation=True)

    def run(self) -> None:
        from services.learner.status_api import StatusServer, api_token, is_loopback, make_app

        s, k = self.session, self.keys
        if not faults.claim_run_role(s, k, "learner", self.stop, self.log):
            return
        self._leave_start_status()
        try:
            self.history.restore(self.args.data, self.wall_s)
        except HistoryError as err:
            self.log(f"{err}: the dashboard's series start again here")
        token = api_token(self.args.api_token_file)
        if token is None and not is_loopback(self.args.host):
            self.log(f"warning: the status API binds {self.args.host} with no token: anyone who reaches it "
                     "can checkpoint or stop the run (set NASA_API_TOKEN)")
        app = make_app(self.status, self.health, self.history.points, self.metrics.render, self.args.data,
                       controls=self.controls(), token=token, degraded=lambda: degraded_reasons(self.core))
        server = StatusServer(app, self.args.host, self.args.port)
        server.start()
        self.history.start(self.status)
        try:
            with ExitStack() as stack:
                subscriptions = ((k.replay_stats, self._on_stats), (k.eval_result, self._on_eval),
                                 (k.actor_status_all, self._on_actor_status), (k.stop, self._on_stop))
                for key, callback in subscriptions:
                    stack.enter_context(s.declare_subscriber(key, callback))
                alive = s.liveliness().declare_subscriber(k.alive_actors, self._on_alive, history=True)
                stack.enter_context(alive)
                evaluators = s.liveliness().declare_subscriber(k.alive_evaluators, self._on_evaluator_alive,
                                                               history=True)
                stack.enter_context(evaluators)
                # The actors' weights: latest wins (DROP). The evaluator's: each one is an eval step (BLOCK).
                for which, key, latest, congestion in (
                        ("policy", k.weights, k.weights_latest, zenoh.CongestionControl.DROP),
                        ("evaluation", k.eval_weights, k.eval_weights_latest, BLOCK)):
                    stack.enter_context(s.declare_queryable(latest, self._latest_answer(which, latest)))
                    self._publishers[which] = stack.enter_context(
                        s.declare_publisher(key, congestion_control=congestion))
                stack.enter_context(s.liveliness().declare_token(k.alive("learner", 0)))
                self.log(f"run {k.run_id}: status on http://{self.args.host}:{self.args.port}/status")
                self._loop()
        finally:
            self.history.stop()
            server.stop()

    def _loop(self) -> None:
        core, c = self.core, self.core.config
        self.publish_weights()
        self.publish_eval_weights()  # before any update: step 0's, the untrained policy
        # The limiter then counts the samples this learner used: the updates its checkpoint lost
        # (a kill -9 after it) are made up, so the run still ends with G * (steps - warm-up).
        while not self.stop and not self.client.sync_samples(core.agent.num_updates):
            self.stop.wait(0.5)
        wall_start, wall0 = time.monotonic(), self.wall_s
        finished, done_at, resynced_at, used = False, None, None, 0
        with ExitStack() as stack:
            prefetcher = Prefetcher(self.client, c.batch_size, self.args.prefetch, self.stop)
            stack.enter_context(prefetcher)
            staged = None
            if use_device_prefetch(self.args.device_prefetch, core.device):
                staged = DevicePrefetcher(lambda: prefetcher.get(timeout=0.2), core.device)
                stack.enter_context(staged)
            if core.scorer is not None and self.args.score_ahead:
                stack.enter_context(core.scorer.fetching_ahead())
            while not self.stop:
                self.wall_s = wall0 + time.monotonic() - wall_start
                self._drain()
                self.publish_eval_weights()
                asked = self._checkpoint_asked.pending()
                if asked or core.checkpoint_due():
                    self.save_checkpoint()
                    if asked:
                        self._checkpoint_asked.written()
                if self.between is not None and (target := self.between.due(core.env_steps)) is not None:
                    self._evaluate(target)
                    continue
                if core.board.replay["done"] and done_at is None:
                    done_at = time.monotonic()
                # Done: every update made, or the limiter refused a sample after the budget was reached
                # and every batch it served has been used.
                starved = ran_dry(done_at, prefetcher.last_miss, prefetcher.drawn - used)
                if starved and not core.done() and resync_due(core.agent.num_updates, resynced_at):
                    # Short of the target: samples were counted that no update used (a replay restart
                    # counts G per stored step; a dead learner's requests served after it died).
                    # Those served and not used yet (queued, staged, or in a thread's hands) still
                    # count; with no request in flight that number is exact.
                    with prefetcher.paused(timeout=self.client.timeout_s) as quiet:
                        if quiet:
                            ahead = prefetcher.drawn - used
                            synced = self.client.sync_samples(core.agent.num_updates + ahead)
                            if synced:
                                resynced_at = core.agent.num_updates
                            self.log(f"the replay ran dry at {core.agent.num_updates} of "
                                     f"{core.target_updates} updates ({ahead} drawn, not used yet): "
                                     f"limiter {'resynced' if synced else 'not resynced'}")
                    done_at = time.monotonic()
                    continue
                if starved and not core.done():
                    self.log(f"the run ends short: {core.agent.num_updates} of {core.target_updates} "
                             "updates made (the replay ran dry, and resyncing its limiter brought no more)")
                if core.done() or starved:
                    finished = True
                    break
                if core.agent.num_updates >= core.target_updates:
                    # Every update due is made; the limiter's slack would allow more until the
                    # replay's stats say its last env step landed, so wait for them instead.
                    self.stop.wait(0.05)
                    continue
                waited = time.perf_counter()
                on_device = None
                if staged is not None:
                    try:
                        ready = staged.get(timeout=0.2)
                    except PrefetchError as err:  # a live learner that cannot train is never restarted
                        raise faults.WorkerDied(f"the device prefetch thread died: {err}") from err
                    batch, on_device = (ready.host, ready.device) if ready is not None else (None, None)
                else:
                    batch = prefetcher.get(timeout=0.2)
                if dead := prefetcher.dead():  # a live learner that cannot train is never restarted
                    raise faults.WorkerDied(f"learner thread(s) {', '.join(dead)} died")
                if batch is None:
                    continue
                used += 1
                began = time.perf_counter()
                core.train_on(batch, on_device)
                self.metrics.batch_wait_seconds.observe(began - waited)
                self.metrics.update_seconds.observe(time.perf_counter() - began)
                self.metrics.scoring_seconds.observe(core.last_scoring_s)
                core.board.seen_env_steps(self.client.num_inserted)
                self.publish_due_weights()
        self._finish(finished)

    def _finish(self, finished: bool) -> None:
        core = self.core
        if finished:
            if core.scorer is not None:
                core.scorer.catch_up()
            self.publish_weights()
            self.publish_eval_weights(final=True)
            if self.between is None:
                self._wait_final_eval()
            elif (target := self.between.due(core.env_steps, final=True)) is not None:
                self._evaluate(target)
        self.history.add(self.status())
        saved = self.save_checkpoint()
        if not saved:
            # status.json too stays the last checkpoint's: the figures a relaunch resumes from.
            self.log(f"the final checkpoint was not written ({core.checkpoint_error}): the run folder keeps "
                     "the last one written, if any, and its status")
        self._write(None, lambda: core.scalars.status(self.status()))
        self._write(None, core.scalars.close)  # raises what its writing thread met, once
        if finished:
            self.log(f"run done: {core.env_steps} env steps, {core.agent.num_updates} updates")
            self.session.put(self.keys.stop, wire.encode(wire.Stop("run done")), congestion_control=BLOCK)
        else:
            where = f"checkpoint at {core.agent.num_updates} updates" if saved else "no final checkpoint"
            self.log(f"stopping ({self.stop.reason}); {where}")
        self.stop.set("done")

    def save_checkpoint(self) -> bool:
        """A checkpoint, and beside it the dashboard's series and the /status of that moment: a
        learner killed later (SIGKILL, out of memory) leaves `nasa status --data` the checkpoint's
        figures, and its restart resumes the series from here, where only a clean stop used to
        leave them. False: the checkpoint was not written (core.checkpoint_error says why)."""
        saved = self.core.save_checkpoint(self.wall_s)
        if saved:  # else the last status.json stays the last checkpoint's: the figures a restart resumes from
            self._leave("status.json", self.write_status)
        self._leave("history.json", lambda: self.history.save(self.args.data))
        return saved

    def _leave_start_status(self) -> None:
        """status.json as this session starts. A learner that resumed from its checkpoint leaves the
        status of that checkpoint, so one killed again before its next checkpoint still leaves
        `nasa status --data` the figures the run resumes from. A fresh run leaves none: an earlier
        session's last status in this folder would read as this one's."""
        if not (self.core.resumed and self._leave("status.json", self.write_status)):
            (Path(self.args.data) / STATUS_FILE).unlink(missing_ok=True)

    def _leave(self, name: str, write: Callable[[], None]) -> bool:
        """Write a file the run leaves for `nasa status` (`name`, as /status `writes` counts it); one
        the disk refuses (full) is logged and counted like every other refused write, and the run
        still ends: raising here would skip the Stop, and the restarted learner would meet the same
        disk at the same end, over and over."""
        writes = self.core.board.writes
        try:
            write()
        except OSError as err:
            writes.failed(name, err)
            self.log(f"{name} not written: {type(err).__name__}: {err}")
            return False
        writes.ok(name)
        return True

    def _evaluate(self, target: int) -> None:
        """Step `target`'s evaluation, here and now (--eval-between-updates)."""
        assert self.between is not None
        board = self.core.board
        board.evaluating = True  # work, not a stall: /healthz must not have the learner restarted now
        try:
            result = self.between.run(target)
        except envs.EnvFault as err:  # a diverged simulation, a policy acting NaN: the run goes on
            self.log(f"eval step {target}: evaluation failed, no result for this step: {err}")
            return
        finally:
            board.evaluating = False
            board.last_update = time.monotonic()
        self._record_eval(result, ", between updates")

    def _record_eval(self, r: wire.EvalResult, how: str = "") -> None:
        """An evaluation's eval.csv row, logged; one sent again is recorded once."""
        if (row := self.core.record_eval(r)) is not None:
            self.log(f"eval step {r.step} (policy {r.policy_version}{how}): mean return {row['mean']:.1f}")

    def _wait_final_eval(self) -> None:
        c = self.core.config
        last = newest_eval_step(self.core.env_steps, c)  # the budget's own, at the end
        start = time.monotonic()
        while not self.stop and time.monotonic() < start + self.args.final_eval_wait_s:
            self._drain()
            if self.core.eval["step"] is not None and self.core.eval["step"] >= last:
                return
            if not self._evaluators and time.monotonic() > start + EVALUATOR_GRACE_S:
                self.log(f"no evaluator is running: eval step {last} is left unevaluated")
                return
            time.sleep(0.1)

    def _drain(self) -> None:
        """Hand what the callbacks queued to the core, on the loop's thread (the CSV files are its).

        A row or TensorBoard point the disk refuses (full) is dropped and logged, and training goes
        on, as with a checkpoint: exiting lost the updates since the last checkpoint, and the
        restarted learner met the same disk again, in a loop until there was space."""
        self.core.board.sample_rates(self.core.agent.num_updates)
        if time.monotonic() - self._scalars_at >= 10.0:  # TensorBoard's fleet figures
            self._scalars_at = time.monotonic()
            if not self._write(None, lambda: self.core.scalars.status(self.status())):
                return
        while not self._evals.empty():
            result = self._evals.get_nowait()
            if not self._write("eval.csv", lambda r=result: self._record_eval(r)):
                return  # the rest waits for the next drain
        while not self._episodes.empty():
            ret, length = self._episodes.get_nowait()
            if not self._write("train.csv",
                               lambda r=ret, n=length: self.core.record_episode(r, n, wall_s=self.wall_s)):
                return

    def _write(self, csv_file: str | None, write: Callable[[], None]) -> bool:
        """`write()`, which writes a row of `csv_file` and/or TensorBoard points; one the disk refuses
        is logged and counted on the board (/status, /healthz) by what refused it, and dropped (False)."""
        scalars, writes = self.core.scalars, self.core.board.writes
        refused = scalars.refused
        try:
            write()
        except OSError as err:
            what = "tensorboard" if scalars.refused > refused or csv_file is None else csv_file
            if what != csv_file and csv_file is not None:
                writes.ok(csv_file)  # its row went in before the TensorBoard point was refused
            writes.failed(what, err)
            self.log.every("write", 60.0, f"cannot write the run folder, what it refused is dropped: "
                                          f"{what}: {type(err).__name__}: {err}")
            return False
        if csv_file is not None:
            writes.ok(csv_file)
        if not scalars.refusing:
            writes.ok("tensorboard")
        return True

    # -- status ------------------------------------------------------------------------

    def health(self) -> list[str]:
        """Why the learner is unhealthy (empty: healthy): /healthz answers 503 with these."""
        return health_reasons(self.core, self.args, self.stop)

    def status(self) -> dict:
        status = self.core.status(self.keys.run_id, self.wall_s)
        status["invalid_messages"] += self.client.invalid  # the replay's replies it refused, too
        return status

    def write_status(self) -> None:
        """The /status of now, in the run folder (atomically: a reader never sees half of it)."""
        path = Path(self.args.data) / STATUS_FILE
        path.parent.mkdir(parents=True, exist_ok=True)
        replace_text(path, json.dumps(self.status(), indent=2) + "\n")


def main(argv: list[str] | None = None) -> None:
    from shared.service import run_service

    def run(args: LearnerArgs, session: zenoh.Session, stop: StopFlag) -> None:
        with faults.lock_service(Path(args.data), "learner"):
            faults.check_port_free(args.host, args.port, "the status API's", "--port")
            run = run_config.join(args.config, session, wire.Keys(args.run_id), stop)
            Learner(args, session, stop, run).run()

    run_service(LearnerArgs, argv, "python -m services.learner", run, check_args)


def check_args(args: LearnerArgs) -> None:
    """The learner's flags that its parser cannot check (ConfigError: exit 2 before it connects)."""
    from services.learner.status_api import api_token

    use_device_prefetch(args.device_prefetch, torch.device("cpu"))
    api_token(args.api_token_file)
    if args.publish_every < 1:
        raise ConfigError(f"--publish-every must be >= 1, got {args.publish_every}")


def ran_dry(done_at: float | None, last_miss: float | None, unused: int) -> bool:
    """Whether no more batches will come: the replay refused a sample (at `last_miss`) after it said
    its last env step was stored (`done_at`), and none of the batches it served is still on its way
    to an update (`unused`: served, not taken yet). A prefetch thread asks again as soon as it has
    queued a batch, so a refusal can come while the learner still has a batch or two to use."""
    return done_at is not None and unused <= 0 and (last_miss or 0.0) > done_at


def resync_due(updates: int, resynced_at: int | None) -> bool:
    """Whether a learner short of its target when the replay ran dry resyncs the limiter's sample
    count (`resynced_at`: its update count at the last resync, None before any): at the first
    shortfall, and again after a resync that let it make more updates, since samples counted that
    no update used can pile up again; one that brought no update ends the run short."""
    return resynced_at is None or updates > resynced_at


def use_device_prefetch(setting: str, device: torch.device) -> bool:
    """--device-prefetch: `on`, `off`, or `auto` (on with CUDA only)."""
    if setting not in ("auto", "on", "off"):
        raise ConfigError(f"--device-prefetch must be auto, on or off, got {setting!r}")
    return setting == "on" or (setting == "auto" and device.type == "cuda")
