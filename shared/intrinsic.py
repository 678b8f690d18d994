"""Intrinsic rewards of NaSA-TD3, batched on the agent's device.

novelty  = 1 - SSIM(obs/255, Dec(Enc(obs)))
surprise = MSE(mean_k P_k(Enc(obs), a), Enc(next_obs))

The SSIM reproduces scikit-image's `structural_similarity` defaults, which the
reference calls per transition: a 7x7 uniform window, sample covariance,
K1 = 0.01, K2 = 0.03, data_range = max - min of the target image, the mean of
the SSIM map over the valid (border-cropped) region, averaged over channels.
A test checks it against scikit-image on rendered frames.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F


def ssim(x: torch.Tensor, y: torch.Tensor, win_size: int = 7) -> torch.Tensor:
    """Mean SSIM per sample of (B, C, H, W) images in [0, 1]; data_range from x per sample."""
    if x.shape != y.shape or x.dim() != 4:
        raise ValueError(f"ssim needs two (B, C, H, W) tensors of one shape, got {x.shape}, {y.shape}")
    x, y = x.float(), y.float()
    batch, channels = x.shape[:2]
    data_range = (x.amax(dim=(1, 2, 3)) - x.amin(dim=(1, 2, 3))).view(-1, 1, 1, 1)
    c1 = (0.01 * data_range) ** 2
    c2 = (0.03 * data_range) ** 2
    n = win_size * win_size
    cov_norm = n / (n - 1)  # sample covariance, as scikit-image's use_sample_covariance=True

    # All five local means in one depthwise convolution; a valid (unpadded) uniform
    # filter equals scikit-image's filtered map after its border crop. Channels-last
    # depthwise convolution is several times faster on CPU than avg_pool2d.
    maps = torch.cat([x, y, x * x, y * y, x * y], dim=1).contiguous(memory_format=torch.channels_last)
    kernel = torch.full((5 * channels, 1, win_size, win_size), 1.0 / n, device=x.device)
    means = F.conv2d(maps, kernel, groups=5 * channels).split(channels, dim=1)
    ux, uy, uxx, uyy, uxy = means
    vx = cov_norm * (uxx - ux * ux)
    vy = cov_norm * (uyy - uy * uy)
    vxy = cov_norm * (uxy - ux * uy)
    s = ((2 * ux * uy + c1) * (2 * vxy + c2)) / ((ux * ux + uy * uy + c1) * (vx + vy + c2))
    return s.mean(dim=(1, 2, 3))


def novelty(obs: torch.Tensor, reconstruction: torch.Tensor) -> torch.Tensor:
    """1 - SSIM between obs (uint8 or 0..255 floats) scaled to [0, 1] and its reconstruction."""
    return 1.0 - ssim(obs.float() / 255.0, reconstruction)


def surprise(predictions: torch.Tensor, next_latent: torch.Tensor) -> torch.Tensor:
    """MSE per sample between the ensemble-mean prediction (K, B, D) and the next latent (B, D)."""
    return (predictions.mean(dim=0) - next_latent).pow(2).mean(dim=1)
