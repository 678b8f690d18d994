"""DrQ's random shift: what it moves, by how much, and that an update reads the shifted stacks."""

import pytest
import torch
import torch.nn.functional as F

from shared.agents.base import float_pixels
from shared.augment import crops_by_copy, crops_by_index, random_shift, shifted_batch
from tests.test_agents import make, random_batch, snapshot


def _offset_of(shifted: torch.Tensor, original: torch.Tensor, pad: int) -> tuple[int, int]:
    """The one (row, col) crop offset of the replicate-padded original that gives `shifted`."""
    padded = F.pad(original.unsqueeze(0), (pad,) * 4, mode="replicate")[0]
    h, w = original.shape[-2:]
    hits = [
        (dy, dx)
        for dy in range(2 * pad + 1)
        for dx in range(2 * pad + 1)
        if torch.equal(padded[:, dy : dy + h, dx : dx + w], shifted)
    ]
    assert len(hits) == 1, hits
    return hits[0]


@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
def test_each_stack_moves_whole_by_at_most_pad_pixels_with_its_edges_replicated(dtype):
    torch.manual_seed(0)
    pad = 3
    stacks = torch.randint(0, 256, (64, 9, 20, 24)).to(dtype).contiguous(memory_format=torch.channels_last)
    out = random_shift(stacks, pad)
    assert out.shape == stacks.shape and out.dtype == dtype
    assert out.is_contiguous(memory_format=torch.channels_last)  # as the encoder reads it
    offsets = {_offset_of(out[i], stacks[i], pad) for i in range(len(stacks))}
    # 64 draws of 49 offsets: the edges and the centre all turn up, and nothing beyond pad.
    rows, cols = {dy for dy, _ in offsets}, {dx for _, dx in offsets}
    assert rows == set(range(2 * pad + 1)) and cols == set(range(2 * pad + 1))


def test_no_shift_is_the_batch_itself_and_a_seed_repeats_the_shifts():
    stacks = torch.rand(8, 3, 16, 16)
    assert random_shift(stacks, 0) is stacks
    batch = {"obs": stacks, "next_obs": stacks.clone(), "action": torch.zeros(8, 2)}
    assert shifted_batch(batch, 0) is batch
    torch.manual_seed(1)
    first = shifted_batch(batch, 2)
    torch.manual_seed(1)
    again = shifted_batch(batch, 2)
    assert torch.equal(first["obs"], again["obs"]) and torch.equal(first["next_obs"], again["next_obs"])
    assert first["action"] is batch["action"]
    # obs and next_obs are shifted independently, as DrQ does (equal inputs, different outputs)
    assert not torch.equal(first["obs"], first["next_obs"])


@pytest.mark.parametrize("algo", ["nasa_td3", "sac_ae"])
def test_an_update_with_random_shift_is_the_update_on_the_shifted_batch(algo):
    batch = random_batch()
    critics = []
    for pad, shift_first in ((2, False), (0, True), (0, False)):
        torch.manual_seed(0)
        agent = make(algo, random_shift=pad)
        torch.manual_seed(1)
        # The same draws, shifting before the update instead of inside it.
        agent.update(shifted_batch(float_pixels(batch), 2) if shift_first else batch)
        critics.append(snapshot(agent.critic))
    inside, outside, unshifted = critics
    assert all(torch.equal(inside[k], outside[k]) for k in inside)
    assert any(not torch.equal(inside[k], unshifted[k]) for k in inside)


def test_the_cpu_copies_and_the_gather_crop_alike():
    padded = torch.rand(16, 9, 14, 18).contiguous(memory_format=torch.channels_last)
    offsets = torch.randint(0, 5, (2, 16, 1))
    by_copy = crops_by_copy(padded, offsets, torch.Size((10, 14)))
    by_index = crops_by_index(padded, offsets, torch.Size((10, 14)))
    assert by_copy.is_contiguous(memory_format=torch.channels_last)
    assert torch.equal(by_copy, by_index)
