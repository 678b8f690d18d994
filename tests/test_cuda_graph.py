"""`agent.cuda_graph`: what can be tested without a GPU.

- Capture needs an update that never waits for the device: every agent's `update_step`
  is run under modes that see each read of a device value by the host (ops and copies to
  the host), taking the GPU's code where it has its own (SSIM, random_shift's crop).
- `GraphedUpdate`'s bookkeeping (warm-up, one graph per phase, static inputs and
  outputs, the update count, capturing again after a load) runs against an emulator of
  torch.cuda's graph API: capture runs the Python once and leaves no trace (as a capture
  runs no kernel), replay runs the captured step again on the static inputs and writes
  the captured outputs. The graphed agent must then train exactly as the eager one.
The capture itself runs on a GPU only: tests/test_cuda.py.
"""

from __future__ import annotations

import contextlib
import copy

import pytest
import torch
from torch.overrides import TorchFunctionMode
from torch.utils._python_dispatch import TorchDispatchMode

from shared import augment, intrinsic
from shared.agents import AGENTS, make_agent
from shared.agents.cuda_graph import GraphedUpdate, capturable
from shared.config import ConfigError, agent_defaults
from tests.test_agents import ACTION_DIM, OBS_SHAPE, SMALL, random_batch

# Ops whose result the host must read: `.item()`, `bool()`, and ops whose output size depends on values.
HOST_READS = {"_local_scalar_dense", "nonzero", "masked_select", "unique", "_unique2", "equal"}

VARIANTS = {
    "nasa_td3": ("nasa_td3", {}),
    "nasa_td3+fresh": ("nasa_td3", {"intrinsic_timing": "fresh"}),
    "nasa_td3+shared_encoder_pass": ("nasa_td3", {"shared_encoder_pass": True}),
    "nasa_td3+ensemble_every_3": ("nasa_td3", {"ensemble_every": 3}),
    "nasa_td3+random_shift": ("nasa_td3", {"random_shift": 2}),
    "td3_ae": ("td3_ae", {}),
    "pixel_td3": ("pixel_td3", {}),
    "sac_ae": ("sac_ae", {}),
}


# Tensor methods that copy a tensor to the host: on the CPU they reach no op the dispatch mode sees
# (`tolist` reads the memory itself, `cpu` returns the tensor), on a GPU each waits for the device.
HOST_METHODS = {"tolist", "numpy", "cpu"}


class HostReads(TorchDispatchMode):
    def __init__(self) -> None:
        super().__init__()
        self.seen: list[str] = []
        self._methods = _HostMethods(self.seen)

    def __enter__(self) -> HostReads:
        self._methods.__enter__()
        return super().__enter__()

    def __exit__(self, *exc: object) -> None:
        super().__exit__(*exc)
        self._methods.__exit__(*exc)

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):  # noqa: ANN001, ANN204
        if func.overloadpacket.__name__ in HOST_READS:
            self.seen.append(str(func))
        return func(*args, **(kwargs or {}))


class _HostMethods(TorchFunctionMode):
    def __init__(self, seen: list[str]) -> None:
        super().__init__()
        self.seen = seen

    def __torch_function__(self, func, types, args=(), kwargs=None):  # noqa: ANN001, ANN204
        if getattr(func, "__name__", "") in HOST_METHODS:
            self.seen.append(f"Tensor.{func.__name__}")
        return func(*args, **(kwargs or {}))


def agent_of(variant: str, **more):  # noqa: ANN003, ANN201
    algo, overrides = VARIANTS[variant]
    config = agent_defaults(algo)
    for key, value in {**SMALL, **overrides, **more}.items():
        setattr(config, key, value)
    # The class itself: make_agent refuses cuda_graph on the CPU, and the emulator stands in here.
    return AGENTS[algo](OBS_SHAPE, ACTION_DIM, config, torch.device("cpu"))


def test_the_host_read_detector_sees_item_and_bool_and_copies_to_the_host():
    with HostReads() as reads:
        x = torch.ones(3)
        x.sum().item()
        bool(x.any())
        x.tolist()
        x.cpu()
    assert len(reads.seen) == 4 and reads.seen[2:] == ["Tensor.tolist", "Tensor.cpu"]


