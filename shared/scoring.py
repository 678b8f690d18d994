"""Collect-timing intrinsic rewards: each transition scored once, soon after it is stored.

The paper scores a transition when it is collected, with the networks of that
moment, and stores the score with it. Both runners do that through one
`IntrinsicScorer` over a replay client: `nasa train` after every environment
step (one new row), the learner service before every update (the oldest rows
not scored yet, up to a batch). The replay stores every row unscored (NaN);
the scorer owns the rule that warm-up rows (global index < warmup_steps) score
0, as the reference stores no bonus before learning starts. A training batch
that still brings an unscored row (the scorer fell behind, or a write-back was
lost to a replay restart) is scored before the update uses it, so an update
never sees NaN. A small cache keeps the first score of a row whose write-back
has not landed yet, so no row is scored twice with different networks. A score
is stored finite and within the replay's reward bound: one that is not finite
(diverged networks) scores 0 (and is counted, `zeroed`), and a larger one is
clipped, as the replay refuses a write-back with either and the row would stay
unscored. The running means and counts go into the learner's checkpoint
(`state`), so a resumed run's /status goes on with the whole run's.

Over the wire (the learner service) asking the replay for the owed rows is a
round trip the update would wait on; `fetching_ahead` asks from a thread
instead, so the rows are on hand when the next update scores them (one or two
updates later than a blocking ask: the learner's updates and the actors' steps
are not in lockstep there anyway).
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict, deque
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np
import torch

from shared import wire
from shared.agents import Agent
from shared.config import TrainConfig
from shared.replay.client import Batch, ReplayClient


def collect_scoring(agent: Agent, config: TrainConfig) -> bool:
    """Whether transitions get a stored intrinsic score (nasa_td3 with collect timing)."""
    return agent.uses_intrinsic and config.agent.intrinsic_timing == "collect"


class IntrinsicScorer:
    def __init__(self, agent: Agent, client: ReplayClient, warmup_steps: int, batch_size: int,
                 cache_size: int = 100_000, max_abs_score: float = wire.Bounds.max_abs_reward) -> None:
        self.agent = agent
        self.client = client
        self.warmup_steps = warmup_steps
        self.batch_size = batch_size
        self.cache_size = cache_size
        self.max_abs_score = max_abs_score  # the replay refuses scores beyond its reward bound
        self.scored = 0  # transitions whose score was computed
        self.scored_at_first_sample = 0  # of those, rows a training batch brought first
        self.zeroed = 0  # of those, rows whose score came out non-finite and was stored as 0
        self.means: dict[str, float | None] = {"novelty": None, "surprise": None}
        self._after = 0  # every row below this index was scored (or seen scored)
        self._cache: OrderedDict[int, float] = OrderedDict()
        self._sums = {"novelty": 0.0, "surprise": 0.0}
        self._count = 0
        self._fetched: deque[tuple[Batch | None, int]] = deque()  # fetching_ahead's answers, in order
        self._fetching = False
        self._fetch_error: BaseException | None = None

    def score_new(self) -> int:
        """Score up to one batch of the oldest rows not scored yet (while fetching ahead: the rows
        fetched so far, without waiting); returns how many rows it saw."""
        zeros = 0
        warm = min(self.client.num_inserted, self.warmup_steps)
        if self._after < warm:  # warm-up rows score 0: no frames needed
            index = np.arange(self._after, warm)
            self.client.set_intrinsic(index, np.zeros(len(index), np.float32))
            self._after, zeros = warm, len(index)
        if self._fetch_error is not None:
            raise RuntimeError("the thread fetching owed rows failed") from self._fetch_error
        if self._fetched or self._fetching:
            seen = 0
            while self._fetched:
                seen += self._score_owed(*self._fetched.popleft())
            return zeros + seen
        if self._after >= self.client.num_inserted:
            # Nothing stored since the last scan: no query (the learner service would otherwise ask
            # the replay before every update). Its count comes with every batch the replay serves,
            # so a row is found at the first update after a batch that could hold it.
            return zeros
        return zeros + self._score_owed(*self.client.unscored(self._after, self.batch_size))

    def _score_owed(self, batch: Batch | None, seen: int) -> int:
        """Score what `client.unscored` answered; every row in [_after, seen) it left out is scored
        or evicted."""
        if batch is None:
            self._after = max(self._after, seen)
            return 0
        self.score_batch(batch, on_arrival=True)
        self._after = max(self._after, int(batch["index"].max()) + 1)
        return len(batch["index"])

    @contextmanager
    def fetching_ahead(self, idle_s: float = 0.005, depth: int = 4) -> Iterator[None]:
        """Inside the block a thread asks the replay for the owed rows as they are stored, and
        score_new scores what it has fetched without asking itself. On exit the thread stops;
        what it fetched is still scored by the next score_new (or catch_up)."""
        stop = threading.Event()

        def fetch() -> None:
            after = max(self._after, self.warmup_steps)  # warm-up rows need no frames (score_new)
            try:
                while not stop.is_set():
                    if len(self._fetched) >= depth or after >= self.client.num_inserted:
                        stop.wait(idle_s)
                        continue
                    batch, seen = self.client.unscored(after, self.batch_size)
                    if batch is None and seen <= after:  # no answer: ask again later, not at once
                        stop.wait(0.1)
                        continue
                    self._fetched.append((batch, seen))
                    after = max(after, seen if batch is None else int(batch["index"].max()) + 1)
            except BaseException as err:  # noqa: BLE001 - score_new raises it in the learner's thread
                self._fetch_error = err

        thread = threading.Thread(target=fetch, name="score-ahead", daemon=True)
        self._fetching = True
        thread.start()
        try:
            yield
        finally:
            stop.set()
            # An ask in flight may take the client's timeout; one it answers late is still scored
            # right (a row scored since comes from the cache).
            thread.join(timeout=1.0)
            self._fetching = False

    def catch_up(self) -> None:
        """Score every row stored so far (the end of a run: the last arrivals); not while
        fetching_ahead, whose thread may not have fetched them yet."""
        if self._fetching:
            raise RuntimeError("catch_up inside fetching_ahead")
        while self.score_new():
            pass

    def score_batch(self, batch: Batch, on_arrival: bool = False) -> None:
        """Fill the batch's unscored rows in place and write their scores back to the replay.

        `on_arrival`: the rows come from score_new; else a training batch brought them first.
        A row drawn twice into one batch is scored once.
        """
        rows = np.flatnonzero(np.isnan(batch["intrinsic"]))
        if len(rows) == 0:
            return
        index, values = batch["index"], batch["intrinsic"]
        todo = []
        for r in rows.tolist():
            i = int(index[r])
            if i < self.warmup_steps:
                values[r] = 0.0
            elif i in self._cache:
                values[r] = self._cache[i]
            else:
                todo.append(r)
        if todo:
            self._compute(batch, np.array(todo), on_arrival)
        self.client.set_intrinsic(index[rows], values[rows])

    def _compute(self, batch: Batch, rows: np.ndarray, on_arrival: bool) -> None:
        index = batch["index"]
        _, first, inverse = np.unique(index[rows], return_index=True, return_inverse=True)
        sel = rows[first]  # one row per distinct transition
        d = self.agent.device
        threads = torch.get_num_threads()
        if len(sel) == 1 and d.type == "cpu":
            # One row is no faster on more threads, and in `nasa up` on 2 cores each op would
            # wait for the learner's second thread, which shares its core with other services.
            torch.set_num_threads(1)
        try:
            scores = self.agent.score(
                torch.as_tensor(batch["obs"][sel], device=d),
                torch.as_tensor(batch["action"][sel], device=d),
                torch.as_tensor(batch["next_obs"][sel], device=d),
            )
        finally:
            torch.set_num_threads(threads)
        self.zeroed += int((~torch.isfinite(scores["intrinsic"])).sum())  # /status shows how many
        scores = {k: self._bounded(v) for k, v in scores.items()}
        values = scores["intrinsic"].float().cpu().numpy()
        batch["intrinsic"][rows] = values[inverse]
        for i, v in zip(index[sel].tolist(), values.tolist(), strict=True):
            self._cache[i] = v
        while len(self._cache) > self.cache_size:
            self._cache.popitem(last=False)
        self._account(scores, len(sel), on_arrival)

    def _bounded(self, values: torch.Tensor) -> torch.Tensor:
        """Non-finite scores as 0, the rest clipped to the replay's bound."""
        b = self.max_abs_score
        return torch.nan_to_num(values, nan=0.0, posinf=0.0, neginf=0.0).clamp(-b, b)

    def _account(self, scores: dict[str, torch.Tensor], n: int, on_arrival: bool) -> None:
        total = self.scored + n
        for name in ("novelty", "surprise"):
            batch_sum = scores[name].double().sum().item()
            self._sums[name] += batch_sum
            old = self.means[name]
            mean = batch_sum / n
            self.means[name] = mean if old is None else old + (mean - old) * n / total
        self._count += n
        self.scored = total
        if not on_arrival:
            self.scored_at_first_sample += n

    def take_episode_means(self) -> dict[str, float]:
        """Mean novelty and surprise per transition scored since the previous call (train.csv)."""
        if self._count == 0:
            return {}
        means = {f"{k}_mean": v / self._count for k, v in self._sums.items()}
        self._sums = {"novelty": 0.0, "surprise": 0.0}
        self._count = 0
        return means

    def status(self) -> dict:
        return {
            "novelty_mean": self.means["novelty"],
            "surprise_mean": self.means["surprise"],
            "scored": self.scored,
            "scored_at_first_sample": self.scored_at_first_sample,
            "zeroed": self.zeroed,
        }

    def state(self) -> dict:
        """The running means and counts, for the checkpoint: a resumed run's /status goes on with
        the whole run's, not those of the scores since the restart."""
        return {"means": dict(self.means), "scored": self.scored,
                "scored_at_first_sample": self.scored_at_first_sample, "zeroed": self.zeroed}

    def load_state(self, state: dict) -> None:
        """`state()` of a checkpoint; a part it lacks (an older checkpoint) stays as it is."""
        means = state.get("means", {})
        for name in self.means:
            if isinstance(value := means.get(name), float | int) and math.isfinite(value):
                self.means[name] = float(value)
        for name in ("scored", "scored_at_first_sample", "zeroed"):
            if isinstance(value := state.get(name), int) and value >= 0:
                setattr(self, name, value)
