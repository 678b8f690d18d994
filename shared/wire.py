"""Everything that crosses Zenoh: key expressions, message types, and who talks on each.

Every key lives under the run prefix `nasa/<run_id>/`. The table below is the
whole wiring of the distributed system (Sample Factory's `connect_components`
in one place); services import their keys from `Keys` and encode/decode with
`encode()` / `decode()`, which check the schema version, the message type and
the type of every field. A message that fails validation raises `WireError`;
services count and log it and carry on.

| key (under nasa/<run>/)      | message          | publisher            | subscribers / queriers        |
|------------------------------|------------------|----------------------|-------------------------------|
| replay/insert/<actor_id>     | TransitionBatch  | actor (BLOCK)        | replay                        |
| replay/ack/<actor_id>        | InsertAck        | replay (BLOCK)       | actor <actor_id>              |
| replay/sample   (queryable)  | SampleRequest -> SampleReply | replay answers | learner (training batches) |
| replay/unscored (queryable)  | UnscoredRequest -> SampleReply | replay answers | learner (rows to score) |
| replay/intrinsic             | SetIntrinsic     | learner (BLOCK)      | replay                        |
| replay/config   (queryable)  | RunConfigMsg     | replay answers       | services joining the run      |
| replay/stats                 | ReplayStats      | replay (2 Hz)        | learner, actors               |
| learner/weights              | Weights          | learner (every K updates) | actors                   |
| learner/weights/latest (queryable) | Weights    | learner answers      | actors at start               |
| learner/eval_weights         | Weights (+ decoder) | learner (each eval step) | evaluator             |
| learner/eval_weights/latest (queryable) | Weights | learner answers    | evaluator at start            |
| actor/status/<actor_id>      | ActorStatus      | actor (1 Hz)         | learner                       |
| eval/result                  | EvalResult       | evaluator (BLOCK)    | learner (writes eval.csv)     |
| control/stop                 | Stop             | learner (run done), operator | every service         |
| alive/<role>/<id>[/<inc>]    | liveliness token | every service        | learner; each actor, its id's |

`routes()` holds the same wiring as data (who puts, answers or declares on each key, and who
listens): the router's access-control list (shared/zenoh_auth.py) is made from it.

Frames travel once: an actor sends each newly rendered frame (3, H, W) once,
never stacks; a batch's frames are delta-coded to the previous frame of the
batch and zstd-compressed together (`encode_frames`). Sample replies carry each
transition's k+1 frame window (obs = window[:3k], next_obs = window[3:]), a
quarter smaller than obs and next_obs for k = 3.
"""

from __future__ import annotations

import dataclasses
import math
import re
import time
import types
import typing
from dataclasses import dataclass, field
from typing import Any, ClassVar, TypeVar

import msgpack
import numpy as np
import zstandard as zstd

from shared.envs import ACTION_BOUND

# 2: policy weights' fc layers index conv features in (h, w, c) order; 3: unscored rows on their own
# key (UnscoredRequest), InsertAck and TransitionBatch lose the sequence numbers nothing read.
# A field added with a default (ReplayStats.write_error, ActorStatus.fault, EvalResult.write_failures,
# InsertAck.refused, ActorStatus.refused, BridgeEStop.request, TransitionBatch.launch, InsertAck.launch,
# BridgeEStopAck.stand_in, BridgeReset.pid, BridgeStep.pid) keeps the version: a receiver fills in
# the default where a sender has not the field, and ignores fields it does not know, so either side
# of a rolling upgrade reads the other's messages.
SCHEMA_VERSION = 3
PREFIX = "nasa"
_EPOCH_2025 = 1_735_689_600.0


def restart_stamp(per_second: int, bits: int) -> int:
    """Time since 2025-01-01 in 1/per_second s, mod 2**bits: grows across process restarts, so
    it orders an actor's incarnations and a learner's weight epochs."""
    return int((time.time() - _EPOCH_2025) * per_second) % 2**bits


class WireError(ValueError):
    """A message that does not follow the schema (wrong version, type or field)."""


_RUN_ID = re.compile(r"^[A-Za-z0-9_.\-]+$")


def check_run_id(run_id: str) -> str:
    if not _RUN_ID.match(run_id):
        raise ValueError(f"run id {run_id!r} may hold only letters, digits, '_', '.', '-'")
    return run_id


ANY = "*"
"""A run or bridge id that stands for every one, in key expressions that match every run's (the ACL's)."""


