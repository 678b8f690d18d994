"""Durability: kill -9 of a real writer process, torn tails, snapshots, incompatible dirs."""

from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from shared.replay import ReplayStore, StoreFormatError

SHAPE = (3, 16, 16)
EP_LEN = 37
ROOT = Path(__file__).resolve().parents[1]

FRAME_SRC = """
def frame(e, t):
    c = e * 1000 + t
    base = (np.arange(768) * (c % 7 + 1) + c) % 256
    return base.astype(np.uint8).reshape(3, 16, 16)
"""
exec(FRAME_SRC)  # the writer process and the checks share one frame function


def expected(g: int) -> tuple[np.ndarray, np.ndarray]:
    e, t = divmod(g, EP_LEN)
    fr = [frame(e, max(i, 0)) for i in range(t - 2, t + 2)]  # noqa: F821
    return np.concatenate(fr[:3]), np.concatenate(fr[1:])


WRITER = textwrap.dedent(
    """
    import sys
    import numpy as np
    from shared.replay import ReplayStore
    """
) + FRAME_SRC + textwrap.dedent(
    """
    store = ReplayStore(100_000, (3, 16, 16), 3, 2, data_dir=sys.argv[1], chunk_len=8,
                        fsync_interval_s=0.05)
    snap_every = int(sys.argv[2])
    e = store.num_inserted // 37
    store.truncate(e * 37)  # restart at a whole episode so index g maps to (g // 37, g % 37)
    while True:
        ep = store.begin_episode(frame(e, 0), actor_id=0, incarnation=e)
        for t in range(37):
            g = store.add(ep, np.array([t / 37, -t / 37]), float(e + t), 1.0, frame(e, t + 1),
                          t == 36, policy_version=e)
            print(g, flush=True)  # acknowledged: add() returned
            if snap_every and g % snap_every == snap_every - 1:
                store.snapshot(block=False)
        e += 1
    """
)


