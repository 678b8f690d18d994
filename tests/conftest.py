import os
import signal
from pathlib import Path

import pytest
import torch

os.environ.setdefault("MUJOCO_GL", "egl")
torch.set_num_threads(2)
# A suite started in the background of a script (`cmd &`) inherits SIGINT ignored, and so would every
# process a test starts: the tests that press Ctrl-C on one would wait for it for ever. A handler of
# our own is reset to the default in each child, as a user's terminal gives it.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)
# anyio is a pytest plugin, so pytest rewrites its modules as they are imported; the module a
# FileResponse imports lazily was then first parsed in a TestClient's event-loop thread, where
# CPython 3.11's parser can fail ("AST constructor recursion depth mismatch"). Imported here, in
# the main thread, it is parsed once and for all before any test.
import anyio._core._fileio  # noqa: E402, F401


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Every test in a tests/test_system_*.py module runs processes: mark it `system`
    (other process-level tests carry the marker themselves)."""
    for item in items:
        if Path(str(item.fspath)).name.startswith("test_system_"):
            item.add_marker(pytest.mark.system)


@pytest.fixture
def cpu() -> torch.device:
    return torch.device("cpu")


@pytest.fixture(autouse=True)
def stop_signal_handlers_kept():
    """`nasa train` run in-process (run_until_stopped) sets the stop signals' handlers; every test
    gets back those it started with, whatever ran before it."""
    saved = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    yield
    for s, handler in saved.items():
        signal.signal(s, handler)
