"""Networks of NaSA-TD3 and its baselines, with the reference initialisation.

Shapes are computed from a dummy forward pass, never hard-coded for 84x84.

The encoder's and decoder's fc layers index the conv features in (h, w, c)
order where the reference uses (c, h, w). That is a fixed relabelling of fc
inputs/outputs: the same functions, and (orthogonal init being invariant to
permuting rows or columns) the same initial distribution. It lets channels-last
activations pass between conv and fc without a copy.
"""

from __future__ import annotations

import contextlib

import torch
from torch import nn

from shared.config import PIXEL_PRECISIONS


def weight_init(module: nn.Module) -> None:
    """Orthogonal linear layers; delta-orthogonal convolutions (as SAC-AE and the reference)."""
    if isinstance(module, nn.Linear):
        nn.init.orthogonal_(module.weight)
        nn.init.zeros_(module.bias)
    elif isinstance(module, nn.Conv2d | nn.ConvTranspose2d):
        nn.init.zeros_(module.weight)
        nn.init.zeros_(module.bias)
        mid = module.weight.size(2) // 2
        nn.init.orthogonal_(module.weight.data[:, :, mid, mid], nn.init.calculate_gain("relu"))


def relu_(x: torch.Tensor) -> torch.Tensor:
    """ReLU in place. A bfloat16 map that autograd does not track (scoring, acting, targets) is
    clamped through its bits as int16, an integer pass several times faster on the CPU than
    torch's bfloat16 ReLU: a bfloat16 is negative exactly when its bits are, so every value
    comes out as ReLU's. Unlike torch's, a NaN with its sign bit set becomes 0; the weights
    never hold one (a non-finite loss skips the step), and pixels are integers."""
    if x.dtype == torch.bfloat16 and not (x.requires_grad and torch.is_grad_enabled()):
        x.view(torch.int16).clamp_min_(0)
        return x
    return torch.relu_(x)


class ReLU(nn.Module):
    """`relu_` as a layer: torch's in-place ReLU, with its bfloat16 shortcut."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return relu_(x)


def mlp(in_dim: int, hidden_dim: int, out_dim: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Linear(in_dim, hidden_dim),
        nn.ReLU(),
        nn.Linear(hidden_dim, hidden_dim),
        nn.ReLU(),
        nn.Linear(hidden_dim, out_dim),
    )


def float_channels_last(obs: torch.Tensor, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Frame stacks as `dtype` (float32, or bfloat16: exact for pixels) in channels-last layout
    (nothing copied if they already are).

    Channels-last convolutions are faster on CPU (oneDNN) and on GPU (cuDNN). Reordering the
    uint8 stacks first and then widening them moves less memory than doing both in one copy.
    Anything else (the state vectors bench.gripper_state feeds an identity encoder) is widened only."""
    if obs.dim() != 4:
        return obs.to(dtype)
    return obs.contiguous(memory_format=torch.channels_last).to(dtype)


def pixel_dtype(precision: str) -> torch.dtype:
    """What frame stacks are cast to for the pixel networks: bfloat16 under `bf16` (pixels,
    integers 0..255, are exact in it, and autocast would round them to it anyway)."""
    return torch.bfloat16 if precision == "bf16" else torch.float32


def pixel_autocast(x: torch.Tensor, precision: str) -> contextlib.AbstractContextManager:
    """The number format of the pixel networks' matmuls and convolutions.

    `fp32`: float32 throughout (the reference). `bf16`: mixed precision, as torch's
    autocast does it: convolutions and linear layers take bfloat16 inputs and weights
    and accumulate in float32; parameters, gradients' updates and optimizer states stay
    float32. Frame pixels (integers 0..255) are exact in bfloat16."""
    check_precision(precision)
    if precision == "bf16":
        return torch.autocast(x.device.type, dtype=torch.bfloat16)
    return contextlib.nullcontext()


def check_precision(precision: str) -> None:
    if precision not in PIXEL_PRECISIONS:
        choices = ", ".join(PIXEL_PRECISIONS)
        raise ValueError(f"unknown pixel precision {precision!r}; choose one of {choices}")


