"""Image augmentation for the pixel agents' updates (off by default: the reference has none).

`random_shift` is DrQ's: each frame stack padded by replicating its edge pixels, then cropped back
to its size at a random integer offset, so the whole stack moves together by up to `pad` pixels on
each axis. It asks the critic for values that do not change when the camera's picture moves by a
few pixels, which is what made DrQ learn from pixels in far fewer steps than unaugmented agents.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F


def random_shift(stacks: torch.Tensor, pad: int) -> torch.Tensor:
    """(B, C, H, W) float stacks, each moved by its own uniform offset in [-pad, pad] pixels on each
    axis, edges replicated; channels-last like the encoder's input. `pad` 0 returns `stacks`."""
    if pad == 0:
        return stacks
    padded = F.pad(stacks, (pad, pad, pad, pad), mode="replicate")
    offsets = torch.randint(0, 2 * pad + 1, (2, len(stacks), 1), device=stacks.device)
    size = stacks.shape[-2:]
    # A copy per stack is the faster on a CPU; one gather keeps a CUDA update free of host syncs.
    crop = crops_by_copy if stacks.device.type == "cpu" else crops_by_index
    return crop(padded, offsets, size)


def crops_by_copy(padded: torch.Tensor, offsets: torch.Tensor, size: torch.Size) -> torch.Tensor:
    """Stack i cropped to `size` from row offsets[0, i] and column offsets[1, i], one copy each."""
    n, c = padded.shape[:2]
    h, w = size
    out = torch.empty((n, c, h, w), dtype=padded.dtype, device=padded.device,
                      memory_format=torch.channels_last)
    for i, (dy, dx) in enumerate(zip(offsets[0, :, 0].tolist(), offsets[1, :, 0].tolist(), strict=True)):
        out[i] = padded[i, :, dy : dy + h, dx : dx + w]
    return out


def crops_by_index(padded: torch.Tensor, offsets: torch.Tensor, size: torch.Size) -> torch.Tensor:
    """The same crops as `crops_by_copy`, as one advanced-indexing gather."""
    n, c = padded.shape[:2]
    h, w = size
    device = padded.device
    rows = (offsets[0] + torch.arange(h, device=device)).view(n, 1, h, 1)
    cols = (offsets[1] + torch.arange(w, device=device)).view(n, 1, 1, w)
    batch = torch.arange(n, device=device).view(n, 1, 1, 1)
    channel = torch.arange(c, device=device).view(1, c, 1, 1)
    return padded[batch, channel, rows, cols].contiguous(memory_format=torch.channels_last)


def shifted_batch(batch: dict[str, torch.Tensor], pad: int) -> dict[str, torch.Tensor]:
    """The batch with `obs` and `next_obs` each shifted independently by `random_shift`, as DrQ
    augments both; the batch itself when `pad` is 0."""
    if pad == 0:
        return batch
    return batch | {key: random_shift(batch[key], pad) for key in ("obs", "next_obs")}