class Keys:
    """The key expressions of one run (of every run for `Keys(ANY, wildcard=True)`)."""

    def __init__(self, run_id: str, *, wildcard: bool = False) -> None:
        self.run_id = run_id if wildcard and run_id == ANY else check_run_id(run_id)
        p = f"{PREFIX}/{run_id}"
        self.prefix = p
        self.insert_all = f"{p}/replay/insert/*"
        self.sample = f"{p}/replay/sample"
        self.unscored = f"{p}/replay/unscored"
        self.intrinsic = f"{p}/replay/intrinsic"
        self.config = f"{p}/replay/config"
        self.replay_stats = f"{p}/replay/stats"
        self.weights = f"{p}/learner/weights"
        self.weights_latest = f"{p}/learner/weights/latest"
        self.eval_weights = f"{p}/learner/eval_weights"
        self.eval_weights_latest = f"{p}/learner/eval_weights/latest"
        self.actor_status_all = f"{p}/actor/status/*"
        self.eval_result = f"{p}/eval/result"
        self.stop = f"{p}/control/stop"
        self.alive_all = f"{p}/alive/**"
        self.alive_actors = f"{p}/alive/actor/**"
        self.alive_evaluators = f"{p}/alive/evaluator/**"

    def insert(self, actor_id: int | str) -> str:
        return f"{self.prefix}/replay/insert/{actor_id}"

    def ack(self, actor_id: int | str) -> str:
        return f"{self.prefix}/replay/ack/{actor_id}"

    def actor_status(self, actor_id: int | str) -> str:
        return f"{self.prefix}/actor/status/{actor_id}"

    def alive(self, role: str, ident: str | int, incarnation: int | None = None) -> str:
        tail = f"/{incarnation}" if incarnation is not None else ""
        return f"{self.prefix}/alive/{role}/{ident}{tail}"

    def parse_alive(self, key: str) -> tuple[str, str, int | None]:
        """(role, id, incarnation or None) of a liveliness key."""
        parts = key[len(self.prefix) + len("/alive/") :].split("/")
        if len(parts) not in (2, 3) or not key.startswith(f"{self.prefix}/alive/"):
            raise WireError(f"not a liveliness key of run {self.run_id}: {key!r}")
        return parts[0], parts[1], int(parts[2]) if len(parts) == 3 else None


# -- messages ---------------------------------------------------------------------


@dataclass
class Message:
    TYPE: ClassVar[str] = ""


@dataclass
class TransitionBatch(Message):
    """Consecutive transitions of one episode of one actor incarnation.

    `start` is the episode step of the first transition; `first_frame` (the
    episode's reset frame) is present exactly when start == 0. Arrays travel as
    raw little-endian bytes: actions float32 (n, A), rewards/discounts float32
    (n,), lasts uint8 (n,), policy_versions int64 (n,); frames via encode_frames.
    """

    TYPE: ClassVar[str] = "transitions"
    actor_id: int
    incarnation: int
    episode: int
    start: int
    n: int
    frame_shape: list
    frames: bytes
    first_frame: bytes | None
    actions: bytes
    rewards: bytes
    discounts: bytes
    lasts: bytes
    policy_versions: bytes
    launch: int = 0
    """Drawn at random when the actor starts: two launches of one id that got the same incarnation
    (started on two hosts in the same tenth of a second) differ here. 0: an actor older than it."""


@dataclass
class InsertAck(Message):
    TYPE: ClassVar[str] = "insert_ack"
    actor_id: int
    incarnation: int
    num_inserted: int
    refused: str = ""
    """Why the batch was not stored; "": stored (an older replay never says otherwise)."""
    lasting: bool = False
    """The refusal holds for every later batch of this incarnation (an older incarnation of its id
    was superseded, an id the store cannot keep): its actor can only stop."""
    launch: int = 0
    """The batch's `launch`, so each of two launches that share an incarnation takes only its own."""


@dataclass
class SampleRequest(Message):
    """A uniform batch, paced by the replay's rate limiter (the replay waits up to wait_s)."""

    TYPE: ClassVar[str] = "sample_request"
    batch_size: int
    wait_s: float = 2.0
    sync_samples: int | None = None
    """Not a sample: the learner's update count at its start, so the rate limiter counts the samples
    the learner used and a restarted learner makes up the updates its checkpoint lost."""


@dataclass
class UnscoredRequest(Message):
    """Up to `limit` of the oldest unscored transitions with global index >= `after`, for
    collect-timing scoring: not a training sample, so not paced. The reply's num_inserted is
    read before the scan: every row in [after, num_inserted) not returned is scored or evicted."""

    TYPE: ClassVar[str] = "unscored_request"
    after: int
    limit: int


@dataclass
class SampleReply(Message):
    """ok=False: not ready within the request's wait (warm-up, rate limit); ask again."""

    TYPE: ClassVar[str] = "sample_reply"
    ok: bool
    reason: str
    num_inserted: int
    batch_size: int = 0
    window_shape: list = field(default_factory=list)
    window: bytes = b""
    action: bytes = b""
    reward: bytes = b""
    intrinsic: bytes = b""
    discount: bytes = b""
    index: bytes = b""
    policy_version: bytes = b""


@dataclass
class SetIntrinsic(Message):
    TYPE: ClassVar[str] = "set_intrinsic"
    index: bytes
    value: bytes


