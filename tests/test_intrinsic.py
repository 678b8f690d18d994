"""Novelty matches scikit-image's SSIM (the reference's) on real frames, in both implementations
(the CPU kernel and the torch one other devices use); surprise is the ensemble MSE; scoring
in stored order reuses the latents of chained rows and gives the same scores."""

import os
import subprocess
import sys

import numpy as np
import pytest
import torch
from skimage.metrics import structural_similarity

from shared import envs, intrinsic, ssim_kernel
from shared.agents import make_agent
from shared.config import agent_defaults


@pytest.fixture(scope="module")
def rendered_stacks() -> np.ndarray:
    env = envs.make("cheetah-run", seed=0, render_quality="fast")
    rng = np.random.default_rng(0)
    ts = env.reset()
    stacks = [ts.obs]
    for _ in range(5):
        ts = env.step(rng.uniform(-1, 1, env.action_dim))
        stacks.append(ts.obs)
    return np.stack(stacks)


def reference_novelty(obs: np.ndarray, reconstruction: np.ndarray) -> float:
    """The reference's call, per transition."""
    target = obs / 255
    value = structural_similarity(
        target, reconstruction, data_range=target.max() - target.min(), channel_axis=0
    )
    return 1 - value


def torch_novelty(obs: torch.Tensor, reconstruction: torch.Tensor) -> torch.Tensor:
    return 1 - intrinsic.ssim_torch(obs.float() / 255, reconstruction)


@pytest.mark.parametrize("novelty", [intrinsic.novelty, torch_novelty], ids=["cpu_kernel", "torch"])
def test_novelty_matches_scikit_image_on_rendered_frames_and_reconstructions(rendered_stacks, novelty):
    agent = make_agent("nasa_td3", (9, 84, 84), 6, agent_defaults("nasa_td3"), torch.device("cpu"))
    obs = torch.from_numpy(rendered_stacks)
    with torch.no_grad():
        reconstruction = agent.decoder(agent.encoder(obs))
    assert reconstruction.is_contiguous(memory_format=torch.channels_last)  # the layout scoring sees
    ours = novelty(obs, reconstruction).numpy()
    expected = [
        reference_novelty(o.astype(np.float64), r.astype(np.float64))
        for o, r in zip(rendered_stacks, reconstruction.numpy(), strict=True)
    ]
    np.testing.assert_allclose(ours, expected, atol=1e-4)


@pytest.mark.parametrize("path", ["cpu_kernel", "device"])
@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_novelty_of_the_decoders_logits_matches_scikit_image_on_their_sigmoid(
    rendered_stacks, precision, path
):
    """Scoring hands the kernel the decoder's logits as computed (bfloat16 under bf16), and the
    kernel takes their sigmoid as it reads them: the same novelty as the reference's call on
    the sigmoid of those logits. `device`: the branch a GPU takes (torch ops), run here."""
    config = agent_defaults("nasa_td3")
    config.pixel_precision = precision
    agent = make_agent("nasa_td3", (9, 84, 84), 6, config, torch.device("cpu"))
    obs = torch.from_numpy(rendered_stacks)
    with torch.no_grad():
        logits = agent.decoder.logits(agent.encoder(obs), keep_precision=True)
    assert logits.dtype == (torch.bfloat16 if precision == "bf16" else torch.float32)
    if path == "cpu_kernel":
        ours = intrinsic.novelty_of_logits(obs, logits).numpy()
    else:
        ours = (1.0 - intrinsic._ssim_in_torch(obs, logits, 1.0 / 255.0, y_logits=True)).numpy()
    reconstruction = torch.sigmoid(logits.double()).numpy()
    pairs = zip(rendered_stacks.astype(np.float64), reconstruction, strict=True)
    expected = [reference_novelty(o, r) for o, r in pairs]
    np.testing.assert_allclose(ours, expected, atol=1e-4)


def test_the_kernels_sigmoid_matches_torchs_over_the_float_range():
    values = torch.cat([torch.linspace(-120, 120, 480_001), torch.tensor([0.0, float("inf"), -float("inf")])])
    row = values.numpy()[None]
    out = np.empty(row.shape[1], np.float32)
    bits = np.empty(row.shape[1], np.int32)
    ssim_kernel._read_row(row, 0, row.shape[1], False, True, out, bits, bits.view(np.float32))
    expected = torch.sigmoid(values.double()).numpy()
    np.testing.assert_allclose(out, expected, rtol=1e-6, atol=1e-37)
    nan = np.array([[np.nan]], np.float32)
    ssim_kernel._read_row(nan, 0, 1, False, True, out, bits, bits.view(np.float32))
    assert np.isnan(out[0])  # a NaN reconstruction is not hidden


