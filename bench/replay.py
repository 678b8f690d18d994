"""Replay store benchmark on real frames of the six paper tasks.

    python -m bench.replay [--frames 2000] [--store 100000] [--seconds 3] [--compression lz4|zstd]

Rendering 100k frames per task is too slow here (~60-160 renders/s), so each
task renders `--frames` real frames (random actions, render_quality "fast")
and the 100k-transition store is built by re-inserting those real episodes.
Beside each sampling rate, the same run measures two bounds on the same real
frames, single-threaded (the lz4 store decodes in one thread):
- `bound_decode_per_s`: transitions/s when a batch costs only its codec calls
  (each chunk's keyframe once per batch, each other frame's delta decompressed
  and added into its row in place) and none of the store's bookkeeping;
- `bound_memcpy_per_s`: transitions/s of gathering the same frames uncompressed
  (one copy per frame), what an uncompressed in-memory store could reach.
Each also per CPU second of this process (`_per_cpu_s`), which moves less when
other processes share the cores.
The bounds use the rendered frames alone (a smaller working set than the store's
100k transitions), so they are, if anything, optimistic.
Prints human-readable lines; the last line is one JSON object.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.args import task_names
from shared.envs import PAPER_TASKS, make
from shared.replay import ReplayStore
from shared.replay.codec import COMPRESSIONS, FrameCodec

GOAL_BYTES = 4096
GOAL_SAMPLES = 20_000


def render_episodes(task: str, frames: int, seed: int) -> tuple[list[list[np.ndarray]], int]:
    env = make(task, seed, render_quality="fast")
    rng = np.random.default_rng(seed)
    episodes, n = [], 0
    while n < frames:
        ts = env.reset()
        ep = [ts.frame]
        while not ts.last and n < frames:
            ts = env.step(rng.uniform(-1, 1, env.action_dim))
            ep.append(ts.frame)
            n += 1
        episodes.append(ep)
    return episodes, env.action_dim


def sample_rate(store: ReplayStore, seconds: float, per_chunk: int) -> tuple[float, float]:
    """(transitions per wall second, per CPU second of this process).

    The CPU-time figure is what the machine could do unshared: the wall figure
    drops when other processes compete for the two cores.
    """
    rng = np.random.default_rng(0)
    store.sample(128, rng, per_chunk=per_chunk)
    n, t0, c0 = 0, time.perf_counter(), time.process_time()
    while time.perf_counter() - t0 < seconds:
        store.sample(128, rng, per_chunk=per_chunk)
        n += 1
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    return n * 128 / wall, n * 128 / max(cpu, 1e-9)


class DecodeBound:
    """The rendered episodes encoded as the store encodes them (chunks of `chunk_len` frames: a
    keyframe, then deltas to it), and each transition's window of k+1 frame references."""

    def __init__(self, episodes: list[list[np.ndarray]], frame_stack: int, chunk_len: int, compression: str):
        frame_size = episodes[0][0].size
        self.codec = FrameCodec(frame_size, compression)
        self.chunks: list[list[bytes]] = []
        self.raw = np.stack([f.reshape(-1) for ep in episodes for f in ep])
        windows, base = [], 0
        for ep in episodes:
            refs = []
            for s in range(0, len(ep), chunk_len):
                key = ep[s]
                blobs = [self.codec.encode_key(key)]
                blobs += [self.codec.encode_delta(f, key) for f in ep[s + 1 : s + chunk_len]]
                self.chunks.append(blobs)
                refs += [(len(self.chunks) - 1, o, base + s + o) for o in range(len(blobs))]
            windows += [refs[t - frame_stack : t + 1] for t in range(frame_stack, len(refs))]
            base += len(ep)
        self.windows = windows
        self.rows = np.array([[r[2] for r in w] for w in windows], np.int64)

    def decode_batch(self, sel: np.ndarray, out: np.ndarray) -> None:
        """The store's decoding of a batch without its bookkeeping: each chunk's keyframe
        decompressed once per batch, each other frame's delta decompressed and added into
        its output row in place."""
        decompress, frombuffer, add, u8 = self.codec.decompress, np.frombuffer, np.add, np.uint8
        keys: dict[int, np.ndarray] = {}
        row = 0
        for w in sel.tolist():
            for c, o, _ in self.windows[w]:
                key = keys.get(c)
                if key is None:
                    key = keys[c] = frombuffer(decompress(self.chunks[c][0]), u8)
                if o == 0:
                    out[row] = key
                else:
                    add(key, frombuffer(decompress(self.chunks[c][o]), u8), out=out[row])
                row += 1

    def rates(self, batch: int, seconds: float, plans: int = 32) -> dict[str, float]:
        """Decode-only and memcpy-only transitions per wall second and per CPU second of this
        process (i.i.d. uniform windows, drawn before the clock starts)."""
        rng = np.random.default_rng(0)
        out = np.empty((batch * self.rows.shape[1], self.raw.shape[1]), np.uint8)
        sels = [rng.integers(0, len(self.windows), batch) for _ in range(plans)]
        gathers = [self.rows[sel].reshape(-1) for sel in sels]

        def rate(fn) -> tuple[float, float]:
            fn(0)
            n, t0, c0 = 0, time.perf_counter(), time.process_time()
            while time.perf_counter() - t0 < seconds:
                fn(n % plans)
                n += 1
            wall, cpu = time.perf_counter() - t0, time.process_time() - c0
            return n * batch / wall, n * batch / max(cpu, 1e-9)

        decode, decode_cpu = rate(lambda i: self.decode_batch(sels[i], out))
        memcpy, memcpy_cpu = rate(lambda i: np.take(self.raw, gathers[i], axis=0, out=out))
        return {"decode": decode, "decode_cpu": decode_cpu, "memcpy": memcpy, "memcpy_cpu": memcpy_cpu}