@dataclass
class ReplayStats(Message):
    TYPE: ClassVar[str] = "replay_stats"
    size: int
    bytes: int
    num_inserted: int
    inserts: int
    samples: int
    invalid: int
    dropped: int
    done: bool
    write_error: str = ""
    """Why the replay cannot write its log now ("" when it can): it accepts no inserts until it can."""


@dataclass
class Weights(Message):
    """Policy weights: name -> [dtype, shape, raw bytes]; version = the learner's update count.

    `epoch` is the learner process's start (ms since 2025): a learner resumed from
    a checkpoint may publish versions lower than ones already seen, and
    (epoch, version) still orders them.
    """

    TYPE: ClassVar[str] = "weights"
    epoch: int
    version: int
    env_steps: int
    tensors: dict


@dataclass
class ActorStatus(Message):
    TYPE: ClassVar[str] = "actor_status"
    actor_id: int
    incarnation: int
    env_steps: int
    episodes: int
    policy_version: int
    steps_per_s: float
    episode_returns: list
    """(return, length) of each episode finished since the previous status."""
    fault: str | None = None
    """The environment's fault state where it reports one (a robot bridge: ok, estop, overload,
    torque_off, held, bridge_lost, ...); None for environments without one (the suite's tasks)."""
    step_counts: list = field(default_factory=list)
    """This incarnation's env steps per bucket of STEP_SECONDS_BUCKETS, the last one slower than
    all (empty: not measured); with step_seconds, a Prometheus histogram's figures."""
    step_seconds: float = 0.0
    """This incarnation's total env step time."""
    refused: int = 0
    """This incarnation's batches the replay acknowledged without storing them (InsertAck.refused)."""


STEP_SECONDS_BUCKETS = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0)
"""Upper bounds of the env step time histogram's buckets (seconds): a suite task's step to a real
robot's (which the paper's budget puts under a second)."""
MAX_FAULT_TEXT = 64
MAX_WRITE_KINDS = 16


@dataclass
class EvalResult(Message):
    TYPE: ClassVar[str] = "eval_result"
    step: int
    policy_version: int
    returns: list
    write_failures: dict = field(default_factory=dict)
    """The evaluator's writes the disk refused since it started (pictures, TensorBoard, its draws),
    by kind; the learner shows them in /status `writes` (shared.writes.WriteFailures.report)."""
    writes_failing: list = field(default_factory=list)
    """The kinds of write_failures that fail still (none of theirs has succeeded since)."""
    write_error: str = ""
    """The last of those errors ("kind: error")."""


@dataclass
class RunConfigMsg(Message):
    """The run's resolved config, as the replay holds it (shared.run_config.RunConfig.to_dict())."""

    TYPE: ClassVar[str] = "run_config"
    run_config: dict
    digest: str


@dataclass
class Stop(Message):
    TYPE: ClassVar[str] = "stop"
    reason: str


MESSAGES: dict[str, type[Message]] = {
    cls.TYPE: cls
    for cls in (
        TransitionBatch, InsertAck, SampleRequest, UnscoredRequest, SampleReply, SetIntrinsic, ReplayStats,
        Weights, ActorStatus, EvalResult, RunConfigMsg, Stop,
    )
}

M = TypeVar("M", bound=Message)
_HINTS: dict[type, dict[str, Any]] = {}


def _allowed(hint: Any) -> tuple[type, ...]:
    if isinstance(hint, types.UnionType) or typing.get_origin(hint) is typing.Union:
        return tuple(t for h in typing.get_args(hint) for t in _allowed(h))
    if hint is type(None) or hint is None:
        return (type(None),)
    if hint is float:
        return (float, int)
    return (typing.get_origin(hint) or hint,)


def encode(msg: Message) -> bytes:
    body = {"v": SCHEMA_VERSION, "t": msg.TYPE}
    body.update({f.name: getattr(msg, f.name) for f in dataclasses.fields(msg)})
    return msgpack.packb(body, use_bin_type=True)


