"""Image augmentation for the pixel agents' updates (off by default: the reference has none).

`random_shift` is DrQ's: each frame stack padded by replicating its edge pixels, then cropped back
to its size at a random integer offset, so the whole stack moves together by up to `pad` pixels on
each axis. It asks the critic for values that do not change when the camera's picture moves by a
few pixels, which is what made DrQ learn from pixels in far fewer steps than unaugmented agents.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F


def random_shift(stacks: torch.Tensor, pad: int, generator: torch.Generator | None = None) -> torch.Tensor:
    """(B, C, H, W) float stacks, each moved by its own uniform offset in [-pad, pad] pixels on each
    axis, edges replicated; channels-last like the encoder's input. `pad` 0 returns `stacks`."""
    if pad == 0:
        return stacks
    n, c, h, w = stacks.shape
    padded = F.pad(stacks, (pad, pad, pad, pad), mode="replicate")
    offsets = torch.randint(0, 2 * pad + 1, (2, n, 1), device=stacks.device, generator=generator)
    rows = (offsets[0] + torch.arange(h, device=stacks.device)).view(n, 1, h, 1)
    cols = (offsets[1] + torch.arange(w, device=stacks.device)).view(n, 1, 1, w)
    batch = torch.arange(n, device=stacks.device).view(n, 1, 1, 1)
    channel = torch.arange(c, device=stacks.device).view(1, c, 1, 1)
    return padded[batch, channel, rows, cols].contiguous(memory_format=torch.channels_last)


def shifted_batch(batch: dict[str, torch.Tensor], pad: int) -> dict[str, torch.Tensor]:
    """The batch with `obs` and `next_obs` each shifted independently by `random_shift`, as DrQ
    augments both; the batch itself when `pad` is 0."""
    if pad == 0:
        return batch
    return batch | {key: random_shift(batch[key], pad) for key in ("obs", "next_obs")}
