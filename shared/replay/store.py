"""The replay store: each rendered frame stored once, compressed; stacks rebuilt at sample time.

Data model
- An episode is a reset frame plus one frame per transition. Its frames live in
  chunks of `chunk_len` consecutive frames (codec.py: keyframe + deltas to it).
  A chunk belongs to one episode, so no stack can mix episodes or incarnations.
- A transition stores small metadata and the k+1 frame references of its window
  (frames t-k+1 .. t+1 of its episode, clamped at 0, exactly as
  shared.envs.FrameStack stacks): obs = window[:k], next_obs = window[1:].
- Transitions live in a FIFO ring of `capacity`; the sampleable set is the
  contiguous global index range [head, num_inserted). A chunk is reference
  counted by the windows of live transitions, so when the first transitions of
  an episode are evicted, frames later transitions still need are kept, and
  uniform sampling over [head, num_inserted) stays exact (with or without
  replacement within a batch).

Durability (log.py): every mutation is one log record written before add()
returns, so an acknowledged add survives the death of the process; fsync
(power loss) runs every `fsync_interval_s` and on flush(). snapshot() compacts
the log; it holds the lock only to rotate the log and copy array metadata.
"""

from __future__ import annotations

import bisect
import math
import os
import struct
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from shared.envs import ACTION_BOUND
from shared.replay import log as rlog
from shared.replay.codec import FrameCodec

if TYPE_CHECKING:
    from shared.run_config import RunConfig

# Log record types. _CLOSE (an episode closed without its last step) is no longer written;
# logs that hold it still replay.
_BEGIN, _STEP, _INTRINSIC, _TRUNCATE, _CLOSE = 1, 2, 3, 4, 5
_BEGIN_S = struct.Struct("<qii")
_STEP_HEAD = struct.Struct("<qq")
_STEP_TAIL = struct.Struct("<fffBq")
_FLOAT32_MAX = float(np.finfo(np.float32).max)
ID_LIMIT = 2**31
"""Actor ids and incarnations are below this: the store keeps them as 32-bit integers."""
STOP_CHECK_EVERY = 256
"""Records (or snapshot chunks) read between two looks at a reopening's `stop`."""
SNAPSHOT_EVERY = 50_000
"""Transitions added between two compactions of a store's log (snapshot_if_due): the replay
service's default and nasa train's."""


class OpenStopped(Exception):
    """A store's reopening ended by its `stop` (a stop signal) before all of its log was read; its
    folder is as it was, and the next opening reads it all."""


class ActorRefused(ValueError):
    """Every episode of this actor incarnation is refused, now and later: it is older than one
    already seen for its id, or its id or incarnation does not fit the store's 32 bits."""


@dataclass
class _Chunk:
    episode_id: int
    blobs: list[bytes] = field(default_factory=list)
    refcount: int = 0  # live transitions whose window touches this chunk
    open: bool = True  # still receiving frames
    key: np.ndarray | None = None  # raw keyframe while open (None after reopen: decoded lazily)
    owned: list[int] = field(default_factory=list)  # global indices whose newest frame is here


@dataclass
class _Episode:
    actor_id: int
    incarnation: int
    chunk_ids: list[int] = field(default_factory=list)
    num_frames: int = 0
    open: bool = True
    live_chunks: int = 0


