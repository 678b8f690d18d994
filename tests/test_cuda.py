"""The CUDA path: the same results as on the CPU within tolerance, checkpoints that move between
devices, the prefetcher's pinned copies, and the benchmark's anchors. Skipped without CUDA;
`scripts/gpu-check.sh` runs them (`pytest -m cuda`)."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from bench import hardware
from shared import checkpoint, intrinsic
from shared.agents import make_agent
from shared.config import agent_defaults
from shared.prefetch import DevicePrefetcher

pytestmark = [
    pytest.mark.cuda,
    pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device"),
]

CPU = torch.device("cpu")
CUDA = torch.device("cuda")
OBS_SHAPE = (9, 84, 84)
ACTION_DIM = 2
SMALL = {"latent_dim": 32, "hidden_dim": 64, "ensemble_hidden_dim": 32, "num_filters": 16}
TD3_FAMILY = ["nasa_td3", "td3_ae", "pixel_td3"]


@pytest.fixture(autouse=True)
def exact_fp32():
    """Plain fp32 on the GPU (no TF32), so CPU and GPU agree to rounding."""
    before = torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = False
    yield
    torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32 = before


def make(algo: str, device: torch.device, **overrides):
    config = agent_defaults(algo)
    for key, value in {**SMALL, "target_noise": 0.0, **overrides}.items():
        setattr(config, key, value)
    torch.manual_seed(0)
    return make_agent(algo, OBS_SHAPE, ACTION_DIM, config, device)


def pair(algo: str, **overrides):
    """One agent on the CPU and one on CUDA with the same weights."""
    cpu = make(algo, CPU, **overrides)
    gpu = make(algo, CUDA, **overrides)
    gpu.load_state_dict(copy.deepcopy(cpu.state_dict()))
    return cpu, gpu


def frames(count: int, seed: int = 0) -> torch.Tensor:
    """Smooth uint8 stacks (structure for SSIM), consecutive ones overlapping as a replay's do."""
    g = torch.Generator().manual_seed(seed)
    base = torch.rand(count + 3, 3, 12, 12, generator=g)
    images = torch.nn.functional.interpolate(base, size=(84, 84), mode="bilinear")
    images = (images * 255).to(torch.uint8)
    return torch.stack([images[i : i + 3].reshape(9, 84, 84) for i in range(count)])


