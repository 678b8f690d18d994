"""How every process that renders sets up GL, before MuJoCo or dm_control pick a backend."""

from __future__ import annotations

import os


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
