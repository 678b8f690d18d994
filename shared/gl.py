"""How every process that renders sets up GL, before MuJoCo or dm_control pick a backend."""

from __future__ import annotations

import os
from typing import TYPE_CHECKING, Literal, get_args

if TYPE_CHECKING:
    import mujoco

RenderQuality = Literal["paper", "fast", "plain"]
RENDER_QUALITIES: tuple[str, ...] = get_args(RenderQuality)


def configure() -> None:
    """Defaults that a variable the user set overrides.

    - MUJOCO_GL=egl: headless rendering, with or without a GPU.
    - LP_NUM_THREADS=0: without a GPU, EGL renders through Mesa's software
      rasterizer (llvmpipe), which by default also draws on a thread per core.
      For frames the size of a pixel agent's the extra threads cost more CPU
      than they save and, in `nasa up`, take the cores from the learner's
      threads; with 0 the calling thread draws the same pixels alone. A GPU's
      EGL driver ignores it.
    """
    os.environ.setdefault("MUJOCO_GL", "egl")
    os.environ.setdefault("LP_NUM_THREADS", "0")


def check_render_quality(quality: str) -> None:
    if quality not in RENDER_QUALITIES:
        raise ValueError(f"render_quality must be one of {', '.join(RENDER_QUALITIES)}, got {quality!r}")


def apply_render_quality(model: mujoco.MjModel, quality: RenderQuality) -> None:
    """Set how `model`'s scene is drawn, before its GL context is made (MuJoCo reads the quality
    struct then).

    - `paper`: the model as it is (the suite's 2048 shadow map, 4x multisampling).
    - `fast`: a 512 shadow map and no multisampling: most of the software renderer's cost,
      for a nearly identical image.
    - `plain`: `fast` without shadows or floor reflections. Each of those is a whole extra
      pass of the scene, and on a software renderer they cost several times the rest of
      the frame; the bodies, their colours and their shading stay as they are.
    """
    check_render_quality(quality)
    if quality == "paper":
        return
    model.vis.quality.shadowsize = 512
    model.vis.quality.offsamples = 0
    if quality == "plain":
        model.light_castshadow[:] = 0
        model.mat_reflectance[:] = 0