class Encoder(nn.Module):
    """Conv stack (3x3, stride 2 then 1) -> Linear -> LayerNorm -> tanh.

    `pixel_scale` divides the input: 1.0 for the NaSA-TD3 reference, which feeds
    raw 0..255 floats, and 255.0 for SAC-AE. `precision` (see `pixel_autocast`)
    covers the convolutions and the linear layer; LayerNorm and tanh run in float32,
    so the latent the heads read is float32 either way.
    """

    def __init__(
        self,
        obs_shape: tuple[int, int, int],
        latent_dim: int,
        num_filters: int = 32,
        num_layers: int = 4,
        pixel_scale: float = 1.0,
        precision: str = "fp32",
    ) -> None:
        super().__init__()
        check_precision(precision)
        self.precision = precision
        layers: list[nn.Module] = [nn.Conv2d(obs_shape[0], num_filters, 3, stride=2), ReLU()]
        for _ in range(num_layers - 1):
            layers += [nn.Conv2d(num_filters, num_filters, 3, stride=1), ReLU()]
        self.convs = nn.Sequential(*layers)
        with torch.no_grad():
            conv_shape = self.convs(torch.zeros(1, *obs_shape)).shape[1:]
        self.conv_shape: tuple[int, int, int] = tuple(conv_shape)  # type: ignore[assignment]
        self.fc = nn.Linear(conv_shape.numel(), latent_dim)
        self.ln = nn.LayerNorm(latent_dim)
        self.latent_dim = latent_dim
        self.pixel_scale = pixel_scale
        self.apply(weight_init)

    def forward_conv(self, obs: torch.Tensor) -> torch.Tensor:
        """Conv features flattened in (h, w, c) order: the channels-last output as it lies
        in memory, so no copy (the reference flattens (c, h, w); `fc` is indexed to match)."""
        x = float_channels_last(obs, pixel_dtype(self.precision))
        if self.pixel_scale != 1.0:
            x = x / self.pixel_scale
        return self.convs(x).permute(0, 2, 3, 1).flatten(1)

    def forward(self, obs: torch.Tensor, detach_conv: bool = False) -> torch.Tensor:
        with pixel_autocast(obs, self.precision):
            h = self.forward_conv(obs)
            if detach_conv:  # SAC-AE's actor: conv tied to the critic's, trained by the critic only
                h = h.detach()
            y = self.fc(h)
        return torch.tanh(self.ln(y.float()))

    def copy_conv_weights_from(self, other: Encoder) -> None:
        """Tie conv weights (SAC-AE: the actor's encoder shares the critic's convolutions)."""
        for mine, theirs in zip(self.convs, other.convs, strict=True):
            if isinstance(mine, nn.Conv2d):
                mine.weight = theirs.weight
                mine.bias = theirs.bias


class Decoder(nn.Module):
    """Linear -> ReLU -> reshape -> transposed convs mirroring the encoder.

    `sigmoid_output`: the NaSA-TD3 reference squashes to [0, 1] (target obs/255);
    SAC-AE leaves the output linear (target: 5-bit obs centred on 0). `precision`
    (see `pixel_autocast`) covers the linear layer and the transposed convolutions;
    the output is float32 either way.
    """

    def __init__(
        self,
        obs_shape: tuple[int, int, int],
        conv_shape: tuple[int, int, int],
        latent_dim: int,
        num_filters: int = 32,
        num_layers: int = 4,
        sigmoid_output: bool = True,
        precision: str = "fp32",
    ) -> None:
        super().__init__()
        check_precision(precision)
        self.precision = precision
        self.conv_shape = conv_shape
        self.fc = nn.Linear(latent_dim, int(torch.Size(conv_shape).numel()))
        layers: list[nn.Module] = []
        for _ in range(num_layers - 1):
            layers += [nn.ConvTranspose2d(num_filters, num_filters, 3, stride=1), ReLU()]
        size = conv_shape[1] + 2 * (num_layers - 1)
        # The stride-2 layer must land exactly on the image size (84: 41 -> 84 needs output_padding 1).
        output_padding = obs_shape[1] - ((size - 1) * 2 + 3)
        if output_padding not in (0, 1):
            raise ValueError(f"cannot decode to {obs_shape} from conv shape {conv_shape}")
        layers.append(
            nn.ConvTranspose2d(num_filters, obs_shape[0], 3, stride=2, output_padding=output_padding)
        )
        self.deconvs = nn.Sequential(*layers)
        self.sigmoid_output = sigmoid_output
        self.apply(weight_init)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        x = self.logits(z)
        return torch.sigmoid_(x) if self.sigmoid_output else x

    def logits(self, z: torch.Tensor, keep_precision: bool = False) -> torch.Tensor:
        """The output before the sigmoid (all of it without one): float32, or with
        `keep_precision` the dtype the layers computed it in (bfloat16 under `bf16`), for a
        reader that widens it as it reads (`intrinsic.novelty_of_logits`)."""
        # Channels-last as in the encoder; in-place activations spare two image-sized
        # passes over memory (neither producer needs its output for its gradient).
        # fc's outputs are read in (h, w, c) order, so the view below is already the
        # channels-last layout the transposed convolutions want (no copy).
        channels, height, width = self.conv_shape
        with pixel_autocast(z, self.precision):
            h = relu_(self.fc(z)).view(-1, height, width, channels).permute(0, 3, 1, 2)
            x = self.deconvs(h)
        return x if keep_precision else x.float()


