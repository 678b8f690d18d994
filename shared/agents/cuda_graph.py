"""An agent's update replayed as captured CUDA graphs (`agent.cuda_graph`).

On a GPU the eager update is bound by the host: it launches hundreds of small
kernels, each from Python, and the device waits between them. A CUDA graph
records those kernels once and replays them with one launch; the arithmetic
is the same.

- The update takes one of `update_period()` paths (the delayed actor, the
  ensemble's schedule), so there is one graph per phase of that period.
- The graphs read the batch from static tensors it is copied into, and write
  their losses to the tensors the capture returned; each replay overwrites them.
- The first updates run eagerly on a side stream, as PyTorch's whole-network
  capture does: the optimizers' states and the libraries' workspaces exist
  before anything is captured.
- The update's Python runs once, at capture, so a replay counts its update here.
- `update_step` never waits for the device (a skipped optimizer step is decided
  there too: `optimizer_step`), which is what capture needs.
- Loading a state replaces the optimizers' state tensors that the graphs point
  to: the agent then drops its graphs (`ModuleStateMixin.load_state_dict`) and
  captures again.
- A capture that fails (a GPU, driver or torch version that cannot capture some
  step) leaves the run eager, with a warning, rather than ending it; the update
  count and which parameters take gradients are as they were before it.
"""

from __future__ import annotations

import warnings
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from typing import Any

import torch


class GraphedUpdate:
    def __init__(self, agent: Any) -> None:  # noqa: ANN401 -- an agent of shared.agents (make_agent
        # refuses cuda_graph without a CUDA device)
        self.agent = agent
        self.period = agent.update_period()
        # Each phase runs eagerly at least twice, so every optimizer has stepped (and made its
        # state) before its step is captured.
        self.warmup = max(3, 2 * self.period)
        self.eager_updates = 0
        self.side = torch.cuda.Stream(agent.device)
        self.static: dict[str, torch.Tensor] = {}
        self.graphs: dict[int, tuple[torch.cuda.CUDAGraph, dict[str, torch.Tensor]]] = {}
        self.failed = ""  # why a capture failed; the updates are then eager for good

    def __call__(self, batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        if self.failed:
            return self.agent.update_step(batch)
        if self.agent.num_updates < self.agent.burst_updates:
            # A warm-up burst's updates may all take one path whatever their phase (SAC-AE's):
            # eager, once per run, rather than a graph captured for another phase.
            return self._on_side_stream(batch)
        if self.eager_updates < self.warmup:
            self.eager_updates += 1
            return self._on_side_stream(batch)
        self._copy_in(batch)
        phase = self.agent.num_updates % self.period
        if phase not in self.graphs:
            try:
                self.graphs[phase] = self._capture()
            except RuntimeError as err:  # a GPU, driver or torch that cannot capture: slower, not dead
                self.failed = f"{type(err).__name__}: {err}"
                self.graphs.clear()
                warnings.warn(f"CUDA graph capture failed; updates run eagerly from now on ({self.failed})",
                              RuntimeWarning, stacklevel=2)
                return self.agent.update_step(batch)
        graph, losses = self.graphs[phase]
        graph.replay()
        self.agent.num_updates += 1
        return losses

    def _on_side_stream(self, batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        main = torch.cuda.current_stream(self.agent.device)
        self.side.wait_stream(main)
        with torch.cuda.stream(self.side):
            losses = self.agent.update_step(batch)
        main.wait_stream(self.side)
        return losses

    def _copy_in(self, batch: dict[str, torch.Tensor]) -> None:
        if not self.static:
            self.static = {key: value.clone() for key, value in batch.items()}
            return
        if batch.keys() != self.static.keys():
            raise ValueError(f"a graphed update's batch has the keys {sorted(self.static)}, "
                             f"got {sorted(batch)}")
        for key, value in batch.items():
            static = self.static[key]
            if value.shape != static.shape or value.dtype != static.dtype:
                raise ValueError(f"a graphed update's batch[{key!r}] is {tuple(static.shape)} "
                                 f"{static.dtype}, got {tuple(value.shape)} {value.dtype}")
            static.copy_(value, non_blocking=True)

    def _capture(self) -> tuple[torch.cuda.CUDAGraph, dict[str, torch.Tensor]]:
        graph = torch.cuda.CUDAGraph()
        count = self.agent.num_updates
        # A step may freeze a network while it runs (the actor's step, the critic's parameters): a
        # capture that stops inside it must not leave it frozen for the eager updates after it.
        grads = [(p, p.requires_grad) for m in self.agent._modules().values() for p in m.parameters()]
        try:
            # The warm-up's stream: libraries cache their handles and workspaces per stream, and
            # creating one mid-capture fails. thread_local: the learner's prefetch thread keeps
            # copying batches to the device meanwhile.
            with capturable(self.agent._optimizers().values()), \
                    torch.cuda.graph(graph, stream=self.side, capture_error_mode="thread_local"):
                losses = self.agent.update_step(self.static)
        finally:
            self.agent.num_updates = count  # capture ran no kernel: the update is the replay's
            for param, requires_grad in grads:
                param.requires_grad_(requires_grad)
        return graph, losses


@contextmanager
def capturable(optimizers: Iterable[torch.optim.Optimizer]) -> Iterator[None]:
    """Optimizers whose step may be captured; only while capturing, so eager steps and the
    checkpoints' optimizer states stay as they are without graphs."""
    groups = [group for opt in optimizers for group in opt.param_groups]
    before = [group["capturable"] for group in groups]
    for group in groups:
        group["capturable"] = True
    try:
        yield
    finally:
        for group, value in zip(groups, before, strict=True):
            group["capturable"] = value