def decode(data: bytes | bytearray | memoryview, cls: type[M], bounds: Bounds | None = None) -> M:
    """Parse and validate one message of type `cls`: its schema, then its values (`CHECKS`, against
    what the receiver knows of the run, `bounds`); raises WireError on anything else."""
    try:
        body = msgpack.unpackb(data, raw=False, strict_map_key=False)
    except Exception as err:  # msgpack raises several unrelated types
        raise WireError(f"not msgpack: {err}") from err
    if not isinstance(body, dict):
        raise WireError(f"message is a {type(body).__name__}, not a map")
    if body.get("v") != SCHEMA_VERSION:
        raise WireError(f"schema version {body.get('v')!r}, this build speaks {SCHEMA_VERSION}")
    if body.get("t") != cls.TYPE:
        raise WireError(f"message type {body.get('t')!r}, expected {cls.TYPE!r}")
    hints = _HINTS.get(cls)
    if hints is None:
        hints = _HINTS[cls] = typing.get_type_hints(cls)
    kwargs = {}
    for f in dataclasses.fields(cls):
        if f.name not in body:
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise WireError(f"{cls.TYPE}: missing field {f.name!r}")
            continue
        value = body[f.name]
        allowed = _allowed(hints[f.name])
        if isinstance(value, bool) and bool not in allowed:
            raise WireError(f"{cls.TYPE}.{f.name}: bool where {allowed} expected")
        if not isinstance(value, allowed):
            raise WireError(f"{cls.TYPE}.{f.name}: {type(value).__name__} where {allowed} expected")
        kwargs[f.name] = _check_scalar(cls, f.name, value)
    msg = cls(**kwargs)
    check = CHECKS.get(cls)
    if check is not None:
        try:
            check(msg, bounds or Bounds())
        except WireError:
            raise
        except (ValueError, TypeError, OverflowError) as err:  # numpy on odd sizes or dtypes
            raise WireError(f"{cls.TYPE}: {err}") from err
    return msg


def _check_scalar(cls: type[Message], name: str, value: Any) -> Any:
    """Every message's ints are counts, ids or indices (>= 0, fit an int64 with room for arithmetic);
    every float is finite; strings are short."""
    if isinstance(value, int) and not isinstance(value, bool) and not 0 <= value < MAX_INT:
        raise WireError(f"{cls.TYPE}.{name}: {value} outside [0, 2**62)")
    if isinstance(value, float) and not math.isfinite(value):
        raise WireError(f"{cls.TYPE}.{name}: {value} is not finite")
    if isinstance(value, str) and len(value) > MAX_TEXT:
        raise WireError(f"{cls.TYPE}.{name}: text of {len(value)} characters")
    return value


# -- payload helpers ----------------------------------------------------------------

_ZC = zstd.ZstdCompressor(level=1, write_checksum=False)


def encode_frames(frames: np.ndarray) -> bytes:
    """(n, C, H, W) uint8 frames -> zstd of the first frame and wrapping deltas to the previous."""
    frames = np.ascontiguousarray(frames, dtype=np.uint8)
    deltas = frames.copy()
    deltas[1:] = np.subtract(frames[1:], frames[:-1], dtype=np.uint8)
    return _ZC.compress(deltas.tobytes())


def decode_frames(blob: bytes, n: int, shape: tuple[int, ...]) -> np.ndarray:
    size = n * math.prod(shape)
    try:
        # The decompressor sizes its output from the header's content size when it has one: a
        # corrupt header claiming a huge one would raise MemoryError before any check of it.
        declared = zstd.frame_content_size(blob)
        if declared not in (-1, size):
            raise WireError(f"frames declare {declared} bytes, expected {size} for {n} x {shape}")
        raw = zstd.ZstdDecompressor().decompress(blob, max_output_size=size)
    except zstd.ZstdError as err:
        raise WireError(f"frames do not decompress: {err}") from err
    if len(raw) != size:
        raise WireError(f"frames hold {len(raw)} bytes, expected {size} for {n} x {shape}")
    deltas = np.frombuffer(raw, np.uint8).reshape(n, *shape)
    return np.cumsum(deltas, axis=0, dtype=np.uint8)  # wrapping sums undo the deltas


def array(data: bytes, dtype: str | np.dtype, shape: tuple[int, ...]) -> np.ndarray:
    """A read-only array view of raw bytes, checking the length matches the shape."""
    try:
        dt = np.dtype(dtype).newbyteorder("<")
    except (TypeError, ValueError) as err:
        raise WireError(f"dtype {dtype!r}: {err}") from err
    expected = math.prod(shape) * dt.itemsize  # Python ints: a huge shape cannot wrap around
    if len(data) != expected:
        raise WireError(f"array of {len(data)} bytes, expected {expected} for {dtype} {shape}")
    return np.frombuffer(data, dt).reshape(shape)


def newer_weights(msg: Weights, held: tuple[int, int] | None) -> bool:
    """Whether weights `msg` are newer than the (epoch, version) a process holds."""
    return held is None or (msg.epoch, msg.version) >= held


def pack_tensors(state: dict) -> dict:
    """A dict of torch tensors -> name: [dtype, shape, bytes] (CPU, contiguous)."""
    out = {}
    for name, t in state.items():
        a = t.detach().cpu().contiguous().numpy()
        out[name] = [a.dtype.str, list(a.shape), a.tobytes()]
    return out


def unpack_tensors(packed: dict) -> dict:
    import torch

    out = {}
    for name, entry in packed.items():
        if not (isinstance(entry, list) and len(entry) == 3 and isinstance(entry[2], bytes)):
            raise WireError(f"tensor {name!r} is not [dtype, shape, bytes]")
        dtype, shape, data = entry
        a = array(data, dtype, tuple(shape))
        out[name] = torch.from_numpy(a.copy())
    return out


