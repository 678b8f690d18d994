"""nasa up's layout: chosen from the cores and the GPU, every choice overridable by a flag."""

import pytest

from nasa.layout import LOW_PRIORITY, choose
from nasa.up import layout_of, parse_up
from shared.config import ConfigError


def test_a_small_cpu_machine_gives_the_learner_every_core_and_one_actor():
    lay = choose(2, gpu=False)
    assert (lay.actors, lay.learner_threads, lay.evaluator, lay.evaluator_nice) == (1, 2, True, LOW_PRIORITY)
    assert lay.omp_passive  # the learner's threads share the cores with the other services
    assert not choose(16, gpu=False).omp_passive


def test_a_large_cpu_machine_keeps_cores_for_the_learner_and_a_normal_priority_evaluator():
    lay = choose(16, gpu=False)
    assert lay.actors == 2 and lay.learner_threads == 13 and lay.evaluator_nice == 0


def test_with_a_gpu_the_spare_cores_go_to_actors():
    assert choose(16, gpu=True).actors == 8
    assert choose(6, gpu=True).actors == 3
    assert choose(2, gpu=True).actors == 1


def test_flags_override_each_choice():
    cmd, _ = parse_up(["--actors", "3", "--learner-threads", "1", "--evaluator-nice", "0", "--no-evaluator"])
    lay = layout_of(cmd, gpu=False, cores=2)
    assert (lay.actors, lay.learner_threads, lay.evaluator, lay.evaluator_nice) == (3, 1, False, 0)
    default, _ = parse_up([])
    assert layout_of(default, gpu=False, cores=2) == choose(2, gpu=False)


def test_the_layout_says_what_it_chose_and_how_to_change_it():
    text = choose(2, gpu=False).describe()
    assert "1 actor(s)" in text and "learner 2 torch thread(s)" in text and f"nice {LOW_PRIORITY}" in text
    assert "--actors" in text and "--learner-threads" in text


def test_a_negative_count_is_refused_with_a_clear_error():
    for flag in ("--actors", "--learner-threads"):
        with pytest.raises(ConfigError, match="must be >= 0"):
            parse_up([flag, "-1"])
