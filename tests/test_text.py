"""shared.text: text cut to a bound."""

from shared.text import clip


def test_text_within_its_bound_is_whole_and_longer_text_ends_in_dots_at_the_bound() -> None:
    assert clip("abcde", 5) == "abcde"
    assert clip("", 5) == ""
    assert clip("abcdef", 5) == "ab..."
    assert len(clip("y" * 1000, 512)) == 512
