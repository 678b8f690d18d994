"""The evaluator service: deterministic evaluation episodes with the weights of each eval step.

Each time the learner's env step count reaches a multiple of
config.eval_every, the learner sends the weights it holds then, with the
decoder (`learner/eval_weights`); the evaluator runs config.eval_episodes
deterministic episodes (shared/evaluation.py, as the single-process trainer)
with them and publishes the returns (`eval/result`, BLOCK); the learner
writes them to eval.csv. Step 0 is evaluated with the learner's initial
weights (version 0), as the trainer does, unless eval_at_start is off (the
reference has no step-0 evaluation). If evaluation is slower than training,
it evaluates the newest eval step's weights and skips those in between. It
takes in no other weights: the policy's weights of every update are the
actors'.

With a run folder (--data, env NASA_DATA) it also leaves pictures there
(services/evaluator/media.py): after each evaluation the autoencoder's view
of the first episode's frames (<data>/media/autoencoder.png, and the
TensorBoard image `autoencoder/view`), and every `video_every` evaluations
an MP4 of that episode. They are made here, from the episode just played:
the learner never renders.

With `--bridge ID` (a gripper task) it evaluates through that robot bridge (its
own, never an actor's), created once the bridge is there; an evaluation the
bridge abandons (gone, e-stop, fault) is played again when the bridge is back.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import zenoh

from services.evaluator.media import AutoencoderTap, EvalMedia
from services.robot_bridge.client import BridgeHeld, BridgePresence, client_name
from shared import checkpoint, envs, faults, run_config, wire
from shared.agents import make_agent
from shared.config import EVAL_SEED_OFFSET
from shared.device import resolve_device
from shared.env_loop import EnvLoop
from shared.evaluation import deterministic_policy, draws_restarter, eval_due, evaluate, first_done
from shared.service import Log, MessageGuard, StopFlag
from shared.video import camera_frame
from shared.weights import WeightsSubscriber
from shared.writes import WriteFailures
from shared.zenoh_session import ServiceArgs

BLOCK = zenoh.CongestionControl.BLOCK
DRAWS_FILE = "draws.pt"


class _Stopped(Exception):
    """The service was told to stop in the middle of an evaluation."""


class SpreadFrames:
    """At most 2n + 1 frames of an episode of unknown length, spread over it: every stride-th one
    (the stride doubling, and every other kept frame dropped, whenever 2n are held) and the newest.
    The autoencoder's view shows n of them; holding every frame of a long episode at a large image
    size would take far more memory than the view needs."""

    def __init__(self, n: int) -> None:
        self.n, self.stride, self.seen = max(1, n), 1, 0
        self.kept: list[np.ndarray] = []
        self.newest: np.ndarray | None = None

    def append(self, frame: np.ndarray) -> None:
        if self.seen % self.stride == 0:
            self.kept.append(frame)
            if len(self.kept) > 2 * self.n:
                self.kept, self.stride = self.kept[::2], self.stride * 2
            self.newest = None
        else:
            self.newest = frame
        self.seen += 1

    def __iter__(self) -> Iterator[np.ndarray]:
        yield from self.kept
        if self.newest is not None:
            yield self.newest

    def __len__(self) -> int:
        return len(self.kept) + (self.newest is not None)


@dataclass
class EvaluatorArgs(ServiceArgs):
    """The evaluator: every eval_every global env steps, deterministic episodes with the newest weights."""

    eval_device: str = "cpu"
    threads: int = 1
    data: Path | None = field(default_factory=lambda: Path(os.environ["NASA_DATA"])
                              if os.environ.get("NASA_DATA") else None)
    """Run folder for the autoencoder's view and videos (env NASA_DATA; none: no pictures)."""
    video_every: int = 5
    """An MP4 of the first evaluation episode every N evaluations (0: none), counted in steps
    (N x eval_every) from the newest video in the run folder."""
    view_frames: int = 8
    """Frames in the autoencoder's view."""
    bridge: str = ""
    """Evaluate through the robot bridge of this id (a gripper task) instead of in this process."""