@pytest.fixture
def gpu_paths(monkeypatch):  # noqa: ANN001, ANN201
    """The update's GPU code where it has its own: the torch SSIM (the CPU's kernel reads the
    frames as numpy arrays) and random_shift's one-gather crop (the CPU's reads each offset)."""
    monkeypatch.setattr(intrinsic, "_ssim", lambda x, y, x_scale, y_logits=False:
                        intrinsic._ssim_in_torch(x, y.detach(), x_scale, y_logits))
    monkeypatch.setattr(augment, "crops_by_copy", augment.crops_by_index)


@pytest.mark.usefixtures("gpu_paths")
@pytest.mark.parametrize("variant", list(VARIANTS))
def test_no_update_step_reads_a_device_value(variant):
    torch.manual_seed(0)
    agent = agent_of(variant, cuda_graph=True)  # the path a capture records
    for i in range(2 * agent.update_period()):  # every phase of the update's path
        with HostReads() as reads:
            losses = agent.update_step(random_batch(seed=i))
        assert reads.seen == [], f"update {i + 1} read the device from the host: {reads.seen}"
        assert all(isinstance(v, torch.Tensor) and v.dim() == 0 for v in losses.values())


@pytest.mark.usefixtures("gpu_paths")
def test_a_skipped_step_reads_no_device_value_either():
    torch.manual_seed(0)
    agent = agent_of("nasa_td3")
    batch = random_batch()
    batch["reward"][:] = 3e38  # the critic's loss overflows: its step is skipped on the device
    with HostReads() as reads:
        losses = agent.update_step(batch)
    assert reads.seen == [] and not torch.isfinite(losses["critic_loss"])
    assert agent.critic_opt.nonfinite_skips.item() == 1


def test_cuda_graph_is_refused_without_a_cuda_device():
    config = agent_defaults("nasa_td3")
    config.cuda_graph = True
    with pytest.raises(ConfigError, match="cuda_graph needs a CUDA device"):
        make_agent("nasa_td3", OBS_SHAPE, ACTION_DIM, config, torch.device("cpu"))


def test_an_agent_that_only_acts_ignores_cuda_graph():
    config = agent_defaults("nasa_td3")
    config.cuda_graph = True  # a learner on a GPU; the actors and the evaluator on CPUs
    agent = make_agent("nasa_td3", OBS_SHAPE, ACTION_DIM, config, torch.device("cpu"), updates=False)
    assert agent.act(random_batch()["obs"][0].numpy(), explore=False, rng=None).shape == (ACTION_DIM,)


def test_capturable_is_set_only_while_capturing():
    opt = torch.optim.Adam(torch.nn.Linear(2, 1).parameters(), fused=True)
    with capturable([opt]):
        assert opt.param_groups[0]["capturable"] is True
    assert opt.param_groups[0]["capturable"] is False
    with pytest.raises(RuntimeError), capturable([opt]):
        raise RuntimeError("a failed capture")
    assert opt.param_groups[0]["capturable"] is False


# -- GraphedUpdate against an emulator of torch.cuda's graph API ----------------------------------