class _SigmoidMSE(torch.autograd.Function):
    """mean((sigmoid(logits) - target)^2) in fewer passes over image-sized memory than
    sigmoid, then mse_loss, then their two backwards."""

    @staticmethod
    def forward(ctx, logits: torch.Tensor, pixels: torch.Tensor, scale: float) -> torch.Tensor:
        s = torch.sigmoid(logits)
        diff = torch.sub(s, pixels, alpha=scale)
        ctx.save_for_backward(s, diff)
        flat = _flat(diff)
        return torch.dot(flat, flat) / diff.numel()

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        s, diff = ctx.saved_tensors
        # d/dx of mean((sigmoid(x) - t)^2) = 2/N (s - t) s (1 - s); sigmoid_backward(g, s) = g s (1 - s).
        grad_logits = torch.ops.aten.sigmoid_backward(diff, s).mul_(grad * (2.0 / diff.numel()))
        return grad_logits, None, None


def _flat(x: torch.Tensor) -> torch.Tensor:
    """A 1-D view of a dense tensor, in whichever of the two layouts it lies."""
    if x.is_contiguous():
        return x.view(-1)
    return x.permute(0, 2, 3, 1).reshape(-1)  # channels-last: a view too


def sigmoid_mse(logits: torch.Tensor, pixels: torch.Tensor, scale: float = 1.0 / 255.0) -> torch.Tensor:
    """The reconstruction loss of a sigmoid decoder: F.mse_loss(sigmoid(logits), pixels * scale),
    fused. `pixels`: frame stacks of the logits' shape, of any dtype (read as float32)."""
    return _SigmoidMSE.apply(logits, pixels, scale)


class DeterministicActor(nn.Module):
    """TD3 actor head on a latent: hidden -> hidden -> tanh actions."""

    def __init__(self, latent_dim: int, action_dim: int, hidden_dim: int) -> None:
        super().__init__()
        self.net = mlp(latent_dim, hidden_dim, action_dim)
        self.apply(weight_init)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        return torch.tanh(self.net(z))


class TwinQ(nn.Module):
    """Two Q heads on (latent, action)."""

    def __init__(self, latent_dim: int, action_dim: int, hidden_dim: int) -> None:
        super().__init__()
        self.q1 = mlp(latent_dim + action_dim, hidden_dim, 1)
        self.q2 = mlp(latent_dim + action_dim, hidden_dim, 1)
        self.apply(weight_init)

    def forward(self, z: torch.Tensor, action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        za = torch.cat([z, action], dim=1)
        return self.q1(za), self.q2(za)


class Ensemble(nn.Module):
    """K latent-dynamics predictors (z, a) -> z', kept as separate modules as the reference does."""

    def __init__(self, latent_dim: int, action_dim: int, hidden_dim: int, size: int) -> None:
        super().__init__()
        self.members = nn.ModuleList(
            mlp(latent_dim + action_dim, hidden_dim, latent_dim) for _ in range(size)
        )
        self.apply(weight_init)

    def forward(self, z: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Stacked predictions, shape (K, B, latent)."""
        za = torch.cat([z, action], dim=1)
        return torch.stack([member(za) for member in self.members])


class GaussianActor(nn.Module):
    """SAC-AE's actor head: tanh-squashed Gaussian with bounded log-std."""

    def __init__(
        self, latent_dim: int, action_dim: int, hidden_dim: int, log_std_min: float, log_std_max: float
    ) -> None:
        super().__init__()
        self.net = mlp(latent_dim, hidden_dim, 2 * action_dim)
        self.log_std_min = log_std_min
        self.log_std_max = log_std_max
        self.apply(weight_init)

    def forward(self, z: torch.Tensor, sample: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
        """Returns (squashed action, log-prob); the mean action when `sample` is False."""
        mu, log_std = self.net(z).chunk(2, dim=-1)
        log_std = torch.tanh(log_std)
        log_std = self.log_std_min + 0.5 * (self.log_std_max - self.log_std_min) * (log_std + 1)
        if not sample:
            return torch.tanh(mu), torch.zeros(mu.shape[0], 1, device=mu.device)
        std = log_std.exp()
        noise = torch.randn_like(mu)
        pre_tanh = mu + noise * std
        log_prob = (-0.5 * noise.pow(2) - log_std).sum(-1, keepdim=True)
        log_prob = log_prob - 0.5 * torch.log(torch.tensor(2 * torch.pi)) * mu.shape[-1]
        action = torch.tanh(pre_tanh)
        log_prob = log_prob - torch.log(torch.relu(1 - action.pow(2)) + 1e-6).sum(-1, keepdim=True)
        return action, log_prob