class ReplayStore:
    """Frame-deduplicated, compressed, durable FIFO replay of pixel transitions."""

    def __init__(
        self,
        capacity: int,
        frame_shape: tuple[int, int, int],
        frame_stack: int,
        action_dim: int,
        data_dir: str | Path | None = None,
        chunk_len: int = 8,
        compression: str = "lz4",
        fsync_interval_s: float = 1.0,
        stop: Callable[[], bool] | None = None,
    ) -> None:
        """`stop`, asked between the records read while reopening `data_dir`: once it says True,
        the opening ends with OpenStopped, its log and snapshot left as they were."""
        if capacity < 1:
            raise ValueError(f"capacity must be >= 1, got {capacity}")
        if frame_stack < 1 or chunk_len < frame_stack:
            # A window of k+1 frames then spans at most two chunks.
            raise ValueError(f"need 1 <= frame_stack <= chunk_len, got {frame_stack}, {chunk_len}")
        if len(frame_shape) != 3 or min(frame_shape) < 1:
            raise ValueError(f"frame_shape must be (C, H, W), got {frame_shape}")
        self.capacity = int(capacity)
        self.frame_shape = tuple(int(x) for x in frame_shape)
        self.frame_size = int(np.prod(self.frame_shape))
        self.k = int(frame_stack)
        self.action_dim = int(action_dim)
        self.chunk_len = int(chunk_len)
        self.fsync_interval_s = float(fsync_interval_s)
        self._codec = FrameCodec(self.frame_size, compression)
        self._tls = threading.local()
        self._lock = threading.RLock()
        # zstd's slower calls gain from a second decode thread; lz4's calls are so short
        # that GIL hand-offs between threads cost more than they save (docs/benchmarks.md).
        decode_threads = 2 if self._codec.compression == "zstd" else 1
        self._pool = ThreadPoolExecutor(decode_threads) if decode_threads > 1 else None
        self._threads = max(1, int(decode_threads))
        self._allocate()
        self._dir = Path(data_dir) if data_dir is not None else None
        self._log: rlog.LogWriter | None = None
        self._segment = 0
        self._last_sync = time.monotonic()
        self._snapshot_thread: threading.Thread | None = None
        self.snapshot_error = ""  # why the last background snapshot failed ("" when it did not)
        self._closed = False
        if self._dir is not None:
            try:
                self._open_dir(stop or (lambda: False))
            except OpenStopped:
                if self._pool is not None:
                    self._pool.shutdown()
                raise
        self._snapshot_at = self._num_inserted  # num_inserted at the last snapshot or at opening

    def _allocate(self) -> None:
        """The metadata ring (one row per transition) and the empty chunk and episode tables."""
        c, a = self.capacity, self.action_dim
        self._action = np.zeros((c, a), np.float32)
        self._reward = np.zeros(c, np.float32)
        self._intrinsic = np.full(c, np.nan, np.float32)
        self._discount = np.zeros(c, np.float32)
        self._episode = np.zeros(c, np.int64)
        self._actor = np.zeros(c, np.int32)
        self._incarnation = np.zeros(c, np.int32)
        self._policy = np.zeros(c, np.int64)
        self._step = np.zeros(c, np.int32)
        self._refs = np.zeros((c, self.k + 1), np.int64)  # chunk_id * chunk_len + offset

        self._head = 0  # oldest live global index
        self._num_inserted = 0
        self._next_episode = 0
        self._next_chunk = 0
        self._chunks: dict[int, _Chunk] = {}
        self._episodes: dict[int, _Episode] = {}
        self._open_by_actor: dict[int, int] = {}  # actor_id -> open episode id
        self._incarnations: dict[int, int] = {}  # actor_id -> newest incarnation seen
        self._blob_bytes = 0
        self._num_blobs = 0

    # ------------------------------------------------------------------ config
    def _config(self) -> dict:
        return {
            "capacity": self.capacity,
            "frame_shape": list(self.frame_shape),
            "frame_stack": self.k,
            "action_dim": self.action_dim,
            "chunk_len": self.chunk_len,
            "compression": self._codec.compression,
        }

    # ------------------------------------------------------------- validation
    def _check_frame(self, frame: np.ndarray, what: str) -> np.ndarray:
        if not isinstance(frame, np.ndarray):
            raise ValueError(f"{what} must be a numpy array, got {type(frame).__name__}")
        if frame.dtype != np.uint8:
            raise ValueError(f"{what} must be uint8, got {frame.dtype}")
        if frame.shape != self.frame_shape:
            raise ValueError(f"{what} has shape {frame.shape}, expected {self.frame_shape}")
        return np.ascontiguousarray(frame).reshape(-1)

    @staticmethod
    def _check_int(value: object, what: str) -> int:
        if isinstance(value, bool) or not isinstance(value, int | np.integer):
            raise ActorRefused(f"{what} must be an int, got {value!r}")
        if value < 0 or value >= ID_LIMIT:
            raise ActorRefused(f"{what} must be in [0, 2**31), got {value}")
        return int(value)

    # ----------------------------------------------------------------- writes
    def begin_episode(self, first_frame: np.ndarray, actor_id: int = 0, incarnation: int = 0) -> int:
        """Start an episode with its reset frame; returns the episode id.

        An open episode of the same actor (its previous run died before its final
        step) is closed first. An incarnation older than one already seen for the
        actor is a zombie and is rejected.
        """
        flat = self._check_frame(first_frame, "first_frame")
        actor_id = self._check_int(actor_id, "actor_id")
        incarnation = self._check_int(incarnation, "incarnation")
        with self._lock:
            self._check_open()
            newest = self._incarnations.get(actor_id, -1)
            if incarnation < newest:
                raise ActorRefused(
                    f"actor {actor_id} incarnation {incarnation} is older than incarnation "
                    f"{newest} already seen: a stale actor may not start episodes"
                )
            blob = self._codec.encode_key(flat)
            ep_id = self._next_episode
            self._write(_BEGIN, _BEGIN_S.pack(ep_id, actor_id, incarnation) + blob)
            self._apply_begin(ep_id, actor_id, incarnation, blob)
            chunk = self._chunks[self._episodes[ep_id].chunk_ids[-1]]
            chunk.key = flat.copy()
            return ep_id

    def add(
        self,
        episode_id: int,
        action: np.ndarray,
        reward: float,
        discount: float,
        next_frame: np.ndarray,
        last: bool,
        policy_version: int = 0,
        intrinsic: float = float("nan"),
    ) -> int:
        """Append one transition; returns its global index. Raises ValueError on bad input."""
        flat = self._check_frame(next_frame, "next_frame")
        act, reward, discount, intrinsic = self._check_step(
            action, reward, discount, intrinsic, last, policy_version
        )
        with self._lock:
            self._check_open()
            ep = self._episodes.get(episode_id) if isinstance(episode_id, int | np.integer) else None
            if ep is None or not ep.open:
                state = "closed" if ep is not None else "unknown"
                raise ValueError(f"episode {episode_id!r} is {state}: begin_episode() first")
            offset = ep.num_frames % self.chunk_len
            if offset == 0:
                blob = self._codec.encode_key(flat)
            else:
                chunk = self._chunks[ep.chunk_ids[-1]]
                if chunk.key is None:
                    chunk.key = self._codec.decode(chunk.blobs[0])
                blob = self._codec.encode_delta(flat, chunk.key)
            g = self._num_inserted
            payload = b"".join(
                (
                    _STEP_HEAD.pack(int(episode_id), g),
                    act.tobytes(),
                    _STEP_TAIL.pack(reward, discount, intrinsic, bool(last), int(policy_version)),
                    blob,
                )
            )
            self._write(_STEP, payload)
            self._apply_step(
                int(episode_id), g, act, reward, discount, intrinsic, bool(last),
                int(policy_version), blob,
            )
            if offset == 0:
                self._chunks[ep.chunk_ids[-1]].key = flat.copy()
            return g

    def _check_step(
        self, action: np.ndarray, reward: float, discount: float, intrinsic: float, last: bool,
        policy_version: int,
    ) -> tuple[np.ndarray, float, float, float]:
        """The step's values as stored (float32 action, floats); ValueError naming a bad one."""
        act = np.asarray(action, dtype=np.float32)
        if act.shape != (self.action_dim,):
            raise ValueError(f"action has shape {act.shape}, expected ({self.action_dim},)")
        if not np.all(np.isfinite(act)):
            raise ValueError(f"action has non-finite values: {act}")
        if np.any(np.abs(act) > ACTION_BOUND):
            raise ValueError(f"action {act} is outside [-{ACTION_BOUND}, {ACTION_BOUND}]")
        reward, discount, intrinsic = float(reward), float(discount), float(intrinsic)
        if not (math.isfinite(reward) and abs(reward) <= _FLOAT32_MAX):
            raise ValueError(f"reward must be finite in float32, got {reward}")
        if not (0.0 <= discount <= 1.0):
            raise ValueError(f"discount must be in [0, 1], got {discount}")
        if math.isinf(intrinsic) or abs(intrinsic) > _FLOAT32_MAX:
            raise ValueError(f"intrinsic must be finite in float32 or NaN (not yet scored), got {intrinsic}")
        if not isinstance(last, bool | np.bool_):
            raise ValueError(f"last must be a bool, got {last!r}")
        if isinstance(policy_version, bool) or not isinstance(policy_version, int | np.integer):
            raise ValueError(f"policy_version must be an int, got {policy_version!r}")
        if not 0 <= policy_version < 2**63:
            raise ValueError(f"policy_version must be in [0, 2**63), got {policy_version}")
        return act, reward, discount, intrinsic

    def set_intrinsic(self, index: np.ndarray, value: np.ndarray) -> None:
        """Fill intrinsic rewards of transitions by global index; evicted indices are ignored."""
        index = np.asarray(index, np.int64).reshape(-1)
        value = np.asarray(value, np.float32).reshape(-1)
        if index.shape != value.shape:
            raise ValueError(f"index {index.shape} and value {value.shape} differ in length")
        if not np.all(np.isfinite(value)):
            raise ValueError("intrinsic values must be finite")
        with self._lock:
            self._check_open()
            if np.any(index >= self._num_inserted) or np.any(index < 0):
                raise ValueError(f"index out of range [0, {self._num_inserted})")
            self._write(
                _INTRINSIC, struct.pack("<I", len(index)) + index.tobytes() + value.tobytes()
            )
            self._apply_intrinsic(index, value)

    def truncate(self, num_inserted: int) -> None:
        """Drop every transition added after the first `num_inserted`; closes all open episodes."""
        with self._lock:
            self._check_open()
            if not 0 <= num_inserted <= self._num_inserted:
                raise ValueError(f"truncate to {num_inserted} outside [0, {self._num_inserted}]")
            self._write(_TRUNCATE, struct.pack("<q", num_inserted))
            self._apply_truncate(num_inserted)

    # -------------------------------------------------------- state mutation
    # Shared by the live path and log replay, so a reopened store is bit-identical.
    def _apply_begin(self, ep_id: int, actor_id: int, incarnation: int, blob: bytes) -> None:
        if (old := self._open_by_actor.get(actor_id)) is not None:
            self._apply_close(old)
        self._incarnations[actor_id] = max(incarnation, self._incarnations.get(actor_id, -1))
        ep = _Episode(actor_id, incarnation)
        self._episodes[ep_id] = ep
        self._open_by_actor[actor_id] = ep_id
        self._next_episode = max(self._next_episode, ep_id + 1)
        self._append_frame(ep_id, ep, blob)

    def _append_frame(self, ep_id: int, ep: _Episode, blob: bytes) -> None:
        if ep.num_frames % self.chunk_len == 0:
            if ep.chunk_ids:
                prev = self._chunks[ep.chunk_ids[-1]]
                prev.open, prev.key = False, None
            cid = self._next_chunk
            self._next_chunk += 1
            self._chunks[cid] = _Chunk(ep_id)
            ep.chunk_ids.append(cid)
            ep.live_chunks += 1
            if len(ep.chunk_ids) >= 3:  # no longer needed for stacking future frames
                self._maybe_free(ep.chunk_ids[-3])
        self._chunks[ep.chunk_ids[-1]].blobs.append(blob)
        self._blob_bytes += len(blob)
        self._num_blobs += 1
        ep.num_frames += 1

    def _apply_step(
        self, ep_id: int, g: int, act: np.ndarray, reward: float, discount: float,
        intrinsic: float, last: bool, policy: int, blob: bytes,
    ) -> None:
        if g != self._num_inserted:
            raise rlog.StoreFormatError(f"log step index {g} != expected {self._num_inserted}")
        ep = self._episodes[ep_id]
        self._append_frame(ep_id, ep, blob)
        t = ep.num_frames - 2  # step index: frame t + 1 was just appended
        if self._num_inserted - self._head >= self.capacity:
            self._evict_oldest(adding=ep_id)
        frames = np.maximum(np.arange(t - self.k + 1, t + 2), 0)
        refs = np.array(ep.chunk_ids, np.int64)[frames // self.chunk_len] * self.chunk_len + (
            frames % self.chunk_len
        )
        pos = g % self.capacity
        self._refs[pos] = refs
        for cid in set((refs // self.chunk_len).tolist()):
            self._chunks[cid].refcount += 1
        self._chunks[ep.chunk_ids[-1]].owned.append(g)
        self._action[pos] = act
        self._reward[pos] = reward
        self._intrinsic[pos] = intrinsic
        self._discount[pos] = discount
        self._episode[pos] = ep_id
        self._actor[pos] = ep.actor_id
        self._incarnation[pos] = ep.incarnation
        self._policy[pos] = policy
        self._step[pos] = t
        self._num_inserted += 1
        if last:
            self._apply_close(ep_id)

    def _apply_close(self, ep_id: int) -> None:
        ep = self._episodes[ep_id]
        if not ep.open:
            return
        ep.open = False
        if self._open_by_actor.get(ep.actor_id) == ep_id:
            del self._open_by_actor[ep.actor_id]
        last = self._chunks[ep.chunk_ids[-1]]
        last.open, last.key = False, None
        for cid in ep.chunk_ids[-2:]:
            self._maybe_free(cid)

    def _maybe_free(self, cid: int) -> None:
        chunk = self._chunks.get(cid)
        if chunk is None or chunk.refcount > 0 or chunk.open:
            return
        ep = self._episodes[chunk.episode_id]
        if ep.open and cid in ep.chunk_ids[-2:]:
            return  # the next add may stack frames from it
        del self._chunks[cid]
        self._blob_bytes -= sum(len(b) for b in chunk.blobs)
        self._num_blobs -= len(chunk.blobs)
        ep.live_chunks -= 1
        if ep.live_chunks == 0 and not ep.open:
            del self._episodes[chunk.episode_id]

    def _release_window(self, pos: int) -> None:
        for cid in set((self._refs[pos] // self.chunk_len).tolist()):
            self._chunks[cid].refcount -= 1
            self._maybe_free(cid)

    def _evict_oldest(self, adding: int) -> None:
        pos = self._head % self.capacity
        g, ep_id = self._head, int(self._episode[pos])
        self._head += 1
        self._release_window(pos)
        # An open episode whose newest transition leaves has had nothing added for a whole capacity
        # of other actors' inserts: its actor is gone (a replica that came back under a new id never
        # continues it). Closed here, its last chunks and entry go with its transitions, rather than
        # stay for the rest of the run; live and log replay both pass here, so a reopen agrees.
        ep = self._episodes.get(ep_id)
        newest = self._chunks[ep.chunk_ids[-1]].owned[-1:] if ep is not None else []
        if ep is not None and ep.open and ep_id != adding and newest == [g]:
            self._apply_close(ep_id)

    def _apply_intrinsic(self, index: np.ndarray, value: np.ndarray) -> None:
        live = (index >= self._head) & (index < self._num_inserted)
        self._intrinsic[index[live] % self.capacity] = value[live]

    def _apply_truncate(self, n: int) -> None:
        for g in range(self._num_inserted - 1, max(n, self._head) - 1, -1):
            pos = g % self.capacity
            ep = self._episodes[int(self._episode[pos])]
            # g is the newest transition of its episode, so its frame is the episode's last.
            cid = ep.chunk_ids[-1]
            chunk = self._chunks[cid]
            blob = chunk.blobs.pop()
            chunk.owned.pop()
            self._blob_bytes -= len(blob)
            self._num_blobs -= 1
            ep.num_frames -= 1
            if not chunk.blobs:
                ep.chunk_ids.pop()
            self._release_window(pos)
            if not chunk.blobs and cid in self._chunks:
                del self._chunks[cid]
                ep.live_chunks -= 1
            self._intrinsic[pos] = np.nan
        self._num_inserted = n
        self._head = min(self._head, n)
        for ep_id in list(self._open_by_actor.values()):
            self._apply_close(ep_id)
        for ep_id in [e for e, ep in self._episodes.items() if ep.live_chunks == 0]:
            del self._episodes[ep_id]

    # ----------------------------------------------------------------- reads
    def __len__(self) -> int:
        return self._num_inserted - self._head

    def is_open(self, episode_id: int) -> bool:
        """Whether the episode takes steps: begun and not closed (by its last step, by its actor's
        next episode, or by the eviction of its newest transition)."""
        with self._lock:
            ep = self._episodes.get(episode_id)
            return ep is not None and ep.open

    @property
    def num_inserted(self) -> int:
        return self._num_inserted

    def sample(
        self, batch_size: int, rng: np.random.Generator, per_chunk: int = 1, replace: bool = True
    ) -> dict[str, np.ndarray]:
        """Sample a batch uniformly over the live transitions.

        Frames come as `window` (B, (k+1)*C, H, W), each transition's k+1 frames;
        `obs` and `next_obs` are views of it (its first and last k frames).

        replace=False draws the batch without replacement (no transition twice in
        one batch, as the reference does); it needs at least batch_size live
        transitions and raises ValueError otherwise (never a smaller batch).

        per_chunk > 1 (with replacement only) draws batch_size / per_chunk anchor
        transitions uniformly and, for each, per_chunk - 1 more uniformly among
        the live transitions whose newest frame shares the anchor's chunk. Every
        draw is still exactly uniform over the store; draws within a group are
        correlated, and each decoded chunk serves several transitions.
        """
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        if per_chunk > 1 and not replace:
            raise ValueError("per_chunk > 1 draws with replacement; it cannot be combined with replace=False")
        with self._lock:
            if len(self) == 0:
                raise ValueError("cannot sample from an empty replay store")
            if replace:
                index = self._draw(batch_size, rng, per_chunk)
            elif batch_size > len(self):
                raise ValueError(
                    f"cannot draw {batch_size} distinct transitions from {len(self)} stored"
                )
            else:
                index = self._head + rng.choice(len(self), batch_size, replace=False)
            plan = self._gather(index)
        return self._assemble(plan)

    def get(self, index: np.ndarray) -> dict[str, np.ndarray]:
        """The live transitions at these global indices, as `sample` returns them."""
        g = np.asarray(index, dtype=np.int64)
        if g.ndim != 1 or len(g) == 0:
            raise ValueError(f"index must be a non-empty 1-d array, got shape {g.shape}")
        with self._lock:
            if g.min() < self._head or g.max() >= self._num_inserted:
                raise ValueError(f"index outside the live range [{self._head}, {self._num_inserted})")
            plan = self._gather(g)
        return self._assemble(plan)

    def unscored(self, after: int, limit: int) -> np.ndarray:
        """Live global indices >= after whose intrinsic slot is unscored (NaN), oldest first."""
        with self._lock:
            return self._unscored(after, limit)

    def _unscored(self, after: int, limit: int) -> np.ndarray:
        g = np.arange(max(int(after), self._head), self._num_inserted, dtype=np.int64)
        return g[np.isnan(self._intrinsic[g % self.capacity])][: max(0, int(limit))]

    def get_unscored(self, after: int, limit: int) -> dict[str, np.ndarray] | None:
        """`get(unscored(after, limit))` in one step, so no insert evicts the rows found before
        they are read; None when there are none."""
        with self._lock:
            g = self._unscored(after, limit)
            if len(g) == 0:
                return None
            plan = self._gather(g)
        return self._assemble(plan)

    def _gather(self, g: np.ndarray) -> tuple:
        """Under the lock: the metadata of transitions `g` and what decoding their frames needs."""
        pos = g % self.capacity
        refs = self._refs[pos]
        uref, first, inv = np.unique(refs.ravel(), return_index=True, return_inverse=True)
        cids = uref // self.chunk_len
        starts = np.flatnonzero(np.r_[True, cids[1:] != cids[:-1]])
        # Chunk objects, not the dict: a chunk freed meanwhile keeps its blobs for us.
        chunks = [self._chunks[c] for c in cids[starts].tolist()]
        out = {
            "action": self._action[pos],
            "reward": self._reward[pos],
            "intrinsic": self._intrinsic[pos],
            "discount": self._discount[pos],
            "index": g,
            "episode_id": self._episode[pos],
            "actor_id": self._actor[pos],
            "incarnation": self._incarnation[pos],
            "policy_version": self._policy[pos],
            "step": self._step[pos],
        }
        return out, refs.size, chunks, starts, uref % self.chunk_len, first, inv

    def _assemble(self, plan: tuple) -> dict[str, np.ndarray]:
        """Outside the lock (blobs are immutable bytes, so writers keep going): decode the frames."""
        out, n, chunks, starts, offs, first, inv = plan
        frames = self._decode(n, chunks, starts, offs, first)
        dup = np.flatnonzero(first[inv] != np.arange(n))  # repeats (episode starts, overlaps)
        if dup.size:
            frames[dup] = frames[first[inv[dup]]]
        b, (c, h, w) = len(out["index"]), self.frame_shape
        # window: the k+1 frames of each transition; obs and next_obs are views of it.
        out["window"] = frames.reshape(b, (self.k + 1) * c, h, w)
        out["obs"] = out["window"][:, : self.k * c]
        out["next_obs"] = out["window"][:, c:]
        return out

    def _draw(self, b: int, rng: np.random.Generator, per_chunk: int) -> np.ndarray:
        if per_chunk <= 1 or self._head == self._num_inserted:
            return rng.integers(self._head, self._num_inserted, b, dtype=np.int64)
        anchors = rng.integers(self._head, self._num_inserted, -(-b // per_chunk), dtype=np.int64)
        out = []
        for a in anchors.tolist():
            cid = int(self._refs[a % self.capacity, -1]) // self.chunk_len
            owned = self._chunks[cid].owned
            lo = bisect.bisect_left(owned, self._head)  # owned ascends; evicted ones lead
            out.append(a)
            out.extend(owned[i] for i in rng.integers(lo, len(owned), per_chunk - 1).tolist())
        return np.array(out[:b], np.int64)

    def _decode(
        self, n: int, chunks: list[_Chunk], starts: np.ndarray, offs: np.ndarray, dest: np.ndarray
    ) -> np.ndarray:
        """Decode the sorted unique frames (chunk `chunks[i]` holds those from `starts[i]` on,
        at offsets `offs`) into rows `dest` of a (n, frame_size) array."""
        out = np.empty((n, self.frame_size), np.uint8)
        ends = np.r_[starts[1:], len(offs)]
        groups = list(zip(chunks, starts.tolist(), ends.tolist(), strict=True))
        if self._pool is None or len(groups) < 4:
            self._decode_groups(groups, offs, dest, out)
            return out
        parts = [groups[i :: self._threads] for i in range(self._threads)]
        for f in [self._pool.submit(self._decode_groups, p, offs, dest, out) for p in parts]:
            f.result()
        return out

    def _decode_groups(self, groups: list, offs: np.ndarray, dest: np.ndarray, out: np.ndarray) -> None:
        codec = getattr(self._tls, "codec", None)
        if codec is None:
            codec = self._tls.codec = FrameCodec(self.frame_size, self._codec.compression)
        # Local names: this loop runs about 5 times per transition.
        decompress, frombuffer, add, u8 = codec.decompress, np.frombuffer, np.add, np.uint8
        offs, dest = offs.tolist(), dest.tolist()
        for chunk, s, e in groups:
            blobs = chunk.blobs
            if offs[s] == 0:  # sorted: the keyframe, when wanted, comes first
                key = out[dest[s]]
                key[:] = frombuffer(decompress(blobs[0]), u8)
                s += 1
            else:
                key = frombuffer(decompress(blobs[0]), u8)
            for i in range(s, e):
                add(key, frombuffer(decompress(blobs[offs[i]]), u8), out=out[dest[i]])

    def stats(self) -> dict:
        with self._lock:
            meta = sum(
                a.nbytes
                for a in (
                    self._action, self._reward, self._intrinsic, self._discount, self._episode,
                    self._actor, self._incarnation, self._policy, self._step, self._refs,
                )
            )
            # Python object overhead per frame: bytes object 33 B + list slot 8 B, plus its
            # owning transition index in `owned` (int 28 B + slot 8 B); ~200 B per chunk.
            overhead = 77 * self._num_blobs + 200 * len(self._chunks) + 200 * len(self._episodes)
            ram = self._blob_bytes + meta + overhead
            n = len(self)
            return {
                "size": n,
                "capacity": self.capacity,
                "num_inserted": self._num_inserted,
                "episodes": len(self._episodes),
                "open_episodes": len(self._open_by_actor),
                "chunks": len(self._chunks),
                "frames": self._num_blobs,
                "frame_bytes": self._blob_bytes,
                "metadata_bytes": meta,
                "bytes_in_ram": ram,
                "bytes_per_transition_ram": ram / n if n else 0.0,
                "bytes_on_disk": self._disk_bytes(),
            }

    def _disk_bytes(self) -> int:
        if self._dir is None:
            return 0
        total = 0
        for p in self._dir.iterdir():
            try:
                total += p.stat().st_size if p.is_file() else 0
            except FileNotFoundError:  # a segment or snapshot a background snapshot just removed
                continue
        return total

    # ------------------------------------------------------------ durability
    def _check_open(self) -> None:
        if self._closed:
            raise RuntimeError("replay store is closed")

    def _write(self, rtype: int, payload: bytes) -> None:
        if self._log is None:
            return
        before = self._log.bytes_written
        self._log.append(rtype, payload)
        try:
            self._sync_if_due()
        except OSError:
            # The record is not applied, so it must not stay in the log: the caller may write
            # it again, and a second copy would make the log unreadable.
            self._log.cut(before)
            raise

    def sync_if_due(self) -> None:
        """fsync the log if it holds writes older than the fsync interval: called periodically,
        so the last writes before a pause in inserts are not left unsynced until the next one."""
        with self._lock:
            if self._log is not None:
                self._sync_if_due()

    def _sync_if_due(self) -> None:
        if self._log.dirty and time.monotonic() - self._last_sync >= self.fsync_interval_s:
            self._log.sync()
            self._last_sync = time.monotonic()

    def flush(self) -> None:
        """fsync the log. Every add() that returned is already safe from process death
        (written to the OS); after flush() it is also safe from power loss."""
        with self._lock:
            if self._log is not None:
                self._log.sync()
                self._last_sync = time.monotonic()

    def _open_dir(self, stop: Callable[[], bool]) -> None:
        assert self._dir is not None
        self._dir.mkdir(parents=True, exist_ok=True)
        existed = rlog.check_manifest(self._dir, self._config())
        if not existed:
            rlog.write_manifest(self._dir, self._config())
        for tmp in self._dir.glob("snapshot-*.tmp"):
            tmp.unlink()  # a snapshot a crash interrupted; it was never renamed, so never read
        segs, snaps = rlog.list_numbered(self._dir)
        start = 1
        if snaps:
            start = snaps[-1]
            self._load_snapshot(rlog.read_snapshot(rlog.snapshot_path(self._dir, start)), stop)
        todo = [s for s in segs if s >= start]
        if todo and todo != list(range(start, todo[-1] + 1)):
            raise rlog.StoreFormatError(f"{self._dir}: log segments {todo} are not contiguous")
        # A stop here leaves the log as it was (a torn tail is cut only where it is met, at the end
        # of the last segment): the next opening reads it all.
        for s in todo:
            path = rlog.segment_path(self._dir, s)
            for i, (rtype, payload) in enumerate(rlog.read_segment(path, is_last=(s == todo[-1]))):
                if i % STOP_CHECK_EVERY == 0 and stop():
                    raise OpenStopped(f"{path} read in part")
                self._replay(rtype, payload)
        self._segment = (todo[-1] + 1) if todo else start
        self._log = rlog.LogWriter(rlog.segment_path(self._dir, self._segment))
        rlog.fsync_dir(self._dir)

    def _replay(self, rtype: int, p: memoryview) -> None:
        if rtype == _BEGIN:
            ep_id, actor, inc = _BEGIN_S.unpack_from(p)
            self._apply_begin(ep_id, actor, inc, bytes(p[_BEGIN_S.size :]))
        elif rtype == _STEP:
            ep_id, g = _STEP_HEAD.unpack_from(p)
            o = _STEP_HEAD.size
            act = np.frombuffer(p[o : o + 4 * self.action_dim], np.float32).copy()
            o += 4 * self.action_dim
            reward, discount, intrinsic, last, policy = _STEP_TAIL.unpack_from(p, o)
            blob = bytes(p[o + _STEP_TAIL.size :])
            self._apply_step(ep_id, g, act, reward, discount, intrinsic, bool(last), policy, blob)
        elif rtype == _INTRINSIC:
            (n,) = struct.unpack_from("<I", p)
            idx = np.frombuffer(p[4 : 4 + 8 * n], np.int64)
            val = np.frombuffer(p[4 + 8 * n : 4 + 12 * n], np.float32)
            self._apply_intrinsic(idx, val)
        elif rtype == _TRUNCATE:
            self._apply_truncate(struct.unpack_from("<q", p)[0])
        elif rtype == _CLOSE:
            self._apply_close(struct.unpack_from("<q", p)[0])
        else:
            raise rlog.StoreFormatError(f"unknown log record type {rtype}")

    _ARRAYS = (
        "_action", "_reward", "_intrinsic", "_discount", "_episode", "_actor",
        "_incarnation", "_policy", "_step", "_refs",
    )

    def snapshot(self, block: bool = True) -> None:
        """Write a compacted snapshot and drop the log it replaces.

        The lock is held only to rotate the log and copy the live metadata and
        the chunk table (blobs are immutable and shared, not copied); the file is
        written without the lock, so inserts keep going. block=False writes it
        in a background thread.
        """
        if self._dir is None:
            return
        with self._lock:
            self._check_open()
            if self._snapshot_thread is not None:
                self._snapshot_thread.join()
            self._log.close()  # fsyncs the old segment
            self._segment += 1
            seg = self._segment
            self._log = rlog.LogWriter(rlog.segment_path(self._dir, seg))
            self._snapshot_at = self._num_inserted
            state = self._capture()
        if block:
            self._write_snapshot(seg, state)
        else:
            self._snapshot_thread = threading.Thread(
                target=self._write_snapshot_in_background, args=(seg, state), daemon=True
            )
            self._snapshot_thread.start()

    def snapshot_if_due(self, every: int = SNAPSHOT_EVERY) -> bool:
        """Start a background snapshot once `every` transitions were added since the last one (or
        since the store was opened), so the log, and the time to read it back, stay bounded over a
        long run. True when one started."""
        with self._lock:
            if self._dir is None or self._num_inserted - self._snapshot_at < every:
                return False
            self.snapshot(block=False)
            return True

    def _write_snapshot_in_background(self, seg: int, state: dict) -> None:
        """A failed snapshot (a full disk) loses nothing: the older snapshot and the log segments
        it would have replaced stay. Its error stands in `snapshot_error` until one succeeds."""
        try:
            self._write_snapshot(seg, state)
        except OSError as err:
            self.snapshot_error = f"{type(err).__name__}: {err}"
        else:
            self.snapshot_error = ""

    def _capture(self) -> dict:
        # Copies only: the file is written outside the lock while inserts go on.
        pos = np.arange(self._head, self._num_inserted) % self.capacity
        arrays = {name: getattr(self, name)[pos] for name in self._ARRAYS}
        chunks = [(cid, c.episode_id, c.refcount, c.open, list(c.blobs)) for cid, c in self._chunks.items()]
        episodes = {
            str(e): [ep.actor_id, ep.incarnation, list(ep.chunk_ids), ep.num_frames, ep.open, ep.live_chunks]
            for e, ep in self._episodes.items()
        }
        meta = {
            "head": self._head,
            "num_inserted": self._num_inserted,
            "next_episode": self._next_episode,
            "next_chunk": self._next_chunk,
            "open_by_actor": {str(a): e for a, e in self._open_by_actor.items()},
            "incarnations": {str(a): i for a, i in self._incarnations.items()},
            "episodes": episodes,
        }
        return {"meta": meta, "arrays": arrays, "chunks": chunks}

    def _write_snapshot(self, seg: int, state: dict) -> None:
        import json

        chunks = state["chunks"]
        chunk_meta = np.array([(c[0], c[1], c[2], int(c[3]), len(c[4])) for c in chunks], np.int64)
        blobs = [b for c in chunks for b in c[4]]
        lengths = np.array([len(b) for b in blobs], np.int64)
        sections: list[tuple[str, bytes | memoryview]] = [
            ("meta", json.dumps(state["meta"]).encode()),
            ("chunk_meta", chunk_meta.reshape(-1, 5).tobytes()),
            ("blob_lengths", lengths.tobytes()),
            ("blobs", b"".join(blobs)),
        ]
        for name, arr in state["arrays"].items():
            sections.append((name, np.ascontiguousarray(arr).tobytes()))
        rlog.write_snapshot(rlog.snapshot_path(self._dir, seg), sections)
        # The snapshot now covers everything before segment `seg`.
        segs, snaps = rlog.list_numbered(self._dir)
        for s in segs:
            if s < seg:
                os.remove(rlog.segment_path(self._dir, s))
        for s in snaps:
            if s < seg:
                os.remove(rlog.snapshot_path(self._dir, s))
        rlog.fsync_dir(self._dir)

    def _load_snapshot(self, sec: dict[str, memoryview], stop: Callable[[], bool]) -> None:
        import json

        meta = json.loads(bytes(sec["meta"]))
        self._head = meta["head"]
        self._num_inserted = meta["num_inserted"]
        self._next_episode = meta["next_episode"]
        self._next_chunk = meta["next_chunk"]
        self._open_by_actor = {int(a): e for a, e in meta["open_by_actor"].items()}
        self._incarnations = {int(a): i for a, i in meta["incarnations"].items()}
        for e, (actor, inc, cids, nf, is_open, live) in meta["episodes"].items():
            self._episodes[int(e)] = _Episode(actor, inc, cids, nf, is_open, live)
        chunk_meta = np.frombuffer(sec["chunk_meta"], np.int64).reshape(-1, 5)
        lengths = np.frombuffer(sec["blob_lengths"], np.int64)
        ends = np.cumsum(lengths)
        blob_data = sec["blobs"]
        i = 0
        for n, (cid, ep_id, refcount, is_open, nb) in enumerate(chunk_meta.tolist()):
            if n % STOP_CHECK_EVERY == 0 and stop():
                raise OpenStopped(f"{self._dir}: its snapshot read in part")
            blobs = [bytes(blob_data[ends[j] - lengths[j] : ends[j]]) for j in range(i, i + nb)]
            i += nb
            self._chunks[cid] = _Chunk(ep_id, blobs, refcount, bool(is_open))
            self._blob_bytes += int(lengths[i - nb : i].sum())
            self._num_blobs += nb
        pos = np.arange(self._head, self._num_inserted) % self.capacity
        for name in self._ARRAYS:
            arr = getattr(self, name)
            arr[pos] = np.frombuffer(sec[name], arr.dtype).reshape((len(pos), *arr.shape[1:]))
        for g, cid in zip(
            range(self._head, self._num_inserted),
            (self._refs[pos, -1] // self.chunk_len).tolist(),
            strict=True,
        ):
            self._chunks[cid].owned.append(g)

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            if self._snapshot_thread is not None:
                self._snapshot_thread.join()
            if self._log is not None:
                self._log.close()
            self._closed = True
        if self._pool is not None:
            self._pool.shutdown()

    def __enter__(self) -> ReplayStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_store(run: RunConfig, data_dir: str | Path | None,
               stop: Callable[[], bool] | None = None) -> ReplayStore:
    """The store of a run, shaped by its EnvSpec and config (in `data_dir`; None: in memory);
    `stop` ends a long reopening (OpenStopped)."""
    c, spec = run.config, run.spec
    return ReplayStore(
        capacity=c.replay_capacity,
        frame_shape=spec.frame_shape,
        frame_stack=spec.frame_stack,
        action_dim=spec.action_dim,
        data_dir=data_dir,
        compression=c.replay_compression,
        stop=stop,
    )
