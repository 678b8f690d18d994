"""The one environment loop: what the adder receives and what an episode returns."""

from __future__ import annotations

import numpy as np

from shared.env_loop import EnvLoop
from shared.envs import TimeStep


class CountingEnv:
    """Episodes of 3 steps; reward = step number; the last step is a time-limit ending (discount 1)."""

    def __init__(self) -> None:
        self.t = 0

    def _ts(self, reward: float, first: bool, last: bool) -> TimeStep:
        frame = np.full((3, 4, 4), self.t, np.uint8)
        return TimeStep(np.concatenate([frame] * 2), frame, reward, 1.0, first, last)

    def reset(self) -> TimeStep:
        self.t = 0
        return self._ts(0.0, True, False)

    def step(self, action: np.ndarray) -> TimeStep:
        self.t += 1
        return self._ts(float(self.t), False, self.t == 3)


class RecordingAdder:
    def __init__(self) -> None:
        self.calls: list[tuple] = []

    def add_first(self, frame: np.ndarray) -> None:
        self.calls.append(("first", int(frame[0, 0, 0])))

    def add(self, action, reward, discount, frame, last, policy_version) -> None:  # noqa: ANN001
        self.calls.append(
            ("add", float(reward), float(discount), int(frame[0, 0, 0]), bool(last), policy_version))


def test_the_adder_gets_the_first_frame_then_each_transition_with_the_stored_discount():
    adder = RecordingAdder()
    loop = EnvLoop(CountingEnv(), adder, time_limit="terminal")
    ts = loop.reset()
    while not ts.last:
        ts = loop.step(np.zeros(1, np.float32), policy_version=7)
    assert adder.calls == [
        ("first", 0),
        ("add", 1.0, 1.0, 1, False, 7),
        ("add", 2.0, 1.0, 2, False, 7),
        ("add", 3.0, 0.0, 3, True, 7),  # terminal: the reference's time-limit handling
    ]
    assert (loop.episode_return, loop.episode_length, loop.steps) == (6.0, 3, 3)


def test_bootstrap_keeps_the_suite_discount_and_run_episode_resets_the_counts():
    adder = RecordingAdder()
    loop = EnvLoop(CountingEnv(), adder, time_limit="bootstrap")
    assert loop.run_episode(lambda obs: np.zeros(1, np.float32)) == 6.0
    assert adder.calls[-1] == ("add", 3.0, 1.0, 3, True, 0)
    assert loop.run_episode(lambda obs: np.zeros(1, np.float32)) == 6.0
    assert (loop.episode_length, loop.steps) == (3, 6)


def test_a_loop_that_stores_transitions_takes_the_runs_time_limit_not_a_default_of_its_own():
    import pytest

    with pytest.raises(TypeError, match="needs the run's time_limit"):
        EnvLoop(CountingEnv(), RecordingAdder())
    EnvLoop(CountingEnv())  # one that only plays episodes (evaluation) stores no discount