# -- value checks: one per message type, run by decode() ---------------------------------

MAX_INT = 2**62
MAX_TEXT = 4096
MAX_BATCH = 4096
MAX_LIST = 10_000
_FLOAT32_MAX = float(np.finfo(np.float32).max)
TENSOR_DTYPES = frozenset({"<f2", "<f4", "<f8", "|u1", "|i1", "<i2", "<i4", "<i8", "|b1"})


@dataclass(frozen=True)
class Bounds:
    """What a receiver knows of the run, for checking values (None: not known to it)."""

    frame_shape: tuple[int, ...] | None = None
    frame_stack: int | None = None
    action_dim: int | None = None
    max_abs_reward: float = 1e3
    """Rewards beyond this are refused: a huge finite reward overflows the critic's loss."""
    max_batch: int = MAX_BATCH
    steps: int | None = None
    """The run's step budget: a replay's count of stored transitions beyond it (and `STEP_SLACK`) is
    refused, as each receiver keeps the largest count it has seen, so one bad count would stay."""

    @classmethod
    def of(cls, spec: Any, max_abs_reward: float = 1e3, steps: int | None = None) -> Bounds:
        """The bounds of a run's EnvSpec (shared.envs) and step budget."""
        return cls(tuple(spec.frame_shape), spec.frame_stack, spec.action_dim, max_abs_reward, steps=steps)


STEP_SLACK = MAX_BATCH
"""How far past the step budget a count may go: the replay stores none past it, and the slack keeps
this check from being the tightest in the system."""


def _count(n: int, what: str, b: Bounds) -> None:
    _need(b.steps is None or n <= b.steps + STEP_SLACK, f"{what} {n} beyond the run's {b.steps} steps")


def _need(ok: bool, what: str) -> None:
    if not ok:
        raise WireError(what)


def _finite(a: np.ndarray, what: str, bound: float | None = None, nan_ok: bool = False) -> None:
    vals = a[~np.isnan(a)] if nan_ok else a
    _need(bool(np.isfinite(vals).all()), f"{what}: non-finite values")
    if bound is not None and vals.size:
        _need(float(np.abs(vals).max()) <= bound, f"{what}: values beyond +-{bound:g}")


def _shape(value: Any, what: str, dims: int | None = None) -> tuple[int, ...]:
    ok = isinstance(value, list) and len(value) <= 8 and all(
        isinstance(d, int) and not isinstance(d, bool) and 0 <= d <= 1 << 20 for d in value)
    _need(ok and (dims is None or len(value) == dims), f"{what}: shape {value!r}")
    return tuple(value)


def _steps(n: int, action_dim: int | None, b: Bounds, actions: bytes, rewards: bytes, discounts: bytes,
           versions: bytes) -> dict[str, np.ndarray]:
    """Per-transition arrays shared by TransitionBatch and SampleReply, checked."""
    a = action_dim if action_dim is not None else len(actions) // (4 * n)
    out = {
        "action": array(actions, "<f4", (n, a)),
        "reward": array(rewards, "<f4", (n,)),
        "discount": array(discounts, "<f4", (n,)),
        "policy_version": array(versions, "<i8", (n,)),
    }
    _need(a >= 1, "actions: empty")
    _finite(out["action"], "actions", ACTION_BOUND)
    _finite(out["reward"], "rewards", b.max_abs_reward)
    d = out["discount"]
    _need(bool(((d >= 0) & (d <= 1)).all()), "discounts outside [0, 1]")
    _need(bool((out["policy_version"] >= 0).all()), "negative policy versions")
    return out


def check_transitions(m: TransitionBatch, b: Bounds) -> None:
    _need(1 <= m.n <= b.max_batch, f"batch of {m.n} transitions")
    shape = _shape(m.frame_shape, "frame_shape", 3)
    _need(b.frame_shape is None or shape == tuple(b.frame_shape),
          f"frame shape {list(shape)}, this run has {b.frame_shape}")
    _need((m.first_frame is not None) == (m.start == 0), "first_frame must come exactly with step 0")
    arrays = _steps(m.n, b.action_dim, b, m.actions, m.rewards, m.discounts, m.policy_versions)
    lasts = array(m.lasts, "u1", (m.n,))
    _need(bool((lasts <= 1).all()), "lasts other than 0 and 1")
    arrays["last"] = lasts
    arrays["frames"] = decode_frames(m.frames, m.n, shape)
    if m.first_frame is not None:
        arrays["first_frame"] = decode_frames(m.first_frame, 1, shape)[0]
    m.arrays = arrays  # decoded once: the receiver stores these


def check_sample_request(m: SampleRequest, b: Bounds) -> None:
    _need(1 <= m.batch_size <= b.max_batch, f"batch_size {m.batch_size}")
    _need(0.0 <= m.wait_s <= 3600.0, f"wait_s {m.wait_s}")