class Emulator:
    """torch.cuda's streams and graphs for one agent, on the CPU.

    A capture runs the step's Python once and then puts every tensor of the agent, the RNG and
    the update count back as they were: a real capture runs no kernel. A replay runs the step
    again on the graph's static inputs and writes the outputs the capture returned."""

    def __init__(self, agent, fail: bool = False, fail_in_actor_step: bool = False) -> None:  # noqa: ANN001
        self.agent, self.fail, self.fail_in_actor_step = agent, fail, fail_in_actor_step
        self.captures = 0
        self.replays = 0

    def tensors(self) -> list[torch.Tensor]:
        a = self.agent
        out = [t for m in a._modules().values() for t in [*m.parameters(), *m.buffers()]]
        for opt in a._optimizers().values():
            out += [v for s in opt.state.values() for v in s.values() if isinstance(v, torch.Tensor)]
            out += [opt.nonfinite_skips] if hasattr(opt, "nonfinite_skips") else []
        return out + ([a.log_alpha] if hasattr(a, "log_alpha") else [])

    @contextlib.contextmanager
    def graph(self, graph, stream=None, capture_error_mode: str = "global"):  # noqa: ANN001, ANN201
        assert capture_error_mode == "thread_local"
        assert stream is self.agent._graphed.side  # captured on the stream the warm-up ran on
        assert all(g["capturable"] for o in self.agent._optimizers().values() for g in o.param_groups)
        tensors = self.tensors()
        saved = [t.detach().clone() for t in tensors]
        rng = torch.get_rng_state()  # the update count: GraphedUpdate puts it back itself
        if self.fail_in_actor_step:  # a capture that stops midway, once the actor's step is reached
            self.agent.actor_opt.step = _refused
        try:
            yield
        finally:
            self.agent.actor_opt.__dict__.pop("step", None)
            with torch.no_grad():
                for t, s in zip(tensors, saved, strict=True):
                    t.copy_(s)
            torch.set_rng_state(rng)
            self.captures += 1
        if self.fail:
            raise RuntimeError("operation not permitted when stream is capturing")

    def make_graph(self):  # noqa: ANN201
        emulator = self

        class Graph:
            def replay(self) -> None:
                graphed = emulator.agent._graphed
                losses = next(out for g, out in graphed.graphs.values() if g is self)
                count = emulator.agent.num_updates
                fresh = emulator.agent.update_step(graphed.static)
                emulator.agent.num_updates = count
                assert fresh.keys() == losses.keys()  # the same phase, the same path
                for key, value in fresh.items():
                    losses[key].copy_(value)
                emulator.replays += 1

        return Graph()

    def install(self, monkeypatch) -> None:  # noqa: ANN001
        monkeypatch.setattr(torch.cuda, "Stream", lambda device=None: _Stream())
        monkeypatch.setattr(torch.cuda, "stream", lambda stream: contextlib.nullcontext())
        monkeypatch.setattr(torch.cuda, "current_stream", lambda device=None: _Stream())
        monkeypatch.setattr(torch.cuda, "CUDAGraph", self.make_graph)
        monkeypatch.setattr(torch.cuda, "graph", self.graph)


def _refused(*args: object, **kwargs: object) -> None:
    raise RuntimeError("operation not permitted when stream is capturing")


class _Stream:
    def wait_stream(self, other) -> None:  # noqa: ANN001
        pass


def _train(agent, batches) -> list[dict[str, float]]:  # noqa: ANN001
    return [agent.update(b) for b in batches]


def _weights(agent) -> dict:  # noqa: ANN001
    return agent.state_dict()


def _same(a, b) -> bool:  # noqa: ANN001
    if isinstance(a, torch.Tensor):
        return torch.equal(a, b)
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, list | tuple):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    return a == b


@pytest.mark.parametrize("variant", ["nasa_td3", "nasa_td3+ensemble_every_3", "sac_ae"])
def test_the_graphed_agent_trains_exactly_as_the_eager_one(monkeypatch, variant):
    torch.manual_seed(1)
    eager = agent_of(variant)
    period = eager.update_period()
    warmup = max(3, 2 * period)
    batches = [random_batch(seed=i) for i in range(warmup + period + 3)]  # every phase replayed
    eager_losses = _train(eager, batches)
    torch.manual_seed(1)
    graphed = agent_of(variant, cuda_graph=True)
    emulator = Emulator(graphed)
    emulator.install(monkeypatch)
    graphed_losses = _train(graphed, batches)
    assert isinstance(graphed._graphed, GraphedUpdate)
    assert emulator.captures == period == len(graphed._graphed.graphs)  # one graph per phase
    assert emulator.replays == len(batches) - warmup
    assert graphed.num_updates == eager.num_updates == len(batches)
    assert graphed_losses == eager_losses
    assert _same(_weights(graphed), _weights(eager))


