"""The evaluator's pictures of a run: the autoencoder's view and evaluation videos, in <data>/media.

The learner sends the evaluator the weights of each eval step with the
autoencoder's modules that the policy lacks (services/learner/core.py: the
decoder, and SAC-AE's critic encoder); `AutoencoderTap` loads them into the
evaluated agent, so the view is always the autoencoder of the evaluated
policy's own update. Everything here runs in the evaluator's process, after
an evaluation's episodes: the learner's update loop renders nothing.

<data>/media/media.json lists what is there, for the dashboard:
`{"autoencoder": {step, policy_version, autoencoder_version, novelty, image},
"videos": [{step, file, frames, return}]}`.
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import numpy as np

from shared.agents.base import check_fits, module_state
from shared.files import finite_only, replace_text
from shared.scalars import TENSORBOARD_DIR, Scalars
from shared.video import (
    CAMERA_SIZE,
    Autoencoder,
    fit,
    newest_frames,
    reconstruct,
    sheet,
    video_frame,
    write_mp4,
)

MEDIA_DIR = "media"
AE_IMAGE = "autoencoder.png"


class AutoencoderTap:
    """Stands for the agent in a WeightsSubscriber: loads the policy into it and, from weights that
    carry the autoencoder's other modules (the agent's `view_extras`: the decoder, and SAC-AE's
    critic encoder), those too. `autoencoder` is the agent's encoder and decoder while every part of
    them came in one message (the evaluated policy's own), else None."""

    def __init__(self, agent) -> None:  # noqa: ANN001
        self.agent = agent
        self.autoencoder: Autoencoder | None = None

    def load_policy_state_dict(self, state: dict) -> None:
        extras = self.agent.view_extras()
        if "decoder" not in extras and module_state(state, "decoder"):
            raise ValueError(f"weights carry a decoder, but {type(self.agent).__name__} has none")
        sent = {name: module_state(state, name) for name in extras}
        for name, part in sent.items():  # checked before anything loads, as the policy is
            if part:
                check_fits(extras[name].state_dict(), part, f"the {name}'s weights")
        prefixes = tuple(f"{name}." for name in extras)
        self.agent.load_policy_state_dict({k: v for k, v in state.items() if not k.startswith(prefixes)})
        for name, part in sent.items():
            if part:
                extras[name].load_state_dict(part)
        # Never an encoder shown with another message's decoder: a learner of an older version sent
        # SAC-AE's decoder without the critic encoder it reads, so its view is not drawn.
        whole = bool(extras) and all(sent.values())
        self.autoencoder = Autoencoder(*self.agent.view_modules(), self.agent.algo) if whole else None


class EvalMedia:
    def __init__(self, data: Path, frames: int = 8) -> None:
        self.dir = Path(data) / MEDIA_DIR
        self.dir.mkdir(parents=True, exist_ok=True)
        self.frames = frames
        self.scalars = Scalars(Path(data) / TENSORBOARD_DIR / "evaluator")
        self.manifest = self._load(self.dir / "media.json")

    @staticmethod
    def _load(path: Path) -> dict:
        """The manifest an earlier evaluator left; a damaged one is moved aside (its pictures stay on
        disk) and a new one started: the pictures are extras, and must not keep the evaluator down."""
        empty = {"autoencoder": None, "videos": []}
        if not path.exists():
            return empty
        try:
            manifest = json.loads(path.read_text())
            if not isinstance(manifest, dict) or not isinstance(manifest.get("videos", []), list):
                raise ValueError("not a media manifest")
        except (OSError, ValueError) as err:
            aside = path.with_name(path.name + ".damaged")
            os.replace(path, aside)
            print(f"evaluator: {path} is damaged ({err}); moved to {aside.name}, starting a new one",
                  file=sys.stderr, flush=True)
            return empty
        # Entries that are not a video's (a hand edit) are dropped rather than trip every later video.
        videos = [v for v in manifest.get("videos", []) if isinstance(v, dict)]
        return {**empty, **manifest, "videos": videos}

    def autoencoder_view(self, autoencoder, obs: np.ndarray, step: int,  # noqa: ANN001
                         policy_version: int) -> np.ndarray:
        """Frames spread over an evaluation episode beside Dec(Enc(s)), with each one's novelty.
        The decoder came in the policy's own message, so the view's autoencoder version is the
        policy's (both fields stay in media.json, which the dashboard reads)."""
        from PIL import Image

        idx = np.unique(np.linspace(0, len(obs) - 1, min(self.frames, len(obs))).round().astype(int))
        recs, novelty = reconstruct(autoencoder, obs[idx])
        image = sheet(newest_frames(obs[idx]), recs, novelty)
        tmp = self.dir / (AE_IMAGE + ".tmp")
        try:
            Image.fromarray(image).save(tmp, format="PNG")
        except BaseException:
            tmp.unlink(missing_ok=True)  # a full disk: free what the failed write took
            raise
        os.replace(tmp, self.dir / AE_IMAGE)
        self.scalars.image("autoencoder/view", image, step)
        self.scalars.add({"autoencoder/novelty_mean": float(novelty.mean())}, step)
        self.scalars.flush()
        self.manifest["autoencoder"] = {
            "step": int(step), "policy_version": int(policy_version),
            "autoencoder_version": int(policy_version),
            "novelty": [round(float(v), 4) for v in novelty], "image": AE_IMAGE,
        }
        self._save()
        return image

    def video(self, autoencoder, obs: np.ndarray, cameras: list[np.ndarray | None], step: int,  # noqa: ANN001
              episode_return: float) -> Path:
        """An MP4 of one evaluation episode: camera | observation over its reconstruction."""
        frames = newest_frames(obs)
        recs = reconstruct(autoencoder, obs)[0] if autoencoder is not None else np.zeros_like(frames)
        out = [video_frame(cam if cam is not None else fit(frame, CAMERA_SIZE), frame, rec)
               for cam, frame, rec in zip(cameras, frames, recs, strict=True)]
        path = self.dir / f"eval_step_{step:09d}.mp4"
        write_mp4(path, out)
        entry = {"step": int(step), "file": path.name, "frames": len(out),
                 "return": round(float(episode_return), 3)}
        # A restarted evaluator may play a step again: its video replaces the listed one.
        self.manifest["videos"] = [v for v in self.manifest["videos"] if v.get("file") != path.name] + [entry]
        self._save()
        return path

    def newest_video_step(self) -> int | None:
        """The step of the newest video media.json lists, or None."""
        steps = [v.get("step") for v in self.manifest["videos"]]
        return max((s for s in steps if isinstance(s, int) and not isinstance(s, bool)), default=None)

    def _save(self) -> None:
        # Strict JSON: the learner serves the file as it is, and a browser refuses NaN.
        text = json.dumps(finite_only(self.manifest), indent=1, allow_nan=False)
        replace_text(self.dir / "media.json", text, durable=True)

    def close(self) -> None:
        self.scalars.close()