@pytest.mark.parametrize("ssim", [intrinsic.ssim, intrinsic.ssim_torch], ids=["cpu_kernel", "torch"])
def test_ssim_matches_scikit_image_on_near_copies(rendered_stacks, ssim):
    # Three noise levels of six stacks, so that samples differ in data range and noise.
    rng = np.random.default_rng(1)
    x = np.tile(rendered_stacks.astype(np.float64) / 255, (3, 1, 1, 1))
    noise = np.repeat([0.01, 0.02, 0.05], len(rendered_stacks))[:, None, None, None]
    y = np.clip(x + rng.normal(0, 1, x.shape) * noise, 0, 1)
    ours = ssim(torch.from_numpy(x), torch.from_numpy(y)).numpy()
    expected = [
        structural_similarity(a, b, data_range=a.max() - a.min(), channel_axis=0)
        for a, b in zip(x, y, strict=True)
    ]
    np.testing.assert_allclose(ours, expected, atol=1e-4)
    assert np.all(np.asarray(expected) > 0.2)  # near copies: the comparison is not trivially at 0
    assert np.ptp(expected) > 0.1  # and the noise levels are told apart


@pytest.mark.parametrize("ssim", [intrinsic.ssim, intrinsic.ssim_torch], ids=["cpu_kernel", "torch"])
def test_ssim_of_an_image_with_itself_is_one(rendered_stacks, ssim):
    x = torch.from_numpy(rendered_stacks).float() / 255
    torch.testing.assert_close(ssim(x, x), torch.ones(len(x)))


def uniform_stacks_and_reconstructions() -> tuple[torch.Tensor, torch.Tensor]:
    """Uniform stacks (black, greys, white: a dark or overexposed camera) against smooth
    reconstructions, flat or with a little noise, as an autoencoder gives them."""
    rng = np.random.default_rng(2)
    levels = np.array([0, 1, 64, 128, 200, 255], np.uint8)
    obs = np.repeat(levels, 4)[:, None, None, None] * np.ones((1, 9, 32, 32), np.uint8)
    means = rng.uniform(0.05, 0.95, (len(obs), 1, 1, 1))
    noise = np.tile([0.0, 0.0, 0.002, 0.02], len(levels))[:, None, None, None]
    reconstruction = np.clip(means + noise * rng.standard_normal(obs.shape), 0, 1).astype(np.float32)
    return torch.from_numpy(obs), torch.from_numpy(reconstruction)


def test_novelty_of_uniform_stacks_is_finite_bounded_and_the_same_in_both_implementations():
    """A uniform stack has data range 0: without a floor both SSIM constants vanish and the
    score is 0/0 plus rounding (NaN in torch, any size in the kernel)."""
    obs, reconstruction = uniform_stacks_and_reconstructions()
    cpu = intrinsic.novelty(obs, reconstruction).numpy()
    in_torch = torch_novelty(obs, reconstruction).numpy()
    for ours in (cpu, in_torch):
        assert np.all(np.isfinite(ours)) and np.all((ours > -0.1) & (ours < 2.1))  # 1 - SSIM, SSIM in [-1, 1]
    floor = ssim_kernel.RANGE_FLOOR
    pairs = zip(obs.numpy().astype(np.float64), reconstruction.numpy().astype(np.float64), strict=True)
    expected = np.array([
        1 - structural_similarity(o / 255, r, data_range=floor, channel_axis=0) for o, r in pairs
    ])
    for ours in (cpu, in_torch):
        # float32 rounding of a flat window's variance is still felt against the floor's constants
        np.testing.assert_allclose(ours, expected, atol=0.1)
    np.testing.assert_allclose(cpu, in_torch, atol=0.1)


def test_the_range_floor_leaves_ordinary_frames_bit_identical(rendered_stacks):
    """Frames whose range is above the floor (any camera frame with contrast) give exactly what
    the unfloored formula, the reference's, gives."""
    rng = np.random.default_rng(3)
    # Real-looking frames: smooth random shapes (coarse noise upsampled) plus sensor noise.
    coarse = rng.integers(0, 256, (16, 9, 12, 12)).astype(np.float64)
    smooth = np.kron(coarse, np.ones((7, 7)))
    frames = np.clip(smooth + rng.normal(0, 4, smooth.shape), 0, 255).astype(np.uint8)
    obs = np.concatenate([frames, rendered_stacks])
    reconstruction = np.clip(obs / 255 + rng.normal(0, 0.05, obs.shape), 0, 1).astype(np.float32)
    assert (np.ptp(obs.reshape(len(obs), -1), axis=1) / 255 > ssim_kernel.RANGE_FLOOR).all()
    floored = ssim_kernel.batch_ssim(obs, reconstruction, 1 / 255, 1)
    unfloored = ssim_kernel.batch_ssim(obs, reconstruction, 1 / 255, 1, range_floor=0.0)
    np.testing.assert_array_equal(floored, unfloored)
    x, y = torch.from_numpy(obs).float() / 255, torch.from_numpy(reconstruction)
    assert torch.equal(intrinsic.ssim_torch(x, y), intrinsic.ssim_torch(x, y, range_floor=0.0))


