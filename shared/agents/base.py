"""What every agent offers: act, update, score, and save/restore its whole state."""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol

import numpy as np
import torch

from shared.config import AgentConfig
from shared.nets import float_channels_last, pixel_dtype

if TYPE_CHECKING:
    from shared.agents.cuda_graph import GraphedUpdate


class Agent(Protocol):
    """The learning core. No I/O inside: runners feed it batches and save its state."""

    device: torch.device
    uses_intrinsic: bool
    num_updates: int
    burst_updates: int  # shared.schedule.burst_updates: set by make_updating_agent

    def act(self, obs: np.ndarray, explore: bool, rng: np.random.Generator) -> np.ndarray:
        """One action in [-1, 1] for one (C, H, W) uint8 observation."""
        ...

    def update(self, batch: dict[str, torch.Tensor]) -> dict[str, float]:
        """One gradient update on a batch already on `device`; returns its losses."""
        ...

    def update_step(self, batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """`update` with its losses left on the device: no step of it waits for the device."""
        ...

    def score(
        self, obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor
    ) -> dict[str, torch.Tensor]:
        """Intrinsic rewards of a batch of transitions: novelty, surprise and their weighted sum."""
        ...

    def state_dict(self) -> dict:
        """Every network, optimizer and counter (not RNG states: runners own those)."""
        ...

    def load_state_dict(self, state: dict) -> None: ...

    def policy_state_dict(self) -> dict[str, torch.Tensor]:
        """The weights an actor needs to act."""
        ...

    def load_policy_state_dict(self, state: dict[str, torch.Tensor]) -> None: ...


def module_state(state: dict[str, torch.Tensor], prefix: str) -> dict[str, torch.Tensor]:
    """The tensors of `state` under `prefix.` (as `policy_state_dict` names them), without it."""
    head = prefix + "."
    return {k[len(head):]: v for k, v in state.items() if k.startswith(head)}


def check_fits(expected: dict[str, torch.Tensor], given: dict, what: str) -> None:
    """ValueError unless `given` has exactly `expected`'s tensors, each of its shape and a floating
    dtype where it is floating: checked whole before anything is loaded, as load_state_dict
    copies every tensor that fits before it raises on one that does not."""
    missing, extra = sorted(set(expected) - set(given)), sorted(set(given) - set(expected))
    if missing or extra:
        raise ValueError(f"{what}: missing {missing[:4]}, unexpected {extra[:4]}")
    for key, want in expected.items():
        got = given[key]
        if not isinstance(got, torch.Tensor) or got.shape != want.shape:
            shape = tuple(got.shape) if isinstance(got, torch.Tensor) else type(got).__name__
            raise ValueError(f"{what}: {key} is {shape}, expected {tuple(want.shape)}")
        if want.is_floating_point() != got.is_floating_point():
            raise ValueError(f"{what}: {key} is {got.dtype}, expected {want.dtype}")


def to_obs_tensor(obs: np.ndarray, device: torch.device) -> torch.Tensor:
    """A (C, H, W) uint8 observation as a (1, C, H, W) uint8 tensor on `device`; the cast happens there."""
    return torch.as_tensor(obs, device=device).unsqueeze(0)


def float_pixels(batch: dict[str, torch.Tensor], precision: str = "fp32") -> dict[str, torch.Tensor]:
    """The batch with its frame stacks cast to the pixel networks' dtype (`shared.nets.pixel_dtype`),
    channels-last: the form every encoder pass reads. An update encodes the same stacks several
    times (critic, target, autoencoder, actor, ensemble), and casting the uint8 stacks once instead
    of at each pass is the same arithmetic with less memory traffic."""
    out = dict(batch)
    for key in ("obs", "next_obs"):
        out[key] = float_channels_last(batch[key], pixel_dtype(precision))
    return out


def batch_to_device(batch: dict[str, np.ndarray], device: torch.device) -> dict[str, torch.Tensor]:
    """Move a sampled batch to the device; uint8 frames travel as uint8 and are cast there."""
    keys = ("obs", "next_obs", "action", "reward", "discount", "intrinsic")
    pin = device.type == "cuda"
    out = {}
    for key in keys:
        t = torch.from_numpy(batch[key])
        out[key] = (t.pin_memory() if pin else t).to(device, non_blocking=pin)
    return out


def collect_action(
    agent: Agent, obs: np.ndarray, warming_up: bool, rng: np.random.Generator, action_dim: int
) -> np.ndarray:
    """The action an actor takes while collecting: uniform during warm-up, then policy + noise."""
    if warming_up:
        return rng.uniform(-1.0, 1.0, action_dim).astype(np.float32)
    return agent.act(obs, explore=True, rng=rng)


def soft_update(target: torch.nn.Module, online: torch.nn.Module, tau: float) -> None:
    with torch.no_grad():
        for t, o in zip(target.parameters(), online.parameters(), strict=True):
            t.lerp_(o, tau)


def channels_last(modules) -> None:
    """Conv weights in channels-last layout, the one oneDNN (CPU) and cuDNN (GPU) run fastest."""
    for module in modules:
        module.to(memory_format=torch.channels_last)


def adam(params, lr: float, weight_decay: float = 0.0, betas=(0.9, 0.999)) -> torch.optim.Adam:
    # The fused kernel (CPU and CUDA) updates every tensor in one pass, where foreach makes
    # several passes over the large fc layers; the numbers agree with foreach's to round-off.
    return torch.optim.Adam(list(params), lr=lr, weight_decay=weight_decay, betas=betas, fused=True)


def optimizer_step(optimizers: list[torch.optim.Optimizer], loss: torch.Tensor) -> torch.Tensor:
    """Zero, backpropagate once, step each optimizer (several when one loss trains several parts).

    A non-finite loss or gradient skips the step: a NaN never reaches the weights or Adam's
    moments, and the step count stays. The test and the skip both run on the device (the fused
    Adam kernel's `found_inf`, as mixed-precision training uses it), so a step never waits for
    the device: the update can be captured as a CUDA graph. Returns the device's 1.0 (skipped)
    or 0.0; the skips add up in each optimizer's `nonfinite_skips` tensor.
    """
    for opt in optimizers:
        opt.zero_grad(set_to_none=True)
    loss.backward()
    grads = [p.grad for opt in optimizers for group in opt.param_groups for p in group["params"]
             if p.grad is not None]
    finite = torch.isfinite(loss.detach()).all()
    if grads:
        finite = finite & torch.isfinite(torch.stack(torch._foreach_norm(grads))).all()
    skipped = (~finite).float()
    for opt in optimizers:
        if not all(group.get("fused") for group in opt.param_groups):
            raise TypeError("optimizer_step needs fused Adam (shared.agents.base.adam): its kernel skips "
                            "a step on the device")
        opt.found_inf = skipped
        opt.step()
        counter = getattr(opt, "nonfinite_skips", None)
        if counter is None:
            opt.nonfinite_skips = skipped.clone()
        else:
            counter.add_(skipped)
    return skipped


def nonfinite_skips(agent: object) -> int:
    """Optimizer steps the agent skipped for a non-finite loss or gradient (optimizer_step)."""
    optimizers = agent._optimizers().values() if hasattr(agent, "_optimizers") else []
    counts = [opt.nonfinite_skips for opt in optimizers if hasattr(opt, "nonfinite_skips")]
    return int(torch.stack(counts).sum()) if counts else 0


def metric_floats(metrics: dict[str, torch.Tensor]) -> dict[str, float]:
    """An update's metrics (0-d tensors on the device) as floats, with one device-to-host copy."""
    if not metrics:
        return {}
    values = torch.stack([v.detach().float() for v in metrics.values()]).tolist()
    return dict(zip(metrics, values, strict=True))


class ModuleStateMixin:
    """state_dict / policy_state_dict from the named modules and optimizers an agent lists, and
    `update` from the agent's `update_step`.

    An agent lists its parts once (`_modules`, `_optimizers`, `_policy_modules`);
    saving, loading and the weights actors receive all follow from that list.
    """

    num_updates: int
    config: AgentConfig
    _graphed: GraphedUpdate | None = None
    # The run's first updates that a warm-up burst makes at one env step (shared.schedule): SAC-AE
    # steps its actor and targets by the env step, so those take that step's path all alike.
    burst_updates: int = 0
    # The autoencoder that the evaluator's pictures reconstruct through, as the `_modules` names of
    # its encoder and decoder; None for an agent without a decoder.
    view: tuple[str, str] | None = None

    def update_step(self, batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        raise NotImplementedError

    def update_period(self) -> int:
        """After how many updates the path of `update_step` repeats (a CUDA graph per phase): the
        delayed actor's period, unless an agent has more on a schedule."""
        return self.config.policy_delay

    def check_batch(self, batch: dict[str, torch.Tensor]) -> None:
        """Raise if the batch cannot be trained on (a test that reads the device, so not in `update_step`)."""

    def update(self, batch: dict[str, torch.Tensor]) -> dict[str, float]:
        """One update, eager or replayed from its CUDA graph (`cuda_graph`); its losses as floats."""
        self.check_batch(batch)
        if not self.config.cuda_graph:
            return metric_floats(self.update_step(batch))
        if self._graphed is None:
            from shared.agents.cuda_graph import GraphedUpdate

            self._graphed = GraphedUpdate(self)
        return metric_floats(self._graphed(batch))

    def _modules(self) -> dict[str, torch.nn.Module]:
        raise NotImplementedError

    def _optimizers(self) -> dict[str, torch.optim.Optimizer]:
        raise NotImplementedError

    def _policy_modules(self) -> dict[str, torch.nn.Module]:
        raise NotImplementedError

    def state_dict(self) -> dict:
        state = {name: m.state_dict() for name, m in self._modules().items()}
        state |= {name: o.state_dict() for name, o in self._optimizers().items()}
        state["num_updates"] = self.num_updates
        return state

    def load_state_dict(self, state: dict) -> None:
        """ValueError, with nothing loaded, unless every network's tensors fit this agent's."""
        modules, optimizers = self._modules(), self._optimizers()
        for name, module in modules.items():
            if not isinstance(state.get(name), dict):
                raise ValueError(f"the state has no {name!r}: is it another algorithm's?")
            check_fits(module.state_dict(), state[name], name)
        known = {*modules, *optimizers}
        if extra := sorted(k for k, v in state.items() if isinstance(v, dict) and k not in known):
            raise ValueError(f"the state holds {extra}, which this agent has not: is it another algorithm's?")
        self._graphed = None  # the optimizers' new state tensors are not the captured ones
        for name, module in modules.items():
            module.load_state_dict(state[name])
        for name, opt in self._optimizers().items():
            opt.load_state_dict(state[name])
        self.num_updates = int(state["num_updates"])

    def policy_state_dict(self) -> dict[str, torch.Tensor]:
        return {
            f"{prefix}.{key}": value
            for prefix, module in self._policy_modules().items()
            for key, value in module.state_dict().items()
        }

    def load_policy_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        """ValueError, with nothing loaded, unless the tensors are exactly this agent's policy's."""
        check_fits(self.policy_state_dict(), state, "the policy's weights")
        for prefix, module in self._policy_modules().items():
            module.load_state_dict(module_state(state, prefix))

    def view_modules(self) -> tuple[torch.nn.Module, torch.nn.Module] | None:
        """The autoencoder's encoder and decoder (`view`), or None."""
        if self.view is None:
            return None
        modules = self._modules()
        return modules[self.view[0]], modules[self.view[1]]

    def view_extras(self) -> dict[str, torch.nn.Module]:
        """The autoencoder's modules that the policy's weights do not carry, by name: what the
        evaluator's weights add to the policy's (the decoder; SAC-AE's critic encoder as well, which
        its decoder reads where its policy acts through the actor's)."""
        if self.view is None:
            return {}
        modules, policy = self._modules(), list(self._policy_modules().values())
        return {name: modules[name] for name in self.view if all(modules[name] is not m for m in policy)}

    def view_state_dict(self) -> dict[str, torch.Tensor]:
        """`view_extras`' tensors, each under its module's name as a prefix."""
        return {f"{name}.{key}": value for name, module in self.view_extras().items()
                for key, value in module.state_dict().items()}
