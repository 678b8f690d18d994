"""Intrinsic rewards of NaSA-TD3, batched on the agent's device.

novelty  = 1 - SSIM(obs/255, Dec(Enc(obs)))
surprise = MSE(mean_k P_k(Enc(obs), a), Enc(next_obs))

The SSIM reproduces scikit-image's `structural_similarity` defaults, which the
reference calls per transition: a 7x7 uniform window, sample covariance,
K1 = 0.01, K2 = 0.03, data_range = max - min of the target image (at least
`ssim_kernel.RANGE_FLOOR`, where the reference has no floor), the mean of
the SSIM map over the valid (border-cropped) region, averaged over channels.
On the CPU it runs as a compiled kernel (`ssim_kernel`), elsewhere in torch
(`ssim_torch`); tests check both against scikit-image on rendered frames.

Surprise needs Enc(next_obs). Transitions scored in the order they were stored
chain: a row's next stack is a later row's obs stack, whose latent the scorer
already has. `encode_with_next` takes those latents from Enc(obs) (`chained_rows`
finds the pairs) and encodes only the rest, in the same pass as obs.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
import torch.nn.functional as F

from shared import ssim_kernel

WIN = ssim_kernel.WIN
_FINGERPRINT_STRIDE = 12  # chained_rows: a stack's key holds every 12th image row of every channel
_MAX_CANDIDATES = 4  # chained_rows: stacks compared whole per row, at most


def ssim(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Mean SSIM per sample of (B, C, H, W) images in [0, 1]; data_range from x per sample."""
    return _ssim(x, y, x_scale=1.0)


def novelty(obs: torch.Tensor, reconstruction: torch.Tensor) -> torch.Tensor:
    """1 - SSIM between obs (uint8 or 0..255 floats) scaled to [0, 1] and its reconstruction."""
    return 1.0 - _ssim(obs, reconstruction, x_scale=1.0 / 255.0)


def novelty_of_logits(obs: torch.Tensor, logits: torch.Tensor) -> torch.Tensor:
    """`novelty` with the reconstruction given as the decoder's logits (float32 or bfloat16):
    on the CPU the kernel takes their sigmoid as it reads them, with no float32 copy."""
    return 1.0 - _ssim(obs, logits, x_scale=1.0 / 255.0, y_logits=True)


def surprise(predictions: torch.Tensor, next_latent: torch.Tensor) -> torch.Tensor:
    """MSE per sample between the ensemble-mean prediction (K, B, D) and the next latent (B, D)."""
    return (predictions.mean(dim=0) - next_latent).pow(2).mean(dim=1)


def _ssim(x: torch.Tensor, y: torch.Tensor, x_scale: float, y_logits: bool = False) -> torch.Tensor:
    if x.shape != y.shape or x.dim() != 4:
        raise ValueError(f"ssim needs two (B, C, H, W) tensors of one shape, got {x.shape}, {y.shape}")
    if min(x.shape[2:]) < WIN:
        raise ValueError(f"ssim needs images of at least {WIN}x{WIN}, got {tuple(x.shape[2:])}")
    y = y.detach()
    if x.device.type != "cpu":
        return _ssim_in_torch(x, y, x_scale, y_logits)
    if x.dtype != torch.uint8:
        x = x.float()
    bf16 = y.dtype == torch.bfloat16
    values = ssim_kernel.batch_ssim(
        x.detach().numpy(), y.view(torch.int16).numpy() if bf16 else y.float().numpy(), x_scale,
        torch.get_num_threads(), y_bf16=bf16, y_logits=y_logits,
    )
    return torch.from_numpy(values).float()


def _ssim_in_torch(x: torch.Tensor, y: torch.Tensor, x_scale: float, y_logits: bool = False) -> torch.Tensor:
    """`_ssim` off the CPU: the same arguments, in torch ops (`ssim_torch`)."""
    y = y.float()
    return ssim_torch(x.float() * x_scale, torch.sigmoid(y) if y_logits else y)