def test_ssim_rejects_mismatched_shapes_and_tiny_images():
    with pytest.raises(ValueError, match="one shape"):
        intrinsic.ssim(torch.zeros(1, 3, 16, 16), torch.zeros(1, 3, 16, 8))
    with pytest.raises(ValueError, match="at least 7x7"):
        intrinsic.ssim(torch.zeros(1, 3, 16, 6), torch.zeros(1, 3, 16, 6))


CONCURRENT_NOVELTY = """
from concurrent.futures import ThreadPoolExecutor
import numba, torch
from shared import intrinsic
obs = torch.randint(0, 256, (8, 9, 84, 84), dtype=torch.uint8)
reconstruction = torch.rand(obs.shape)
expected = intrinsic.novelty(obs, reconstruction)
with ThreadPoolExecutor(4) as pool:
    results = list(pool.map(lambda _: intrinsic.novelty(obs, reconstruction), range(16)))
assert numba.threading_layer() == "workqueue", numba.threading_layer()
assert all(torch.equal(r, expected) for r in results)
"""


def test_novelty_from_several_threads_at_once_with_numbas_plain_thread_pool():
    # Any thread may score. numba's plain thread pool (workqueue: the SSIM kernel's layer under
    # ACTIVE OpenMP waits, and numba's fallback) aborts the process when two threads enter it at once.
    env = os.environ | {"NUMBA_THREADING_LAYER": "workqueue"}
    run = subprocess.run([sys.executable, "-c", CONCURRENT_NOVELTY], env=env, capture_output=True, text=True)
    assert run.returncode == 0, run.stderr[-2000:]


IDLE_AFTER_NOVELTY = """
import resource, time
import numba, torch
from shared import intrinsic
obs = torch.randint(0, 256, (8, 9, 84, 84), dtype=torch.uint8)
torch.set_num_threads(2)
intrinsic.novelty(obs, torch.rand(obs.shape))  # on two threads
def cpu():
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime
before = cpu()
time.sleep(1.0)
print(numba.threading_layer(), cpu() - before)
"""


def test_no_ssim_thread_spins_after_scoring_under_active_openmp_waits():
    # `nasa up` gives its learner OMP_WAIT_POLICY=ACTIVE on small machines; numba's OpenMP layer
    # would read it too, and its worker would then spin on a core for the rest of the process.
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_THREADING_LAYER"}
    env["OMP_WAIT_POLICY"] = "ACTIVE"
    run = subprocess.run([sys.executable, "-c", IDLE_AFTER_NOVELTY], env=env, capture_output=True, text=True)
    assert run.returncode == 0, run.stderr[-2000:]
    layer, busy_s = run.stdout.split()
    assert layer == "workqueue"
    assert float(busy_s) < 0.3, f"{busy_s} s of CPU in a 1 s sleep: a thread is spinning"


def test_surprise_is_mse_of_the_ensemble_mean():
    predictions = torch.tensor([[[1.0, 2.0]], [[3.0, 4.0]]])  # K=2, B=1, D=2; mean (2, 3)
    next_latent = torch.tensor([[0.0, 0.0]])
    torch.testing.assert_close(intrinsic.surprise(predictions, next_latent), torch.tensor([6.5]))


def test_score_weights_novelty_and_surprise():
    config = agent_defaults("nasa_td3")
    config.novelty_weight, config.surprise_weight = 2.0, 3.0
    config.latent_dim, config.hidden_dim, config.ensemble_hidden_dim = 16, 32, 16
    agent = make_agent("nasa_td3", (9, 32, 32), 2, config, torch.device("cpu"))
    obs = torch.randint(0, 256, (4, 9, 32, 32), dtype=torch.uint8)
    scores = agent.score(obs, torch.zeros(4, 2), obs)
    torch.testing.assert_close(scores["intrinsic"], 2.0 * scores["novelty"] + 3.0 * scores["surprise"])


