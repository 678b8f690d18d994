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
| replay/sample   (queryable)  | SampleRequest -> SampleReply | replay answers | learner (batches; unscored) |
| replay/intrinsic             | SetIntrinsic     | learner (BLOCK)      | replay                        |
| replay/stats                 | ReplayStats      | replay (2 Hz)        | learner, actors, evaluator    |
| learner/weights              | Weights          | learner (every K updates) | actors, evaluator        |
| learner/weights/latest (queryable) | Weights    | learner answers      | actors, evaluator at start    |
| actor/status/<actor_id>      | ActorStatus      | actor (1 Hz)         | learner                       |
| eval/result                  | EvalResult       | evaluator (BLOCK)    | learner (writes eval.csv)     |
| control/stop                 | Stop             | learner (run done), nasa up | every service          |
| alive/<role>/<id>[/<inc>]    | liveliness token | every service        | learner (actors' alive flag)  |

Frames travel once: an actor sends each newly rendered frame (3, H, W) once,
never stacks; a batch's frames are delta-coded to the previous frame of the
batch and zstd-compressed together (`encode_frames`). Sample replies carry each
transition's k+1 frame window (obs = window[:3k], next_obs = window[3:]), a
quarter smaller than obs and next_obs for k = 3.
"""

from __future__ import annotations

import dataclasses
import re
import time
import types
import typing
from dataclasses import dataclass, field
from typing import Any, ClassVar, TypeVar

import msgpack
import numpy as np
import zstandard as zstd

SCHEMA_VERSION = 2  # 2: policy weights' fc layers index conv features in (h, w, c) order
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


class Keys:
    """The key expressions of one run."""

    def __init__(self, run_id: str) -> None:
        self.run_id = check_run_id(run_id)
        p = f"{PREFIX}/{run_id}"
        self.prefix = p
        self.insert_all = f"{p}/replay/insert/*"
        self.sample = f"{p}/replay/sample"
        self.intrinsic = f"{p}/replay/intrinsic"
        self.replay_stats = f"{p}/replay/stats"
        self.weights = f"{p}/learner/weights"
        self.weights_latest = f"{p}/learner/weights/latest"
        self.actor_status_all = f"{p}/actor/status/*"
        self.eval_result = f"{p}/eval/result"
        self.stop = f"{p}/control/stop"
        self.alive_all = f"{p}/alive/**"
        self.alive_actors = f"{p}/alive/actor/**"

    def insert(self, actor_id: int) -> str:
        return f"{self.prefix}/replay/insert/{actor_id}"

    def ack(self, actor_id: int) -> str:
        return f"{self.prefix}/replay/ack/{actor_id}"

    def actor_status(self, actor_id: int) -> str:
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
    seq: int
    n: int
    frame_shape: list
    frames: bytes
    first_frame: bytes | None
    actions: bytes
    rewards: bytes
    discounts: bytes
    lasts: bytes
    policy_versions: bytes


@dataclass
class InsertAck(Message):
    TYPE: ClassVar[str] = "insert_ack"
    actor_id: int
    incarnation: int
    seq: int
    accepted: int
    num_inserted: int


@dataclass
class SampleRequest(Message):
    """A uniform batch (paced by the replay's rate limiter); or, with unscored_after >= 0, up
    to batch_size of the oldest unscored transitions from that global index on (not paced)."""

    TYPE: ClassVar[str] = "sample_request"
    batch_size: int
    wait_s: float = 2.0
    unscored_after: int = -1


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


@dataclass
class EvalResult(Message):
    TYPE: ClassVar[str] = "eval_result"
    step: int
    policy_version: int
    returns: list


@dataclass
class Stop(Message):
    TYPE: ClassVar[str] = "stop"
    reason: str


MESSAGES: dict[str, type[Message]] = {
    cls.TYPE: cls
    for cls in (
        TransitionBatch, InsertAck, SampleRequest, SampleReply, SetIntrinsic, ReplayStats,
        Weights, ActorStatus, EvalResult, Stop,
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


def decode(data: bytes | bytearray | memoryview, cls: type[M]) -> M:
    """Parse and validate one message of type `cls`; raises WireError on anything else."""
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
        kwargs[f.name] = value
    return cls(**kwargs)


# -- payload helpers ----------------------------------------------------------------

_ZC = zstd.ZstdCompressor(level=1, write_checksum=False)


def encode_frames(frames: np.ndarray) -> bytes:
    """(n, C, H, W) uint8 frames -> zstd of the first frame and wrapping deltas to the previous."""
    frames = np.ascontiguousarray(frames, dtype=np.uint8)
    deltas = frames.copy()
    deltas[1:] = np.subtract(frames[1:], frames[:-1], dtype=np.uint8)
    return _ZC.compress(deltas.tobytes())


def decode_frames(blob: bytes, n: int, shape: tuple[int, ...]) -> np.ndarray:
    size = n * int(np.prod(shape))
    try:
        raw = zstd.ZstdDecompressor().decompress(blob, max_output_size=size)
    except zstd.ZstdError as err:
        raise WireError(f"frames do not decompress: {err}") from err
    if len(raw) != size:
        raise WireError(f"frames hold {len(raw)} bytes, expected {size} for {n} x {shape}")
    deltas = np.frombuffer(raw, np.uint8).reshape(n, *shape)
    return np.cumsum(deltas, axis=0, dtype=np.uint8)  # wrapping sums undo the deltas


def array(data: bytes, dtype: str | np.dtype, shape: tuple[int, ...]) -> np.ndarray:
    """A read-only array view of raw bytes, checking the length matches the shape."""
    dt = np.dtype(dtype).newbyteorder("<")
    expected = int(np.prod(shape)) * dt.itemsize
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


# -- robot bridge ---------------------------------------------------------------------
#
# | key (under nasa/bridge/<bridge_id>/) | message                    | who                          |
# |--------------------------------------|----------------------------|------------------------------|
# | spec      (queryable)                | BridgeSpecRequest -> BridgeSpec | bridge answers; actor    |
# | reset     (queryable)                | BridgeReset -> BridgeReply | bridge answers; its actor    |
# | step      (queryable)                | BridgeStep -> BridgeReply  | bridge answers; its actor    |
# | estop                                | BridgeEStop                | operator, `nasa`, tests      |
# | alive     (liveliness token)         |                            | bridge; actors watch it      |
#
# A bridge owns one gripper (or its stand-in), so its keys name the bridge, not a run.


class BridgeKeys:
    """The key expressions of one robot bridge."""

    def __init__(self, bridge_id: str | int) -> None:
        ident = check_run_id(str(bridge_id))
        p = f"{PREFIX}/bridge/{ident}"
        self.prefix = p
        self.spec = f"{p}/spec"
        self.reset = f"{p}/reset"
        self.step = f"{p}/step"
        self.estop = f"{p}/estop"
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
    TYPE: ClassVar[str] = "bridge_reset"
    client: str


@dataclass
class BridgeStep(Message):
    """`action` is float32 (action_dim,) raw bytes; `episode`/`step` let the bridge refuse a stale step."""

    TYPE: ClassVar[str] = "bridge_step"
    client: str
    episode: int
    step: int
    action: bytes


@dataclass
class BridgeReply(Message):
    """One raw (unstacked) frame, uint8 (C, H, W) bytes, and the step's outcome.

    ok=False: the bridge could not reset (e-stop, fault, waiting for an operator); `reason` says
    why and the client retries later. `info` holds the valve and target angles, servo positions,
    loads and error bits, the step latency and the safety state.
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


MESSAGES.update({
    cls.TYPE: cls
    for cls in (BridgeSpecRequest, BridgeSpec, BridgeReset, BridgeStep, BridgeReply, BridgeEStop)
})
