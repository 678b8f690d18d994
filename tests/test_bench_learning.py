"""bench.learning's command line: its own flags, and the settings it passes to both runs."""

from bench.learning import split_settings


def test_settings_after_a_double_dash_go_to_the_runs():
    own, settings = split_settings(["--task", "gripper-valve", "--", "--action-repeat", "1"])
    assert own == ["--task", "gripper-valve"] and settings == ["--action-repeat", "1"]
    assert split_settings(["--only", "train"]) == (["--only", "train"], [])
    assert split_settings(["--"]) == ([], [])
