"""What the autoencoder sees, as images and videos: observations beside Dec(Enc(s)), with novelty.

Used by the evaluator, which holds the policy's weights and, once per
evaluation period, the autoencoder's (the learner sends the decoder with the
weights then): the learner renders nothing. The reconstruction shown is of
the newest frame of each stacked observation; novelty is the agent's
(1 - SSIM between the whole stacked observation and its reconstruction).

Videos are MP4 (H.264 through imageio's ffmpeg plugin, whose wheel ships an
ffmpeg binary): each frame is the task's camera at `camera_size` on the left,
the observation above its reconstruction on the right.
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from shared import intrinsic

CAMERA_SIZE = 256


class Autoencoder(NamedTuple):
    """What a picture reconstructs through: an agent's encoder and decoder, and its algorithm."""

    encoder: torch.nn.Module
    decoder: torch.nn.Module
    algo: str


@torch.no_grad()
def reconstruct(agent, obs: np.ndarray, chunk: int = 64) -> tuple[np.ndarray, np.ndarray]:  # noqa: ANN001
    """Dec(Enc(obs)) of a batch (N, C*k, H, W) uint8: its newest frames (N, H, W, 3) uint8 and
    each observation's novelty (N,). `agent` has an `encoder`, a `decoder` and its `algo` (an
    `Autoencoder`, or an agent whose own modules are named so)."""
    frames, novelty = [], []
    device = next(agent.decoder.parameters()).device
    for i in range(0, len(obs), chunk):
        x = torch.as_tensor(obs[i:i + chunk], device=device)  # uint8; the encoder casts
        rec = agent.decoder(agent.encoder(x)).float()
        if agent.algo == "sac_ae":
            rec = rec + 0.5  # SAC-AE's decoder targets the 5-bit observation centred on 0
        novelty.append(intrinsic.novelty(x, rec).float().cpu().numpy())
        rec = rec.clamp(0.0, 1.0)
        frames.append((rec[:, -3:] * 255.0).round().to(torch.uint8).permute(0, 2, 3, 1).cpu().numpy())
    return np.concatenate(frames), np.concatenate(novelty)


def newest_frames(obs: np.ndarray) -> np.ndarray:
    """The newest frame of each stacked observation: (N, C*k, H, W) -> (N, H, W, 3)."""
    return np.ascontiguousarray(obs[:, -3:].transpose(0, 2, 3, 1))


def upscale(image: np.ndarray, factor: int) -> np.ndarray:
    """Nearest-neighbour upscaling of (H, W, C) by an integer factor (pixels stay visible)."""
    return image.repeat(factor, axis=0).repeat(factor, axis=1)


def fit(image: np.ndarray, size: int) -> np.ndarray:
    """(H, W, 3) to (size, size, 3): nearest-neighbour, so frames keep their pixels."""
    h, w = image.shape[:2]
    rows = (np.arange(size) * h // size).clip(0, h - 1)
    cols = (np.arange(size) * w // size).clip(0, w - 1)
    return image[rows][:, cols]


def sheet(frames: np.ndarray, recs: np.ndarray, novelty: np.ndarray, scale: int = 2) -> np.ndarray:
    """The autoencoder's view: frames on top, reconstructions below, novelty written under each."""
    from PIL import Image, ImageDraw

    n, h, w, _ = frames.shape
    gap, label = 2, 14
    cell_w, cell_h = w * scale, h * scale
    out = np.full((2 * cell_h + gap + label, n * (cell_w + gap) - gap, 3), 255, np.uint8)
    for i in range(n):
        x = i * (cell_w + gap)
        out[:cell_h, x:x + cell_w] = upscale(frames[i], scale)
        out[cell_h + gap:2 * cell_h + gap, x:x + cell_w] = upscale(recs[i], scale)
    image = Image.fromarray(out)
    draw = ImageDraw.Draw(image)
    for i in range(n):
        draw.text((i * (cell_w + gap) + 2, 2 * cell_h + gap + 1), f"{novelty[i]:.3f}", fill=(40, 40, 40))
    return np.asarray(image)


def video_frame(camera: np.ndarray, frame: np.ndarray, rec: np.ndarray) -> np.ndarray:
    """One video frame: the camera (size x size) on the left, observation over reconstruction right."""
    size = camera.shape[0]
    half = size // 2
    right = np.concatenate([fit(frame, half), fit(rec, half)], axis=0)
    right = np.pad(right, ((0, size - right.shape[0]), (0, 0), (0, 0)))
    return np.concatenate([camera, right], axis=1)


def camera_frame(env, size: int = CAMERA_SIZE) -> np.ndarray | None:  # noqa: ANN001
    """The task's camera at size x size (H, W, 3), or None when the environment cannot render one."""
    pixels = getattr(env, "_env", None)
    suite = getattr(pixels, "_env", None)
    physics = getattr(suite, "physics", None)
    if physics is None:
        return None
    return np.ascontiguousarray(physics.render(size, size, camera_id=getattr(pixels, "camera_id", 0)))


def write_mp4(path: Path, frames: list[np.ndarray], fps: int = 20) -> None:
    """Encode (H, W, 3) uint8 frames as H.264 MP4 (written to a temporary name, then renamed)."""
    import imageio.v2 as imageio

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.stem + ".tmp.mp4")
    try:
        with imageio.get_writer(tmp, fps=fps, codec="libx264", quality=7, macro_block_size=16,
                                ffmpeg_log_level="error") as writer:
            for frame in frames:
                writer.append_data(frame)
    except BaseException:
        tmp.unlink(missing_ok=True)  # a full disk: free what the failed write took
        raise
    tmp.replace(path)


def count_frames(path: Path) -> int:
    """Decode an MP4 and count its frames."""
    import imageio.v2 as imageio

    with imageio.get_reader(path, format="ffmpeg") as reader:
        return sum(1 for _ in reader)