@pytest.mark.parametrize("burst", [3, 4])
def test_a_warm_up_bursts_updates_run_eagerly_then_the_graphs_train_as_the_eager_agent(monkeypatch, burst):
    """SAC-AE's burst takes one path at every phase (its env step's): no graph of another phase
    may replay it."""
    torch.manual_seed(1)
    eager = agent_of("sac_ae")
    eager.burst_updates = burst
    batches = [random_batch(seed=i) for i in range(burst + 8)]
    eager_losses = _train(eager, batches)
    torch.manual_seed(1)
    graphed = agent_of("sac_ae", cuda_graph=True)
    graphed.burst_updates = burst
    emulator = Emulator(graphed)
    emulator.install(monkeypatch)
    graphed_losses = _train(graphed, batches)
    assert emulator.replays == len(batches) - burst - graphed._graphed.warmup
    assert graphed_losses == eager_losses
    assert _same(_weights(graphed), _weights(eager))


def test_loading_a_state_drops_the_graphs_and_captures_again(monkeypatch):
    batches = [random_batch(seed=i) for i in range(16)]
    torch.manual_seed(2)
    eager = agent_of("nasa_td3")
    _train(eager, batches[:8])
    saved = copy.deepcopy(eager.state_dict())  # a state_dict holds the live tensors
    torch.manual_seed(2)
    graphed = agent_of("nasa_td3", cuda_graph=True)
    emulator = Emulator(graphed)
    emulator.install(monkeypatch)
    _train(graphed, batches[:8])
    assert emulator.captures == 2
    graphed.load_state_dict(saved)
    assert graphed._graphed is None  # its graphs point to the optimizers' old state tensors
    torch.manual_seed(5)
    _train(graphed, batches[8:])
    assert emulator.captures == 4  # after a new warm-up
    torch.manual_seed(5)
    _train(eager, batches[8:])  # from the same state, eagerly
    assert graphed.num_updates == eager.num_updates == 16
    assert _same(_weights(graphed), _weights(eager))


def test_a_batch_of_another_shape_is_refused(monkeypatch):
    graphed = agent_of("pixel_td3", cuda_graph=True)
    Emulator(graphed).install(monkeypatch)
    _train(graphed, [random_batch(seed=i) for i in range(5)])
    with pytest.raises(ValueError, match=r"batch\['obs'\] is \(8, 9, 48, 48\)"):
        graphed.update(random_batch(batch_size=4))


def test_a_failed_capture_leaves_the_run_eager_with_a_warning(monkeypatch):
    torch.manual_seed(4)
    eager = agent_of("td3_ae")
    batches = [random_batch(seed=i) for i in range(9)]
    eager_losses = _train(eager, batches)
    torch.manual_seed(4)
    graphed = agent_of("td3_ae", cuda_graph=True)
    emulator = Emulator(graphed, fail=True)
    emulator.install(monkeypatch)
    with pytest.warns(RuntimeWarning, match="CUDA graph capture failed; updates run eagerly"):
        graphed_losses = _train(graphed, batches)
    assert emulator.captures == 1 and emulator.replays == 0  # tried once, then eager for good
    assert "operation not permitted" in graphed._graphed.failed
    assert graphed.num_updates == 9 and graphed_losses == eager_losses
    assert _same(_weights(graphed), _weights(eager))


def test_a_capture_that_stops_inside_the_actors_step_leaves_every_network_training(monkeypatch):
    # The actor's step freezes the critic's parameters while it runs; a capture that fails there
    # must not leave them frozen, or the eager update that takes its place trains no critic head.
    torch.manual_seed(4)
    eager = agent_of("td3_ae")
    batches = [random_batch(seed=i) for i in range(10)]
    _train(eager, batches)
    torch.manual_seed(4)
    graphed = agent_of("td3_ae", cuda_graph=True)
    emulator = Emulator(graphed, fail_in_actor_step=True)
    emulator.install(monkeypatch)
    with pytest.warns(RuntimeWarning, match="CUDA graph capture failed; updates run eagerly"):
        _train(graphed, batches)
    assert emulator.captures == 2 and emulator.replays == 1  # the actor's phase failed, then eager
    assert all(p.requires_grad for p in graphed.critic.parameters())
    assert graphed.num_updates == eager.num_updates == 10
    assert _same(_weights(graphed), _weights(eager))
