"""The reference implementation (UoA-CARES/NaSA_TD3), loaded at run time from a checkout the user made.

The project holds none of its code: `load(directory)` imports the checkout's
`nasa_td3.AE_TD3` (and its `networks` package) from `directory`. It needs only
torch, numpy and scikit-image, which the project's dev extras install; its
training loop (`train_loop.py`, which imports `cares_reinforcement_learning`)
is never imported.

One reference update is what its training loop does per sampled minibatch with
intrinsic rewards on: `train_policy` then `train_predictive_model`, on numpy
arrays. Its intrinsic scoring is `get_intrinsic_values`, one transition at a time.

`load_sac_ae(directory)` imports SAC-AE's reference (denisyarats/pytorch_sac_ae) the same way:
its `sac_ae` module, with the `encoder`, `decoder` and `utils` it imports from the checkout.
"""

from __future__ import annotations

import ast
import importlib
import sys
from pathlib import Path
from types import ModuleType

import numpy as np
import torch

ENTRY = "nasa_td3.py"
LATENT_SIZE = 200  # the reference training loop's default --latent_size


class ReferenceError(RuntimeError):
    """The directory is not a checkout of the reference, or it does not load."""


def load_class(directory: Path) -> type:
    """The reference's agent class, imported from `directory`."""
    directory = Path(directory).resolve()
    if not (directory / ENTRY).is_file() or not (directory / "networks").is_dir():
        raise ReferenceError(
            f"{directory} is not a checkout of UoA-CARES/NaSA_TD3 (no {ENTRY} and networks/ there); "
            "get one with: git clone https://github.com/UoA-CARES/NaSA_TD3"
        )
    module = import_from(directory, "nasa_td3", ("nasa_td3", "networks"))
    if not hasattr(module, "AE_TD3"):
        raise ReferenceError(f"{directory / ENTRY} defines no AE_TD3")
    return module.AE_TD3


def argument_defaults(script: Path) -> dict[str, object]:
    """The defaults of a training script's `add_argument` calls, by option name, read from its
    source: the references' scripts import packages the project does not install."""
    found: dict[str, object] = {}
    for node in ast.walk(ast.parse(Path(script).read_text())):
        if isinstance(node, ast.Call) and getattr(node.func, "attr", "") == "add_argument":
            default = [kw.value for kw in node.keywords if kw.arg == "default"]
            if default:
                found[node.args[0].value.lstrip("-")] = ast.literal_eval(default[0])
    return found


def import_from(directory: Path, module: str, names: tuple[str, ...]) -> ModuleType:
    """`module` imported from `directory`, after dropping the modules `names` (and their
    submodules) that another checkout loaded before in this process."""
    for name in [n for n in sys.modules if n in names or n.split(".")[0] in names]:
        del sys.modules[name]
    sys.path.insert(0, str(directory))
    try:
        return importlib.import_module(module)
    except ImportError as err:
        raise ReferenceError(f"the reference in {directory} does not import: {err}") from err
    finally:
        sys.path.remove(str(directory))


SAC_AE_FILES = ("sac_ae.py", "encoder.py", "decoder.py", "utils.py")


def load_sac_ae(directory: Path) -> ModuleType:
    """SAC-AE's reference `sac_ae` module (its `SacAeAgent`), imported from `directory`. Its
    `utils` imports gym at the top, for an environment wrapper the agent does not use."""
    directory = Path(directory).resolve()
    missing = [name for name in SAC_AE_FILES if not (directory / name).is_file()]
    if missing:
        raise ReferenceError(
            f"{directory} is not a checkout of denisyarats/pytorch_sac_ae (no {', '.join(missing)} there); "
            "get one with: git clone https://github.com/denisyarats/pytorch_sac_ae"
        )
    own = tuple(name.removesuffix(".py") for name in SAC_AE_FILES)
    module = import_from(directory, "sac_ae", own)
    for name in own:  # names as common as utils must not shadow other packages' modules later
        sys.modules.pop(name, None)
    if not hasattr(module, "SacAeAgent"):
        raise ReferenceError(f"{directory / 'sac_ae.py'} defines no SacAeAgent")
    return module


def make(directory: Path, action_dim: int, frame_stack: int, device: torch.device):
    """The reference agent at its training loop's settings."""
    cls = load_class(directory)
    return cls(latent_size=LATENT_SIZE, action_num=action_dim, device=device, k=frame_stack)


def update(agent, batch: dict[str, np.ndarray]) -> None:
    """One reference update on a numpy batch (uint8 stacks), as its loop calls it."""
    dones = np.zeros(len(batch["reward"]), dtype=np.int64)
    agent.train_policy((batch["obs"], batch["action"], batch["reward"], batch["next_obs"], dones))
    agent.train_predictive_model((batch["obs"], batch["action"], batch["next_obs"]))


def score_one(agent, obs: np.ndarray, action: np.ndarray, next_obs: np.ndarray) -> float:
    """The reference's intrinsic reward of one transition: surprise + novelty (weights 1, 1)."""
    surprise, novelty = agent.get_intrinsic_values(obs, action, next_obs)
    return float(surprise) + float(novelty)
