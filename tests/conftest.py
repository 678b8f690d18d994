import os
from pathlib import Path

import pytest
import torch

os.environ.setdefault("MUJOCO_GL", "egl")
torch.set_num_threads(2)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Every test in a tests/test_system_*.py module runs processes: mark it `system`
    (other process-level tests carry the marker themselves)."""
    for item in items:
        if Path(str(item.fspath)).name.startswith("test_system_"):
            item.add_marker(pytest.mark.system)


@pytest.fixture
def cpu() -> torch.device:
    return torch.device("cpu")