def check_unscored_request(m: UnscoredRequest, b: Bounds) -> None:
    _need(1 <= m.limit <= b.max_batch, f"limit {m.limit}")


def check_sample_reply(m: SampleReply, b: Bounds) -> None:
    _count(m.num_inserted, "num_inserted", b)
    if not m.ok:
        return
    n = m.batch_size
    _need(1 <= n <= b.max_batch, f"batch_size {n}")
    shape = _shape(m.window_shape, "window_shape", 4)
    if b.frame_shape is not None and b.frame_stack is not None:
        c, h, w = b.frame_shape
        expected = (n, c * (b.frame_stack + 1), h, w)
        _need(shape == expected, f"window shape {shape}, expected {expected} for a batch of {n}")
    array(m.window, "u1", shape)
    _steps(n, b.action_dim, b, m.action, m.reward, m.discount, m.policy_version)
    _finite(array(m.intrinsic, "<f4", (n,)), "intrinsic", b.max_abs_reward, nan_ok=True)
    _need(bool((array(m.index, "<i8", (n,)) >= 0).all()), "negative indices")


def check_insert_ack(m: InsertAck, b: Bounds) -> None:
    _count(m.num_inserted, "num_inserted", b)


def check_replay_stats(m: ReplayStats, b: Bounds) -> None:
    _count(m.num_inserted, "num_inserted", b)


def check_set_intrinsic(m: SetIntrinsic, b: Bounds) -> None:
    n = len(m.index) // 8
    _need(1 <= n <= b.max_batch, f"{n} scores")
    index = array(m.index, "<i8", (n,))
    _need(bool(((index >= 0) & (index < MAX_INT)).all()), "indices outside [0, 2**62)")
    _finite(array(m.value, "<f4", (n,)), "scores", b.max_abs_reward)


def check_weights(m: Weights, b: Bounds) -> None:
    _count(m.env_steps, "env_steps", b)
    _need(len(m.tensors) <= 1000, f"{len(m.tensors)} tensors")
    for name, entry in m.tensors.items():
        _need(isinstance(name, str) and len(name) <= 256, f"tensor name {name!r}")
        _need(isinstance(entry, list) and len(entry) == 3 and isinstance(entry[2], bytes),
              f"tensor {name!r} is not [dtype, shape, bytes]")
        dtype, shape, data = entry
        _need(dtype in TENSOR_DTYPES, f"tensor {name!r}: dtype {dtype!r} not in {sorted(TENSOR_DTYPES)}")
        a = array(data, dtype, _shape(shape, f"tensor {name!r}"))
        if a.dtype.kind == "f":
            # A float64 value beyond float32's range becomes inf in the float32 parameters it loads into.
            _finite(a, f"tensor {name!r}", _FLOAT32_MAX)


def check_actor_status(m: ActorStatus, b: Bounds) -> None:
    _need(m.steps_per_s >= 0, f"steps_per_s {m.steps_per_s}")
    _need(len(m.episode_returns) <= MAX_LIST, f"{len(m.episode_returns)} episode returns")
    for e in m.episode_returns:
        ok = (isinstance(e, list) and len(e) == 2 and _is_number(e[0]) and abs(e[0]) <= 1e12
              and is_count(e[1]))
        _need(ok, f"episode return {e!r} is not [finite return, length]")
    _need(m.fault is None or len(m.fault) <= MAX_FAULT_TEXT, "fault: longer than a state name")
    counts = m.step_counts
    _need(not counts or len(counts) == len(STEP_SECONDS_BUCKETS) + 1,
          f"step_counts: {len(counts)} buckets, expected {len(STEP_SECONDS_BUCKETS) + 1}")
    _need(all(is_count(n) for n in counts),
          "step_counts: not counts")
    _need(m.step_seconds >= 0, f"step_seconds {m.step_seconds}")


def check_eval_result(m: EvalResult, b: Bounds) -> None:
    _need(1 <= len(m.returns) <= MAX_LIST, f"{len(m.returns)} returns")
    _need(all(_is_number(r) and abs(r) <= 1e12 for r in m.returns), "returns must be finite numbers")
    # A few kinds of write, each a short name: they become /status keys and /metrics labels.
    kinds = m.write_failures
    _need(len(kinds) <= MAX_WRITE_KINDS, f"write_failures: {len(kinds)} kinds")
    _need(all(isinstance(k, str) and 0 < len(k) <= MAX_FAULT_TEXT for k in kinds),
          "write_failures: kinds must be short names")
    _need(all(is_count(n) for n in kinds.values()),
          "write_failures: not counts")
    _need(all(isinstance(k, str) and k in kinds for k in m.writes_failing),
          "writes_failing: a kind without a count in write_failures")


def _is_number(x: Any) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)