def test_novelty_reads_obs_in_the_replay_s_layout(rendered_stacks):
    # The replay hands out obs and next_obs as views of one (B, stack + 1, 3, H, W) window,
    # so obs is not contiguous: the kernel must read it as it is.
    frames = torch.from_numpy(rendered_stacks).view(len(rendered_stacks), 3, 3, 84, 84)
    window = torch.cat([frames, frames[:, :1]], dim=1)  # (B, 4, 3, H, W)
    obs = window[:, :3].flatten(1, 2)
    assert not obs.is_contiguous()
    reconstruction = torch.rand(obs.shape).contiguous(memory_format=torch.channels_last)
    torch.testing.assert_close(intrinsic.novelty(obs, reconstruction),
                               intrinsic.novelty(obs.contiguous(), reconstruction))


OBS_SHAPE = (9, 48, 48)


def small_nasa_td3():
    config = agent_defaults("nasa_td3")
    config.latent_dim, config.hidden_dim, config.ensemble_hidden_dim, config.num_filters = 32, 64, 32, 16
    return make_agent("nasa_td3", OBS_SHAPE, 2, config, torch.device("cpu"))


def stored_rows(actors: int = 2, steps: int = 5, seed: int = 0):
    """Rows as the replay stores them: actors' steps interleaved, each next stack the obs
    stack of the same actor's next row. Returns obs, next_obs and each row's successor."""
    g = torch.Generator().manual_seed(seed)
    frames = torch.randint(0, 256, (actors, steps + 3, 3, *OBS_SHAPE[1:]), dtype=torch.uint8, generator=g)
    obs, next_obs, successor = [], [], []
    for t in range(steps):
        for a in range(actors):
            obs.append(frames[a, t : t + 3].flatten(0, 1))
            next_obs.append(frames[a, t + 1 : t + 4].flatten(0, 1))
            successor.append(len(successor) + actors if t + 1 < steps else -1)
    return torch.stack(obs), torch.stack(next_obs), successor


def test_chained_rows_pairs_each_next_stack_with_its_successors_obs_only():
    obs, next_obs, successor = stored_rows()
    assert intrinsic.chained_rows(obs, next_obs).tolist() == successor
    # A decoy equal to an unchained next stack on every fingerprint row (each 12th) but
    # one pixel: it must not be taken for it.
    last = successor.index(-1)
    decoy = next_obs[last].clone()
    decoy[0, 5, 5] ^= 1
    found = intrinsic.chained_rows(torch.cat([obs, decoy[None]]), next_obs)
    assert found[last] == -1 and found.tolist() == successor
    assert (intrinsic.chained_rows(obs, next_obs.flip(-1)) == -1).all()  # an i.i.d.-like batch: no chain


def test_chained_rows_reads_stacks_cast_to_bfloat16_as_the_uint8_ones():
    obs, next_obs, successor = stored_rows()
    bf16 = intrinsic.chained_rows(obs.to(torch.bfloat16), next_obs.to(torch.bfloat16))
    assert bf16.tolist() == successor


def test_scoring_a_chained_batch_equals_scoring_each_transition_apart():
    agent = small_nasa_td3()
    obs, next_obs, successor = stored_rows()
    action = torch.rand(len(obs), 2) * 2 - 1
    scores = agent.score(obs, action, next_obs)
    with torch.no_grad():
        rows = zip(obs, action, next_obs, strict=True)
        alone = [agent.score(o[None], a[None], n[None]) for o, a, n in rows]
    for name in ("novelty", "surprise", "intrinsic"):
        torch.testing.assert_close(scores[name], torch.cat([s[name] for s in alone]), rtol=1e-4, atol=1e-6)
    assert sum(s >= 0 for s in successor) > len(obs) // 2  # the batch really chains


def test_encode_with_next_encodes_only_the_rows_no_other_row_chains_to():
    agent = small_nasa_td3()
    obs, next_obs, successor = stored_rows()
    encoded = []

    def encode(x):
        encoded.append(len(x))
        return agent.encoder(x)

    with torch.no_grad():
        expected_z, expected_next = agent.encoder(obs), agent.encoder(next_obs)
        z, z_next = intrinsic.encode_with_next(encode, obs, next_obs, expected_z)
        assert z is expected_z
        torch.testing.assert_close(z_next, expected_next, rtol=1e-5, atol=1e-6)
        assert encoded == [successor.count(-1)]
        # Without Enc(obs): the same latents from one call over obs and the unchained rows.
        encoded.clear()
        z, z_next = intrinsic.encode_with_next(encode, obs, next_obs)
        torch.testing.assert_close(z, expected_z, rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(z_next, expected_next, rtol=1e-5, atol=1e-6)
    assert encoded == [len(obs) + successor.count(-1)]
