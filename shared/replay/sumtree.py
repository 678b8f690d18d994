"""Array sum tree for proportional prioritized sampling, vectorised over a batch.

A batch of B lookups walks the tree level by level with numpy (log2(capacity)
steps of B-wide work), so a batch costs microseconds, not the tens of
milliseconds of a per-item Python tree at 1M entries.
"""

from __future__ import annotations

import numpy as np


class SumTree:
    def __init__(self, capacity: int) -> None:
        self.size = 1
        while self.size < capacity:
            self.size *= 2
        self.tree = np.zeros(2 * self.size, np.float64)

    def set(self, pos: np.ndarray, value: np.ndarray) -> None:
        pos = np.asarray(pos, np.int64)
        value = np.broadcast_to(np.asarray(value, np.float64), pos.shape)
        node = np.unique(pos + self.size)
        # Last write wins for duplicate positions (np.unique sorts, so map values by position).
        last = {int(p): float(v) for p, v in zip(pos, value, strict=True)}
        self.tree[node] = [last[int(n - self.size)] for n in node]
        node //= 2
        while node.size and node[0] >= 1:
            node = np.unique(node)
            self.tree[node] = self.tree[2 * node] + self.tree[2 * node + 1]
            if node[0] == 1:
                break
            node //= 2

    def get(self, pos: np.ndarray) -> np.ndarray:
        return self.tree[np.asarray(pos, np.int64) + self.size]

    @property
    def total(self) -> float:
        return float(self.tree[1])

    def find(self, mass: np.ndarray) -> np.ndarray:
        """Leaf positions whose prefix-sum interval holds each mass in [0, total)."""
        node = np.ones(len(mass), np.int64)
        mass = np.array(mass, np.float64)
        while node[0] < self.size:
            left = 2 * node
            lv = self.tree[left]
            go_right = mass >= lv
            mass = np.where(go_right, mass - lv, mass)
            node = np.where(go_right, left + 1, left)
        return node - self.size