class EvaluatorService(MessageGuard):
    def __init__(self, args: EvaluatorArgs, session: zenoh.Session, stop: StopFlag,
                 run: run_config.RunConfig) -> None:
        c = self.config = run.config
        self.args, self.session, self.stop = args, session, stop
        self.keys = wire.Keys(args.run_id)
        self.log = Log("evaluator")
        torch.set_num_threads(max(1, args.threads))
        self.bridge: BridgePresence | None = None
        if args.bridge:
            envs.check_remote(c.env)
            self.bridge = BridgePresence(session, args.bridge)
        # A bridge's environment is made once the bridge is there (`_env_ready`).
        self.env = None if args.bridge else envs.from_config(c.env, c.seed + EVAL_SEED_OFFSET)
        self.restart_draws: Callable[[], None] = (
            (lambda: None) if self.env is None else draws_restarter(self.env, c.eval_same_episodes))
        spec = run.spec
        device = resolve_device(args.eval_device)
        self.agent = make_agent(c.algo, spec.obs_shape, spec.action_dim, c.agent, device,
                                updates=False)
        self.tap = AutoencoderTap(self.agent)
        self.weights = WeightsSubscriber(self.tap, self._invalid, steps=c.steps)  # type: ignore[arg-type]
        self.media = EvalMedia(args.data, args.view_frames) if args.data is not None else None
        self.writes = WriteFailures()  # refused writes, which each result carries to the learner
        self.evaluations = 0
        self.done = first_done(c)  # the newest step evaluated
        self._kept: tuple | None = None  # what `pictures` needs of the evaluation just played
        self._epoch: int | None = None  # the learner's incarnation whose weights it holds
        self._held_by: str | None = None  # the other client holding the bridge's gripper, once said
        self._policy = deterministic_policy(self.agent)
        # Where the evaluation draws stood after the last evaluation, so a restarted evaluator plays
        # the episodes an uninterrupted one would (no run folder: they start from the seed again).
        self.draws_file = Path(args.data) / "evaluator" / DRAWS_FILE if args.data else None
        self._restore_draws()

    def due(self) -> int | None:
        """The eval step to evaluate now (the newest multiple of eval_every the learner's weights
        were sent at), or None."""
        self.weights.maybe_load()
        if self.weights.version is None:
            return None
        if self.weights.epoch != self._epoch:
            if self._epoch is not None:
                # A restarted learner: the result of the step last evaluated may have gone out while
                # it was down. Evaluate the newest step again; one it holds already is not recorded twice.
                self.done = first_done(self.config)
            self._epoch = self.weights.epoch
        return eval_due(self.weights.env_steps, self.config, self.done)

    def _env_ready(self) -> bool:
        """Whether there is an environment to evaluate on; through a bridge, waits for it."""
        if self.env is not None:
            return True
        assert self.bridge is not None
        if not self.bridge.wait(lambda: bool(self.stop)):
            return False
        try:
            self.env = envs.source_for(self.config.env.task).make_remote(
                self.config.env, self.session, self.args.bridge, client_name("evaluator", self.args.run_id))
            self.restart_draws = draws_restarter(self.env, self.config.eval_same_episodes)
        except envs.EnvUnavailable as err:
            self.log.every("bridge", 10.0, f"waiting for bridge {self.args.bridge}: {err}")
            return False
        return True

    def evaluate(self, target: int) -> wire.EvalResult | None:
        """The evaluation's episodes; the first one's frames (and camera, for a video) are kept
        for the pictures (`pictures`, made after the result is out). None: the bridge abandoned it
        (played again when it is back), an episode failed (skipped: the same weights would fail
        the same way), or the service was told to stop (within an env step: nothing of the
        evaluation is kept, and a restarted evaluator plays it again from the same draws)."""
        self._kept = None
        if not self._env_ready():
            return None
        version = self.weights.version or 0
        video = self.video_due(target)
        try:
            self.restart_draws()
            first, obs, cameras = self._first_episode(keep=self.media is not None, video=video)
            returns = [first, *evaluate(self.agent, self.env, self.config.eval_episodes - 1, self._act)]
        except _Stopped:
            self.log(f"step {target}: evaluation stopped unfinished ({self.stop.reason}); no result")
            return None
        except envs.EnvUnavailable as err:  # a bridge gone or refusing: no partial result
            holder = err.holder if isinstance(err, BridgeHeld) else None
            if holder is None or holder != self._held_by:  # a holder once, not at every retry
                self.log(f"step {target}: evaluation abandoned, played again when the bridge is back: {err}")
            self._held_by = holder
            if self.bridge is not None:
                self.env = None  # made again once the bridge is there
            self.stop.wait(1.0)
            return None
        except envs.EnvFault as err:  # a diverged simulation, a policy acting NaN: no row, no crash loop
            self.done = target
            self.log(f"step {target}: evaluation failed, no result for this step: {err}")
            return None
        self.done, self.evaluations = target, self.evaluations + 1
        self._held_by = None
        self._save_draws()
        self._kept = (obs, cameras, first, video, version)
        return self.with_writes(wire.EvalResult(target, version, [float(r) for r in returns]))

    def with_writes(self, result: wire.EvalResult) -> wire.EvalResult:
        """`result` carrying this evaluator's refused writes as they stand now."""
        w = self.writes.snapshot()
        return dataclasses.replace(result, write_failures=w["failed"], writes_failing=w["failing"],
                                   write_error=w["last_error"])

    def video_due(self, target: int) -> bool:
        """Whether the evaluation of step `target` gets a video: the first one, then one every
        video_every evaluations' worth of steps after the newest video listed in media.json, so a
        restarted evaluator goes on with the cadence rather than start it again."""
        if self.media is None or self.args.video_every <= 0:
            return False
        newest = self.media.newest_video_step()
        return newest is None or target - newest >= self.args.video_every * self.config.eval_every

    def _act(self, obs: np.ndarray) -> np.ndarray:
        """The deterministic policy's action; _Stopped once the service is told to stop."""
        if self.stop:
            raise _Stopped
        return self._policy(obs)

    def pictures(self, target: int) -> None:
        """The autoencoder's view and the video of the evaluation just published. They are extras:
        a full disk or an unwritable folder loses them (said once a minute), never the result."""
        if self.media is None or not self._kept or not self._kept[0]:
            return
        if self.stop:  # the result is out; a video's encoding would outlast a container's stop
            self.log(f"step {target}: stopping ({self.stop.reason}), its pictures are not made")
            self._kept = None
            return
        obs, cameras, first, video, version = self._kept
        self._kept = None
        scalars = self.media.scalars
        refused = scalars.refused
        try:
            autoencoder, frames = self.tap.autoencoder, np.stack(obs)
            if autoencoder is not None:
                self.media.autoencoder_view(autoencoder, frames, target, version)
            if video:
                path = self.media.video(autoencoder, frames, cameras, target, first)
                self.log(f"step {target}: video {path}")
        except OSError as err:
            self.writes.failed("tensorboard" if scalars.refused > refused else "media", err)
            self.log.every("media", 60.0, f"step {target}: pictures not written: {err}")
            return
        self.writes.ok("media")
        if not scalars.refusing:
            self.writes.ok("tensorboard")

    def _restore_draws(self) -> None:
        if self.env is None or self.draws_file is None or not self.draws_file.exists():
            return  # through a bridge the draws live in the bridge
        try:
            self.env.set_rng_state(checkpoint.load(self.draws_file)["draws"])
        except (checkpoint.CheckpointError, OSError, KeyError, TypeError, ValueError) as err:
            self.log(f"{self.draws_file} cannot be read ({err}): evaluation draws start from the seed")

    def _save_draws(self) -> None:
        if self.env is None or self.draws_file is None:
            return
        try:
            checkpoint.save(self.draws_file, {"draws": self.env.rng_state()})
        except (OSError, RuntimeError) as err:  # a full disk: only a restart's episodes would differ
            self.writes.failed("draws", err)
            self.log.every("draws", 60.0, f"evaluation draws not saved: {err}")
        else:
            self.writes.ok("draws")

    def _first_episode(self, keep: bool, video: bool) -> tuple[float, list[np.ndarray], list]:
        """One deterministic episode (as shared.evaluation's), keeping its observations if asked:
        each of them for a video, else the few the autoencoder's view spreads over the episode."""
        obs = [] if video else SpreadFrames(self.args.view_frames)
        cameras: list = []

        def act(o: np.ndarray) -> np.ndarray:
            if keep:
                obs.append(o)
            if video:
                cameras.append(camera_frame(self.env))
            return self._act(o)

        return EnvLoop(self.env).run_episode(act), list(obs), cameras

    def evaluate_and_send(self, target: int) -> None:
        """Step `target`'s evaluation: its result out to the learner, then its pictures."""
        if (msg := self.evaluate(target)) is None:
            return

        def put(m: wire.EvalResult) -> None:
            self.session.put(self.keys.eval_result, wire.encode(m), congestion_control=BLOCK)

        put(msg)
        self.log(f"step {target} (policy {msg.policy_version}): mean {np.mean(msg.returns):.1f}")
        self.pictures(target)
        if (again := self.with_writes(msg)) != msg:
            # The pictures come after the result: what they met goes out now, not with the next
            # result. The learner records a step once, so only the counts are new to it.
            put(again)

    def run(self) -> None:
        s, k, c = self.session, self.keys, self.config
        if not faults.claim_run_role(s, k, "evaluator", self.stop, self.log):
            return
        with (
            self.weights.subscribe(s, k.eval_weights, k.eval_weights_latest),
            s.declare_subscriber(k.stop, self._on_stop),
            s.liveliness().declare_token(k.alive("evaluator", 0)),
            self.bridge if self.bridge is not None else contextlib.nullcontext(),
        ):
            where = f" through bridge {self.args.bridge}" if self.args.bridge else ""
            self.log(f"evaluating every {c.eval_every} env steps, {c.eval_episodes} episodes{where}")
            while not self.stop.wait(0.1):
                if (target := self.due()) is not None:
                    self.evaluate_and_send(target)
            self.log(f"stopping ({self.stop.reason})")
        if self.media is not None:
            try:
                self.media.close()
            except OSError as err:  # TensorBoard's last points, refused at the end: nothing to retry
                self.log(f"TensorBoard's last points not written: {err}")


def main(argv: list[str] | None = None) -> None:
    from shared.service import run_service

    def run(args: EvaluatorArgs, session: zenoh.Session, stop: StopFlag) -> None:
        # The run folder's media are this evaluator's alone; no folder: nothing to lock.
        with faults.lock_service(args.data, "evaluator") if args.data else contextlib.nullcontext():
            run = run_config.join(args.config, session, wire.Keys(args.run_id), stop)
            EvaluatorService(args, session, stop, run).run()

    run_service(EvaluatorArgs, argv, "python -m services.evaluator", run, check_args)


def check_args(args: EvaluatorArgs) -> None:
    """The evaluator's flags that its parser cannot check (ConfigError: exit 2 before it connects)."""
    from shared.config import ConfigError

    resolve_device(args.eval_device)
    if args.threads < 1:
        raise ConfigError(f"--threads {args.threads}: at least 1")
    if args.view_frames < 1:
        raise ConfigError(f"--view-frames {args.view_frames}: at least 1")
    if args.video_every < 0:
        raise ConfigError(f"--video-every {args.video_every}: 0 (no videos) or more")