def is_count(x: Any) -> bool:
    """Whether a raw field holds an int the wire takes as a count, id or index: [0, 2**62)."""
    return isinstance(x, int) and not isinstance(x, bool) and 0 <= x < MAX_INT


CHECKS: dict[type[Message], Any] = {
    TransitionBatch: check_transitions,
    SampleRequest: check_sample_request,
    UnscoredRequest: check_unscored_request,
    SampleReply: check_sample_reply,
    InsertAck: check_insert_ack,
    ReplayStats: check_replay_stats,
    SetIntrinsic: check_set_intrinsic,
    Weights: check_weights,
    ActorStatus: check_actor_status,
    EvalResult: check_eval_result,
}
"""The value checks of each message type (the others' fields are checked by type and range alone)."""


# -- robot bridge ---------------------------------------------------------------------
#
# | key (under nasa/bridge/<bridge_id>/) | message                    | who                          |
# |--------------------------------------|----------------------------|------------------------------|
# | spec      (queryable)                | BridgeSpecRequest -> BridgeSpec | bridge answers; actor    |
# | reset     (queryable)                | BridgeReset -> BridgeReply | bridge answers; its actor    |
# | step      (queryable)                | BridgeStep -> BridgeReply  | bridge answers; its actor    |
# | estop                                | BridgeEStop                | operator, `nasa`, tests      |
# | estop_ack                            | BridgeEStopAck             | bridge; the operator waiting |
# | alive     (liveliness token)         |                            | bridge; actors watch it      |
#
# A bridge owns one gripper (or its stand-in), so its keys name the bridge, not a run.


class BridgeKeys:
    """The key expressions of one robot bridge."""

    def __init__(self, bridge_id: str | int, *, wildcard: bool = False) -> None:
        ident = ANY if wildcard and bridge_id == ANY else check_run_id(str(bridge_id))
        p = f"{PREFIX}/bridge/{ident}"
        self.prefix = p
        self.spec = f"{p}/spec"
        self.reset = f"{p}/reset"
        self.step = f"{p}/step"
        self.estop = f"{p}/estop"
        self.estop_ack = f"{p}/estop_ack"
        self.alive = f"{p}/alive"


@dataclass
class BridgeSpecRequest(Message):
    TYPE: ClassVar[str] = "bridge_spec_request"


@dataclass
class BridgeSpec(Message):
    TYPE: ClassVar[str] = "bridge_spec"
    task: str
    action_dim: int
    frame_shape: list


@dataclass
class BridgeReset(Message):
    """`client`: who asks (`services.robot_bridge.client.client_name`; an older client sends its
    task's name): the bridge serves one client at a time. `pid`: the asking process, named in the
    bridge's refusals to other clients (0: not sent). `rewind`: before this reset, the bridge puts
    its draws (targets, reset angles) back where they stood when it started, so an evaluation can
    play the same episodes each time."""

    TYPE: ClassVar[str] = "bridge_reset"
    client: str
    rewind: bool = False
    pid: int = 0


@dataclass
class BridgeStep(Message):
    """`action` is float32 (action_dim,) raw bytes; `episode`/`step` let the bridge refuse a stale step;
    `client` and `pid` as in BridgeReset."""

    TYPE: ClassVar[str] = "bridge_step"
    client: str
    episode: int
    step: int
    action: bytes
    pid: int = 0


@dataclass
class BridgeReply(Message):
    """One raw (unstacked) frame, uint8 (C, H, W) bytes, and the step's outcome.

    ok=False: the bridge could not reset (e-stop, fault, waiting for an operator, another client
    holding the gripper: `info["holder"]` names it); `reason` says why and the client retries later.
    `info` holds the valve and target angles, servo positions, loads and error bits, the step
    latency and the safety state.
    """

    TYPE: ClassVar[str] = "bridge_reply"
    ok: bool
    reason: str
    episode: int
    step: int
    frame_shape: list
    frame: bytes
    reward: float
    discount: float
    first: bool
    last: bool
    info: dict


@dataclass
class BridgeEStop(Message):
    """engage=True: e-stop (torque off, refuse steps); engage=False: the operator's re-arm."""

    TYPE: ClassVar[str] = "bridge_estop"
    engage: bool
    reason: str
    request: str = ""
    """The sender's own tag, echoed in the bridge's BridgeEStopAck so it knows the answer is to it."""


@dataclass
class BridgeEStopAck(Message):
    """A bridge's answer to a BridgeEStop, sent once it holds: for an e-stop, after the torque-off
    went to every servo (`unreached`: those that did not answer it) or the stand-in's stop is
    latched; for a re-arm, once the stop is released (the homing follows)."""

    TYPE: ClassVar[str] = "bridge_estop_ack"
    request: str
    engage: bool
    state: str
    """The bridge's safety state after it (`estop`; `recovering` after a re-arm)."""
    unreached: list
    bridge: str
    """Which process answered: its host and pid."""
    stand_in: bool = False
    """The bridge serves the stand-in, which has no servos: its e-stop is a latched stop, not a
    torque-off (an older bridge never says so)."""