def run_and_kill(data_dir: Path, n_acks: int, snap_every: int) -> int:
    proc = subprocess.Popen(
        [sys.executable, "-c", WRITER, str(data_dir), str(snap_every)],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    last = -1
    try:
        for line in proc.stdout:
            last = int(line)
            if last + 1 >= n_acks:
                break
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.wait(10)
        if last < 0:
            pytest.fail(f"writer produced nothing: {proc.stderr.read()}")
    return last


def check_store(store: ReplayStore, last_acked: int) -> None:
    assert store.num_inserted >= last_acked + 1
    n = store.num_inserted
    for s in range(6):
        b = store.sample(128, np.random.default_rng(s))
        for i, g in enumerate(b["index"].tolist()):
            obs, nxt = expected(g)
            np.testing.assert_array_equal(b["obs"][i], obs)
            np.testing.assert_array_equal(b["next_obs"][i], nxt)
            e, t = divmod(g, EP_LEN)
            assert b["reward"][i] == e + t and b["step"][i] == t and b["policy_version"][i] == e
    assert store.sample(1, np.random.default_rng(0))["index"][0] < n


@pytest.mark.parametrize("snap_every", [0, 150])
def test_sigkill_loses_no_acknowledged_insert(tmp_path: Path, snap_every: int) -> None:
    d = tmp_path / "replay"
    last = run_and_kill(d, 400, snap_every)
    with ReplayStore(100_000, SHAPE, 3, 2, data_dir=d) as store:
        check_store(store, last)
        n1 = store.num_inserted
        assert len(store) == n1  # nothing evicted, nothing lost in the middle
    # A second life continues the same directory; killed again, mid-snapshot or not.
    last2 = run_and_kill(d, n1 + 300, snap_every)
    assert last2 >= n1
    with ReplayStore(100_000, SHAPE, 3, 2, data_dir=d) as store:
        check_store(store, last2)
        if snap_every:
            assert any(p.name.startswith("snapshot-") for p in d.iterdir())


def fill(store: ReplayStore, episodes: range) -> None:
    for e in episodes:
        ep = store.begin_episode(frame(e, 0), incarnation=e)  # noqa: F821
        for t in range(EP_LEN):
            store.add(ep, np.array([t / 37, -t / 37]), float(e + t), 1.0, frame(e, t + 1),  # noqa: F821
                      t == EP_LEN - 1, policy_version=e)


def test_torn_tail_is_dropped(tmp_path: Path) -> None:
    with ReplayStore(10_000, SHAPE, 3, 2, data_dir=tmp_path) as store:
        fill(store, range(3))
    seg = sorted(tmp_path.glob("log-*.bin"))[-1]
    size = seg.stat().st_size
    with open(seg, "r+b") as f:  # the last record half written
        f.truncate(size - 7)
    with ReplayStore(10_000, SHAPE, 3, 2, data_dir=tmp_path) as store:
        assert store.num_inserted == 3 * EP_LEN - 1
        check_store(store, 3 * EP_LEN - 2)
        fill(store, range(3, 4))  # appending after the cut works (episode 3 reuses e)
    with open(sorted(tmp_path.glob("log-*.bin"))[-1], "ab") as f:
        f.write(b"\x10\x00\x00\x00garbage")  # a header with a bad payload
    with ReplayStore(10_000, SHAPE, 3, 2, data_dir=tmp_path) as store:
        assert store.num_inserted == 4 * EP_LEN - 1


def test_corruption_in_middle_is_an_error(tmp_path: Path) -> None:
    with ReplayStore(10_000, SHAPE, 3, 2, data_dir=tmp_path) as store:
        fill(store, range(2))
    with ReplayStore(10_000, SHAPE, 3, 2, data_dir=tmp_path) as store:
        fill(store, range(2, 3))  # second segment
    first = sorted(tmp_path.glob("log-*.bin"))[0]
    data = bytearray(first.read_bytes())
    data[100] ^= 0xFF
    first.write_bytes(bytes(data))
    with pytest.raises(StoreFormatError, match="corrupt"):
        ReplayStore(10_000, SHAPE, 3, 2, data_dir=tmp_path)


def test_snapshot_roundtrip_intrinsic_truncate_eviction(tmp_path: Path) -> None:
    with ReplayStore(200, SHAPE, 3, 2, data_dir=tmp_path) as store:
        fill(store, range(8))  # 296 added, 96 evicted
        store.set_intrinsic(np.array([100, 150, 5]), np.array([1.0, 2.0, 3.0]))
        store.snapshot()
        fill(store, range(8, 9))
        store.set_intrinsic(np.array([300]), np.array([4.0]))
        store.truncate(320)
        before = store.sample(64, np.random.default_rng(0))
        stats = store.stats()
    assert len(list(tmp_path.glob("log-*.bin"))) == 1  # compacted
    with ReplayStore(200, SHAPE, 3, 2, data_dir=tmp_path) as store:
        # 333 added, head 133 when truncated to 320: evicted items stay evicted
        assert store.num_inserted == 320 and len(store) == 187
        after_stats = store.stats()
        for key in ("size", "frames", "frame_bytes", "episodes", "chunks"):
            assert after_stats[key] == stats[key], key
        b = store.sample(64, np.random.default_rng(0))
        check_store(store, 319)
        ints = dict(zip(b["index"].tolist(), b["intrinsic"].tolist(), strict=True))
        assert ints.get(150, 2.0) == 2.0 and ints.get(300, 4.0) == 4.0
    # Same contents after reopen: the same rng draws the same batch.
    for key in ("index", "obs", "intrinsic"):
        np.testing.assert_array_equal(b[key], before[key])


def hold_snapshot_writes(store: ReplayStore) -> tuple[threading.Event, threading.Event]:
    """(writing, release): a snapshot's file write sets `writing`, then waits for `release` (as a
    thread the scheduler holds back would), with the store's lock not held."""
    writing, release = threading.Event(), threading.Event()
    write = store._write_snapshot

    def held_write(seg: int, state: dict) -> None:
        writing.set()
        assert release.wait(60), "test never released the snapshot writer"
        write(seg, state)

    store._write_snapshot = held_write
    return writing, release


def test_snapshot_does_not_stall_inserts(tmp_path: Path) -> None:
    """Inserts complete while a snapshot's file is being written (it is written without the lock)."""
    with ReplayStore(50_000, SHAPE, 3, 2, data_dir=tmp_path) as store:
        fill(store, range(60))
        writing, release = hold_snapshot_writes(store)
        snap = threading.Thread(target=store.snapshot)
        snap.start()
        assert writing.wait(30), "snapshot never reached its write"
        inserter = threading.Thread(target=fill, args=(store, range(60, 63)))
        inserter.start()
        inserter.join(30)  # a snapshot holding the lock would keep these inserts waiting
        finished_while_writing = not inserter.is_alive()
        release.set()
        inserter.join()
        snap.join()
        assert finished_while_writing, "inserts waited for the snapshot's file write"
        assert store.num_inserted == 63 * EP_LEN
    with ReplayStore(50_000, SHAPE, 3, 2, data_dir=tmp_path) as store:
        check_store(store, 63 * EP_LEN - 1)  # the snapshot plus the log written during it


def test_an_episode_that_grows_while_its_snapshot_is_written_reopens(tmp_path: Path) -> None:
    """The snapshot holds an open episode as it stood when captured, not the chunks it gained
    while the file was being written (those are in the next log segment)."""
    with ReplayStore(50_000, SHAPE, 3, 2, data_dir=tmp_path, chunk_len=8) as store:
        fill(store, range(2))
        ep = store.begin_episode(frame(2, 0), incarnation=2)  # noqa: F821

        def add(t: int) -> None:
            store.add(ep, np.array([t / 37, -t / 37]), float(2 + t), 1.0, frame(2, t + 1),  # noqa: F821
                      t == EP_LEN - 1, policy_version=2)

        for t in range(10):
            add(t)
        writing, release = hold_snapshot_writes(store)
        store.snapshot(block=False)
        assert writing.wait(30), "snapshot never reached its write"
        for t in range(10, EP_LEN):  # new chunks of the open episode
            add(t)
        release.set()
        store._snapshot_thread.join()
    with ReplayStore(50_000, SHAPE, 3, 2, data_dir=tmp_path, chunk_len=8) as store:
        check_store(store, 3 * EP_LEN - 1)


def test_a_snapshot_that_fails_leaves_no_file_and_loses_nothing(tmp_path: Path, monkeypatch) -> None:
    import shared.replay.log as rlog

    class NoRoom:  # the snapshot's file cannot be put in place (a full disk)
        def __getattr__(self, name: str):  # noqa: ANN204
            return getattr(os, name)

        @staticmethod
        def replace(src, dst) -> None:  # noqa: ANN001
            raise OSError(errno.ENOSPC, "No space left on device")

    with ReplayStore(50_000, SHAPE, 3, 2, data_dir=tmp_path) as store:
        fill(store, range(3))
        monkeypatch.setattr(rlog, "os", NoRoom())
        store.snapshot(block=False)
        store._snapshot_thread.join()
        monkeypatch.undo()
        assert "No space left" in store.snapshot_error
        assert not list(tmp_path.glob("*.tmp")) and not list(tmp_path.glob("snapshot-*"))
        fill(store, range(3, 5))  # the log goes on
        store.snapshot(block=False)
        store._snapshot_thread.join()
        assert store.snapshot_error == ""
    with ReplayStore(50_000, SHAPE, 3, 2, data_dir=tmp_path) as store:
        check_store(store, 5 * EP_LEN - 1)


def test_a_failed_fsync_leaves_no_record_the_retry_would_repeat(tmp_path: Path) -> None:
    with ReplayStore(50_000, SHAPE, 3, 2, data_dir=tmp_path, fsync_interval_s=0.0) as store:
        fill(store, range(1))
        ep = store.begin_episode(frame(1, 0), incarnation=1)  # noqa: F821
        sync, failures = store._log.sync, [OSError(errno.EIO, "Input/output error")]

        def failing_once() -> None:
            if failures:
                raise failures.pop()
            sync()

        store._log.sync = failing_once
        for t in range(EP_LEN):
            args = (ep, np.array([t / 37, -t / 37]), float(1 + t), 1.0, frame(1, t + 1),  # noqa: F821
                    t == EP_LEN - 1)
            try:
                store.add(*args, policy_version=1)
            except OSError:  # as the replay service does: write it again
                store.add(*args, policy_version=1)
        assert not failures
    with ReplayStore(50_000, SHAPE, 3, 2, data_dir=tmp_path) as store:
        check_store(store, 2 * EP_LEN - 1)


def test_damage_inside_the_newest_segment_is_an_error_and_cuts_nothing(tmp_path: Path) -> None:
    with ReplayStore(10_000, SHAPE, 3, 2, data_dir=tmp_path) as store:
        fill(store, range(3))
    seg = sorted(tmp_path.glob("log-*.bin"))[-1]
    body = bytearray(seg.read_bytes())
    body[300] ^= 0x10  # one flipped bit inside an early record
    seg.write_bytes(bytes(body))
    with pytest.raises(StoreFormatError, match="corrupt at byte .* an intact record follows"):
        ReplayStore(10_000, SHAPE, 3, 2, data_dir=tmp_path)
    assert seg.read_bytes() == bytes(body)  # the acknowledged records after it are still there


def test_the_last_writes_before_a_pause_are_synced_when_due(tmp_path: Path) -> None:
    with ReplayStore(10_000, SHAPE, 3, 2, data_dir=tmp_path, fsync_interval_s=60.0) as store:
        store._last_sync = time.monotonic()  # just synced: the writes below are not due
        fill(store, range(1))
        store.sync_if_due()
        assert store._log.dirty
        store._last_sync -= 61.0  # a minute on, and no insert since
        store.sync_if_due()
        assert not store._log.dirty


def test_incompatible_directory_fails_clearly(tmp_path: Path) -> None:
    with ReplayStore(100, SHAPE, 3, 2, data_dir=tmp_path) as store:
        fill(store, range(1))
    with pytest.raises(StoreFormatError, match="differs"):
        ReplayStore(100, SHAPE, 3, 4, data_dir=tmp_path)
    with pytest.raises(StoreFormatError, match="'compression': 'lz4'.*differs.*'compression': 'zstd'"):
        ReplayStore(100, SHAPE, 3, 2, data_dir=tmp_path, compression="zstd")
    with pytest.raises(ValueError, match="unknown compression 'brotli'"):
        ReplayStore(100, SHAPE, 3, 2, compression="brotli")
    m = tmp_path / "MANIFEST.json"
    body = json.loads(m.read_text())
    body["version"] = 0
    m.write_text(json.dumps(body))
    with pytest.raises(StoreFormatError, match="version 0"):
        ReplayStore(100, SHAPE, 3, 2, data_dir=tmp_path)
    os.remove(m)
    with pytest.raises(StoreFormatError, match="no MANIFEST"):
        ReplayStore(100, SHAPE, 3, 2, data_dir=tmp_path)


def test_a_folder_written_before_prioritized_sampling_was_removed_still_opens(tmp_path: Path) -> None:
    """Its manifest names `prioritized: false` and its log may hold episode-close records."""
    from shared.replay import log as rlog
    from shared.replay.store import _CLOSE

    with ReplayStore(10_000, SHAPE, 3, 2, data_dir=tmp_path) as store:
        fill(store, range(2))
        ep = store.begin_episode(frame(9, 0), incarnation=9)  # noqa: F821
        store.add(ep, np.zeros(2), 0.0, 1.0, frame(9, 1), False)  # noqa: F821
    seg = sorted(tmp_path.glob("log-*.bin"))[-1]
    writer = rlog.LogWriter(seg)
    writer.append(_CLOSE, ep.to_bytes(8, "little"))  # what close_episode() used to write
    writer.close()
    m = tmp_path / "MANIFEST.json"
    body = json.loads(m.read_text())
    body["config"]["prioritized"] = False
    m.write_text(json.dumps(body))
    with ReplayStore(10_000, SHAPE, 3, 2, data_dir=tmp_path) as store:
        assert store.num_inserted == 2 * EP_LEN + 1
        assert store.stats()["open_episodes"] == 0  # the close record was applied
        b = store.get(np.arange(2 * EP_LEN))
        for g in range(2 * EP_LEN):
            obs, nxt = expected(g)
            np.testing.assert_array_equal(b["obs"][g], obs)
            np.testing.assert_array_equal(b["next_obs"][g], nxt)
        with pytest.raises(ValueError, match="closed"):
            store.add(ep, np.zeros(2), 0.0, 1.0, frame(9, 2), False)  # noqa: F821
    body["config"]["prioritized"] = True  # never reachable, but not silently read as uniform
    m.write_text(json.dumps(body))
    with pytest.raises(StoreFormatError, match="differs"):
        ReplayStore(10_000, SHAPE, 3, 2, data_dir=tmp_path)


def test_a_snapshot_is_due_every_so_many_inserts_counted_from_the_last_one_or_the_opening(
    tmp_path: Path,
) -> None:
    with ReplayStore(50_000, SHAPE, 3, 2, data_dir=tmp_path) as store:
        fill(store, range(1))  # 37 added
        assert not store.snapshot_if_due(40)
        fill(store, range(1, 2))  # 74
        assert store.snapshot_if_due(40)
        store._snapshot_thread.join()
        assert not store.snapshot_if_due(40)  # counted from the snapshot just taken
        fill(store, range(2, 3))  # 111: 37 since
        assert not store.snapshot_if_due(40)
    assert [p.name for p in sorted(tmp_path.glob("snapshot-*"))] == ["snapshot-000002.bin"]
    assert [p.name for p in sorted(tmp_path.glob("log-*"))] == ["log-000002.bin"]  # the one after it
    with ReplayStore(50_000, SHAPE, 3, 2, data_dir=tmp_path) as store:
        fill(store, range(3, 4))  # 37 since the opening, 74 since the snapshot
        assert not store.snapshot_if_due(40)
        check_store(store, 4 * EP_LEN - 1)
    with ReplayStore(50_000, SHAPE, 3, 2) as memory:  # nothing to compact
        fill(memory, range(2))
        assert not memory.snapshot_if_due(1)


@pytest.mark.parametrize("snapshot", [False, True])
def test_a_reopening_stopped_part_way_changes_nothing_and_the_next_reads_it_all(tmp_path, snapshot):
    # A stop signal while a replay reopens its store (its `stop` says True from some record on):
    # it ends with OpenStopped, and the next opening finds every row, in the snapshot or the log.
    from shared.replay.store import STOP_CHECK_EVERY, OpenStopped

    rows = 4 * STOP_CHECK_EVERY
    with ReplayStore(10_000, SHAPE, 3, 2, data_dir=tmp_path) as store:
        for e in range(rows // EP_LEN + 1):
            ep = store.begin_episode(frame(e, 0))  # noqa: F821
            for t in range(EP_LEN):
                store.add(ep, np.zeros(2), 1.0, 1.0, frame(e, t + 1), t == EP_LEN - 1)  # noqa: F821
        if snapshot:
            store.snapshot()
        written = store.num_inserted
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    asked = []
    looks = 1 if snapshot else 3  # the log: part way through it

    def stop() -> bool:
        asked.append(True)
        return len(asked) == looks

    with pytest.raises(OpenStopped, match="read in part"):
        ReplayStore(10_000, SHAPE, 3, 2, data_dir=tmp_path, stop=stop)
    assert len(asked) == looks
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before
    with ReplayStore(10_000, SHAPE, 3, 2, data_dir=tmp_path) as store:
        assert store.num_inserted == written
        index = np.arange(written - 5, written)
        newest = np.stack([expected(g)[1][-3:] for g in index])
        assert np.array_equal(store.get(index)["next_obs"][:, -3:], newest)