def bench_task(task: str, args: argparse.Namespace, workdir: Path) -> dict:
    t0 = time.perf_counter()
    episodes, action_dim = render_episodes(task, args.frames, args.seed)
    render_s = time.perf_counter() - t0
    data_dir = workdir / task
    store = ReplayStore(
        args.store,
        (3, 84, 84),
        3,
        action_dim,
        data_dir=data_dir,
        chunk_len=args.chunk_len,
        compression=args.compression,
    )
    rng = np.random.default_rng(1)
    t0 = time.perf_counter()
    frames_in = 0
    while store.num_inserted < args.store:
        for ep_frames in episodes:
            ep = store.begin_episode(ep_frames[0])
            frames_in += 1
            for j, f in enumerate(ep_frames[1:], start=1):
                a = rng.uniform(-1, 1, action_dim)
                store.add(ep, a, 0.5, 1.0, f, j == len(ep_frames) - 1)
                frames_in += 1
                if store.num_inserted >= args.store:
                    break
            if store.num_inserted >= args.store:
                break
    store.flush()
    insert_fps = frames_in / (time.perf_counter() - t0)
    log_bytes = store.stats()["bytes_on_disk"]
    t0 = time.perf_counter()
    store.snapshot()
    snapshot_s = time.perf_counter() - t0
    st = store.stats()
    n = len(store)
    iid, iid_cpu = sample_rate(store, args.seconds, 1)
    grouped, grouped_cpu = sample_rate(store, args.seconds, args.per_chunk)
    bound = DecodeBound(episodes, 3, args.chunk_len, args.compression).rates(128, args.seconds)
    store.close()
    shutil.rmtree(data_dir)
    row = {
        "rendered_frames": sum(len(e) for e in episodes),
        "render_fps": round(sum(len(e) for e in episodes) / render_s, 1),
        "transitions": n,
        "bytes_per_transition_ram": round(st["bytes_in_ram"] / n, 1),
        "frame_bytes_per_transition": round(st["frame_bytes"] / n, 1),
        "bytes_per_transition_disk_log": round(log_bytes / n, 1),
        "bytes_per_transition_disk_snapshot": round(st["bytes_on_disk"] / n, 1),
        "insert_frames_per_s": round(insert_fps),
        "snapshot_s": round(snapshot_s, 2),
        "sampled_per_s_b128_uniform_iid": round(iid),
        f"sampled_per_s_b128_per_chunk_{args.per_chunk}": round(grouped),
        "sampled_per_cpu_s_uniform_iid": round(iid_cpu),
        f"sampled_per_cpu_s_per_chunk_{args.per_chunk}": round(grouped_cpu),
        "bound_decode_per_s": round(bound["decode"]),
        "bound_memcpy_per_s": round(bound["memcpy"]),
        "bound_decode_per_cpu_s": round(bound["decode_cpu"]),
        "bound_memcpy_per_cpu_s": round(bound["memcpy_cpu"]),
        "iid_fraction_of_decode_bound": round(iid / bound["decode"], 3),
        "iid_fraction_of_memcpy_bound": round(iid / bound["memcpy"], 4),
        "iid_fraction_of_decode_bound_cpu": round(iid_cpu / bound["decode_cpu"], 3),
        "load_avg_1min": round(os.getloadavg()[0], 2),
    }
    print(f"{task}: {row}", flush=True)
    return row


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=2000, help="real frames rendered per task")
    p.add_argument("--store", type=int, default=100_000, help="transitions in the store")
    p.add_argument("--seconds", type=float, default=3.0, help="sampling time per mode")
    p.add_argument("--chunk-len", type=int, default=8)
    p.add_argument("--compression", choices=COMPRESSIONS, default="lz4")
    p.add_argument("--per-chunk", type=int, default=8, help="transitions per decoded chunk")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--tasks", type=task_names, default=list(PAPER_TASKS), help="comma-separated")
    args = p.parse_args()
    print(
        f"replay bench: {args.frames} real frames per task (render_quality=fast, random actions), "
        f"store of {args.store} transitions built by re-inserting those real episodes; batch 128",
        flush=True,
    )
    rows = {}
    with tempfile.TemporaryDirectory(prefix="replay-bench-") as tmp:
        for task in args.tasks:
            rows[task] = bench_task(task, args, Path(tmp))

    def mean(key: str) -> float:
        return round(float(np.mean([r[key] for r in rows.values()])), 1)

    gk = f"sampled_per_s_b128_per_chunk_{args.per_chunk}"
    summary = {
        "tasks": rows,
        "mean_bytes_per_transition_ram": mean("bytes_per_transition_ram"),
        "mean_bytes_per_transition_disk_snapshot": mean("bytes_per_transition_disk_snapshot"),
        "mean_bytes_per_transition_disk_log": mean("bytes_per_transition_disk_log"),
        "mean_sampled_per_s_uniform_iid": mean("sampled_per_s_b128_uniform_iid"),
        f"mean_{gk}": mean(gk),
        "mean_sampled_per_cpu_s_uniform_iid": mean("sampled_per_cpu_s_uniform_iid"),
        f"mean_sampled_per_cpu_s_per_chunk_{args.per_chunk}": mean(
            f"sampled_per_cpu_s_per_chunk_{args.per_chunk}"
        ),
        "mean_bound_decode_per_s": mean("bound_decode_per_s"),
        "mean_bound_memcpy_per_s": mean("bound_memcpy_per_s"),
        "mean_iid_fraction_of_decode_bound": round(
            float(np.mean([r["iid_fraction_of_decode_bound"] for r in rows.values()])), 3
        ),
        "mean_iid_fraction_of_decode_bound_cpu": round(
            float(np.mean([r["iid_fraction_of_decode_bound_cpu"] for r in rows.values()])), 3
        ),
        "mean_iid_fraction_of_memcpy_bound": round(
            float(np.mean([r["iid_fraction_of_memcpy_bound"] for r in rows.values()])), 4
        ),
        "cpu_count": os.cpu_count(),
        "min_sampled_per_s_uniform_iid": min(r["sampled_per_s_b128_uniform_iid"] for r in rows.values()),
        "goal_bytes_met": mean("bytes_per_transition_ram") <= GOAL_BYTES,
        "goal_samples_iid_met": mean("sampled_per_s_b128_uniform_iid") >= GOAL_SAMPLES,
        f"goal_samples_per_chunk_{args.per_chunk}_met": mean(gk) >= GOAL_SAMPLES,
        "render_quality": "fast",
        "chunk_len": args.chunk_len,
        "compression": args.compression,
        "note": (
            f"{args.frames} real rendered frames per task re-inserted to {args.store} transitions; "
            "uniform_iid = i.i.d. uniform draws; per_chunk = each decoded chunk serves several "
            "uniform-marginal draws (correlated within a batch)"
        ),
    }
    print(json.dumps(summary))


if __name__ == "__main__":
    from bench.processes import stopped_cleanly

    with stopped_cleanly("python -m bench.replay"):
        main()