def ssim_torch(
    x: torch.Tensor, y: torch.Tensor, range_floor: float = ssim_kernel.RANGE_FLOOR
) -> torch.Tensor:
    """`ssim` in torch ops, for devices other than the CPU (x, y float, in [0, 1]);
    `range_floor` as in `ssim_kernel.batch_ssim`."""
    batch, channels, height, width = x.shape
    data_range = (x.amax(dim=(1, 2, 3)) - x.amin(dim=(1, 2, 3))).clamp(min=range_floor).view(-1, 1, 1, 1)
    c1 = (0.01 * data_range) ** 2
    c2 = (0.03 * data_range) ** 2
    n = WIN * WIN
    cov_norm = n / (n - 1)  # sample covariance, as scikit-image's use_sample_covariance=True

    # Four local means in one depthwise convolution: x, y, x^2 + y^2 (SSIM only needs
    # var_x + var_y) and xy. A valid (unpadded) uniform filter equals scikit-image's
    # filtered map after its border crop. The maps are built channels-last, where
    # cuDNN and oneDNN run depthwise convolutions fastest.
    maps = torch.empty((batch, height, width, 4 * channels), device=x.device).permute(0, 3, 1, 2)
    maps[:, :channels] = x
    maps[:, channels : 2 * channels] = y
    torch.addcmul(x * x, y, y, out=maps[:, 2 * channels : 3 * channels])
    torch.mul(x, y, out=maps[:, 3 * channels :])
    kernel = torch.full((4 * channels, 1, WIN, WIN), 1.0 / n, device=x.device)
    ux, uy, u_sq, uxy = F.conv2d(maps, kernel, groups=4 * channels).split(channels, dim=1)
    uxuy = ux * uy
    u2 = torch.addcmul(ux * ux, uy, uy)
    numerator = (2 * uxuy + c1) * (uxy - uxuy).mul_(2 * cov_norm).add_(c2)
    denominator = (u2 + c1) * (u_sq - u2).mul_(cov_norm).add_(c2)
    return numerator.div_(denominator).mean(dim=(1, 2, 3))


def encode_with_next(
    encode: Callable[[torch.Tensor], torch.Tensor],
    obs: torch.Tensor,
    next_obs: torch.Tensor,
    z: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Enc(obs) and Enc(next_obs), in one call of `encode` (none for obs when `z`, Enc(obs)
    computed with the same weights, is given).

    A row whose next stack equals another row's obs stack takes that row's latent;
    only the others are encoded, together with obs. Rows in stored order chain that
    way (each next stack is its successor's obs), so one encoder pass serves them
    all; an i.i.d. batch finds no chain and only pays the lookup."""
    source = chained_rows(obs, next_obs)
    unchained = source < 0
    rest = next_obs[unchained]
    if z is None:
        # One pass: each call of a network pays its own fixed costs (under bf16 the
        # weights' casts), a large share of encoding the one stack that ends a stored run.
        both = encode(torch.cat([obs, rest])) if len(rest) else encode(obs)
        z, z_rest = both[: len(obs)], both[len(obs) :]
    else:
        z_rest = encode(rest) if len(rest) else None
    z_next = z[source.clamp(min=0)]
    if z_rest is not None:
        z_next[unchained] = z_rest
    return z, z_next


def chained_rows(obs: torch.Tensor, next_obs: torch.Tensor) -> torch.Tensor:
    """For each row i, a row j with obs[j] equal to next_obs[i] (exactly), else -1.

    Candidates share a fingerprint (every 12th image row of every channel); each is
    then compared whole, so a shared fingerprint never pairs two different stacks.
    At most a few candidates are compared per row, which bounds the cost when many
    stacks share a fingerprint (a still scene): a missed pair only costs an encoder pass."""
    candidates: dict[bytes, list[int]] = {}
    for j, key in enumerate(_fingerprints(obs)):
        candidates.setdefault(key, []).append(j)
    source = [-1] * len(next_obs)
    for i, key in enumerate(_fingerprints(next_obs)):
        for j in candidates.get(key, [])[:_MAX_CANDIDATES]:
            if torch.equal(next_obs[i], obs[j]):
                source[i] = j
                break
    return torch.tensor(source, dtype=torch.long, device=obs.device)


def _fingerprints(stacks: torch.Tensor) -> list[bytes]:
    """A short key per (C, H, W) stack: a few image rows of every channel."""
    rows = stacks[:, :, ::_FINGERPRINT_STRIDE]
    if rows.dtype == torch.bfloat16:  # numpy has no bfloat16: the same bits as int16
        rows = rows.view(torch.int16)
    return [row.tobytes() for row in rows.cpu().numpy()]