def batch(device: torch.device, size: int = 16, seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    stacks = frames(size + 1, seed)
    out = {
        "obs": stacks[:size],
        "next_obs": stacks[1:],
        "action": torch.rand(size, ACTION_DIM, generator=g) * 2 - 1,
        "reward": torch.rand(size, generator=g),
        "discount": torch.ones(size),
        "intrinsic": torch.rand(size, generator=g),
    }
    return {k: v.to(device) for k, v in out.items()}


def assert_same_state(cpu_agent, gpu_agent, rtol: float = 1e-3, atol: float = 1e-4) -> None:
    for name, module in cpu_agent._modules().items():
        for key, value in module.state_dict().items():
            other = gpu_agent._modules()[name].state_dict()[key].cpu()
            torch.testing.assert_close(other, value, rtol=rtol, atol=atol, msg=f"{name}.{key}")


@pytest.mark.parametrize("algo", TD3_FAMILY)
def test_updates_on_cuda_match_the_cpu(algo):
    cpu, gpu = pair(algo)
    for step in range(2):  # the second steps the actor too
        m_cpu = cpu.update(batch(CPU, seed=step))
        m_gpu = gpu.update(batch(CUDA, seed=step))
        assert m_cpu.keys() == m_gpu.keys()
        for key in m_cpu:
            assert m_gpu[key] == pytest.approx(m_cpu[key], rel=1e-3, abs=1e-5), key
    assert_same_state(cpu, gpu)


def test_bf16_pixel_precision_on_cuda_updates_near_the_cpus_bf16():
    cpu, gpu = pair("nasa_td3", pixel_precision="bf16")
    m_cpu, m_gpu = cpu.update(batch(CPU)), gpu.update(batch(CUDA))
    for key in m_cpu:
        assert np.isfinite(m_gpu[key]) and m_gpu[key] == pytest.approx(m_cpu[key], rel=0.05, abs=1e-3), key
    with torch.no_grad():
        obs = batch(CPU, seed=3)["obs"]
        torch.testing.assert_close(gpu.encoder(obs.to(CUDA)).cpu(), cpu.encoder(obs), rtol=0.0, atol=0.05)


def test_scoring_on_cuda_matches_the_cpu():
    cpu, gpu = pair("nasa_td3")
    b = batch(CPU, 24)
    others = frames(24, seed=7)  # no row's obs: every next latent needs its own encoder pass
    for next_obs in (b["next_obs"], others):  # stored order (chained rows), then unchained
        s_cpu = cpu.score(b["obs"], b["action"], next_obs)
        s_gpu = gpu.score(b["obs"].to(CUDA), b["action"].to(CUDA), next_obs.to(CUDA))
        for key in ("novelty", "surprise", "intrinsic"):
            torch.testing.assert_close(s_gpu[key].cpu(), s_cpu[key], rtol=1e-3, atol=1e-4, msg=key)


def test_torch_ssim_on_cuda_matches_the_cpu_kernel():
    x = frames(6).float() / 255
    y = frames(6, seed=1).float() / 255
    torch.testing.assert_close(
        intrinsic.ssim(x.to(CUDA), y.to(CUDA)).cpu(), intrinsic.ssim(x, y), rtol=1e-4, atol=1e-5
    )


@pytest.mark.parametrize("source,target", [(CUDA, CPU), (CPU, CUDA)])
def test_checkpoints_move_between_devices(tmp_path, source, target):
    agent = make("nasa_td3", source)
    agent.update(batch(source))
    checkpoint.save(tmp_path / "checkpoint.pt", {"agent": agent.state_dict()})
    moved = make("nasa_td3", target)
    moved.load_state_dict(checkpoint.load(tmp_path / "checkpoint.pt", target)["agent"])
    assert_same_state(agent if source == CPU else moved, moved if source == CPU else agent, rtol=0, atol=0)
    obs = batch(CPU)["obs"][0].numpy()
    rng = np.random.default_rng(0)
    np.testing.assert_allclose(
        moved.act(obs, explore=False, rng=rng), agent.act(obs, explore=False, rng=rng), atol=1e-4
    )
    optimizer_state = next(iter(moved.critic_opt.state.values()))
    assert optimizer_state["exp_avg"].device.type == target.type
    moved.update(batch(target))  # the optimizers step on the new device


def test_a_checkpoints_random_states_restore_when_it_is_loaded_onto_cuda(tmp_path):
    # A learner or a resumed `nasa train` on CUDA loads its checkpoint onto the GPU, the random
    # states with the rest; torch takes a generator's state only from the CPU.
    rng = np.random.default_rng(0)
    state = checkpoint.rng_state(rng)
    state["cuda"] = [*state["cuda"], state["cuda"][0]]  # saved on a machine with one GPU more
    checkpoint.save(tmp_path / "checkpoint.pt", {"rng": state})
    expected = rng.random(), torch.rand(3), torch.rand(3, device=CUDA).cpu()
    loaded = checkpoint.load(tmp_path / "checkpoint.pt", CUDA)["rng"]
    assert loaded["torch"].device.type == "cuda"
    rng = np.random.default_rng(1)
    checkpoint.restore_rng_state(rng, loaded)
    assert rng.random() == expected[0]
    torch.testing.assert_close(torch.rand(3), expected[1], rtol=0, atol=0)
    torch.testing.assert_close(torch.rand(3, device=CUDA).cpu(), expected[2], rtol=0, atol=0)


def test_the_prefetcher_stages_in_pinned_memory_and_copies_to_cuda():
    host = {k: v.numpy() for k, v in batch(CPU).items()}
    with DevicePrefetcher(lambda: host, CUDA, depth=2) as prefetch:
        items = [prefetch.get(timeout=60) for _ in range(4)]
        assert all(buf.is_pinned() for slot in prefetch._slots for buf in slot.buffers.values())
    for item in items:
        for key, value in host.items():
            assert item.device[key].device.type == "cuda"
            np.testing.assert_array_equal(item.device[key].cpu().numpy(), value)


def test_matmul_peaks_and_flop_counts_on_cuda():
    for dtype, tf32 in ((torch.float32, False), (torch.float32, True), (torch.bfloat16, False)):
        assert hardware.matmul_peak_gflops(CUDA, dtype, sizes=(1024,), seconds=0.05, tf32=tf32) > 0
    conv = torch.nn.Conv2d(9, 32, 3, stride=2).to(CUDA)
    x = torch.randn(4, 9, 84, 84, device=CUDA)
    assert hardware.count_flops(lambda: conv(x)) == 2 * 4 * 32 * 41 * 41 * 9 * 9


def graphed_pair(algo: str, **overrides):
    """Two agents on CUDA with the same weights: one eager, one replaying captured graphs."""
    eager = make(algo, CUDA, **overrides)
    graphed = make(algo, CUDA, cuda_graph=True, **overrides)
    graphed.load_state_dict(copy.deepcopy(eager.state_dict()))
    return eager, graphed


@pytest.mark.parametrize("variant", [{}, {"intrinsic_timing": "fresh"}, {"ensemble_every": 3}])
def test_a_graphed_update_matches_the_eager_one_on_cuda(variant):
    eager, graphed = graphed_pair("nasa_td3", **variant)  # target_noise 0: no draw differs
    steps = max(3, 2 * graphed.update_period()) + graphed.update_period() + 2
    for step in range(steps):
        m_eager = eager.update(batch(CUDA, seed=step))
        m_graphed = graphed.update(batch(CUDA, seed=step))
        assert m_graphed.keys() == m_eager.keys()
        for key in m_eager:
            assert m_graphed[key] == pytest.approx(m_eager[key], rel=1e-3, abs=1e-5), (step, key)
    assert len(graphed._graphed.graphs) == graphed.update_period()
    assert graphed.num_updates == eager.num_updates == steps
    assert_same_state(eager, graphed)


def test_a_graphed_update_skips_a_non_finite_step_and_captures_again_after_a_load():
    eager, graphed = graphed_pair("td3_ae")
    for step in range(6):
        graphed.update(batch(CUDA, seed=step))
    before = copy.deepcopy(graphed.state_dict())
    bad = batch(CUDA, seed=9)
    bad["reward"][:] = 3e38  # the critic's loss overflows
    graphed.update(bad)
    assert graphed.critic_opt.nonfinite_skips.item() == 1
    torch.testing.assert_close(graphed.critic.state_dict(), before["critic"], rtol=0, atol=0)
    graphed.load_state_dict(before)
    assert graphed._graphed is None
    eager.load_state_dict(copy.deepcopy(before))
    for step in range(6, 14):
        eager.update(batch(CUDA, seed=step))
        graphed.update(batch(CUDA, seed=step))
    assert len(graphed._graphed.graphs) == 2
    assert_same_state(eager, graphed)