MESSAGES.update({
    cls.TYPE: cls
    for cls in (BridgeSpecRequest, BridgeSpec, BridgeReset, BridgeStep, BridgeReply, BridgeEStop,
                BridgeEStopAck)
})

MAX_SERVO_ID = 252
"""Dynamixel Protocol 2.0's highest servo id (253 and up are reserved or broadcast)."""


def check_bridge_estop_ack(m: BridgeEStopAck, b: Bounds) -> None:
    # The operator is told these: a state is a short name, and `unreached` names servos.
    _need(0 < len(m.state) <= MAX_FAULT_TEXT, "state: not a state name")
    _need(len(m.unreached) <= MAX_SERVO_ID + 1 and all(
        isinstance(i, int) and not isinstance(i, bool) and 0 <= i <= MAX_SERVO_ID for i in m.unreached),
        f"unreached: not servo ids (0..{MAX_SERVO_ID})")


CHECKS[BridgeEStopAck] = check_bridge_estop_ack


# -- who may do what on each key (the access-control list is made from this) -----------------------

PUT, QUERY, TOKEN = "put", "query", "token"
ROLES = ("actor", "replay", "learner", "evaluator", "bridge", "operator")
"""The roles a process connects to the router as; `operator` is a person's or launcher's credential."""


@dataclass(frozen=True)
class Route:
    """One key expression and who uses it. `kind` PUT: `senders` put, `receivers` subscribe.
    QUERY: `senders` answer (a queryable), `receivers` query. TOKEN: `senders` declare a liveliness
    token, `receivers` watch or query it."""

    key: str
    kind: str
    senders: tuple[str, ...]
    receivers: tuple[str, ...]


def routes(run_id: str = ANY, bridge_id: str = ANY) -> tuple[Route, ...]:
    """The wiring of the table above, from `Keys` and `BridgeKeys` (per-id keys for every id)."""
    k, b = Keys(run_id, wildcard=True), BridgeKeys(bridge_id, wildcard=True)
    services = ("replay", "learner", "actor", "evaluator")
    return (
        Route(k.insert(ANY), PUT, ("actor",), ("replay",)),
        Route(k.ack(ANY), PUT, ("replay",), ("actor",)),
        Route(k.sample, QUERY, ("replay",), ("learner",)),
        Route(k.unscored, QUERY, ("replay",), ("learner",)),
        Route(k.intrinsic, PUT, ("learner",), ("replay",)),
        Route(k.config, QUERY, ("replay",), ("learner", "actor", "evaluator")),
        Route(k.replay_stats, PUT, ("replay",), ("learner", "actor")),
        Route(k.weights, PUT, ("learner",), ("actor",)),
        Route(k.weights_latest, QUERY, ("learner",), ("actor",)),
        Route(k.eval_weights, PUT, ("learner",), ("evaluator",)),
        Route(k.eval_weights_latest, QUERY, ("learner",), ("evaluator",)),
        Route(k.actor_status(ANY), PUT, ("actor",), ("learner",)),
        Route(k.eval_result, PUT, ("evaluator",), ("learner",)),
        # The learner ends a finished run; an operator may stop one. No other role can.
        Route(k.stop, PUT, ("learner", "operator"), services),
        # An actor watches its own id's tokens: a newer incarnation of it takes the id over.
        Route(k.alive("actor", "**"), TOKEN, ("actor",), ("learner", "actor")),
        # The replay's own container healthcheck asks for its token, under the replay's credentials.
        Route(k.alive("replay", "**"), TOKEN, ("replay",), ("actor", "replay")),
        # A replay, learner or evaluator starting looks for one already serving the run.
        Route(k.alive("learner", "**"), TOKEN, ("learner",), ("learner",)),
        # The learner waits for the last evaluation only while an evaluator is alive.
        Route(k.alive("evaluator", "**"), TOKEN, ("evaluator",), ("learner", "evaluator")),
        # `nasa up --bridge stand-in|emulator` gives the evaluator a bridge of its own to play on.
        Route(b.spec, QUERY, ("bridge",), ("actor", "evaluator")),
        Route(b.reset, QUERY, ("bridge",), ("actor", "evaluator")),
        Route(b.step, QUERY, ("bridge",), ("actor", "evaluator")),
        Route(b.estop, PUT, ("operator",), ("bridge",)),
        # Only the bridge confirms an e-stop, and only the operator who sent it waits to hear it.
        Route(b.estop_ack, PUT, ("bridge",), ("operator",)),
        # A bridge starting looks for one already serving its id.
        Route(b.alive, TOKEN, ("bridge",), ("actor", "evaluator", "bridge")),
    )
