"""Env-step counts as tables write them and command lines give them (mcrs_lab.analysis.step_notation)."""

from __future__ import annotations

import math

import pytest

from mcrs_lab.analysis.step_notation import format_steps, parse_step_list, seeds_reached, step_labels


def test_format_steps_in_thousands_and_millions() -> None:
    assert [format_steps(s) for s in (0, 640, 12_800, 668_800, 1_001_600)] == [
        "0",
        "640",
        "12.8k",
        "668.8k",
        "1.00M",
    ]


def test_seeds_short_of_a_column_say_how_far_they_got() -> None:
    assert seeds_reached(1, 169_600, [(300.0, 0.0), (math.nan, math.nan)]) == "1 (to 169.6k)"
    assert seeds_reached(3, 1_001_600, [(300.0, 1.0), (310.0, 2.0)]) == "3"


def test_step_labels_take_the_decimals_that_tell_steps_apart() -> None:
    assert step_labels([11_150, 11_200]) == ["11.15k", "11.20k"]
    assert step_labels([0, 100_000, 1_000_000]) == ["0", "100.0k", "1.00M"]


def test_parse_step_list_reads_suffixes_and_names_a_bad_item() -> None:
    assert parse_step_list("1M,100k, 300k,100000") == [100_000, 300_000, 1_000_000]
    for bad in ("0", "-5k", "1.5", "abc", "10x"):
        with pytest.raises(ValueError, match=rf"'{bad}' is not an env step count"):
            parse_step_list(f"100k,{bad}")
