"""``benchmarks/bench_knee.py``'s command line: every ``--env`` setting reaches the demo."""

from __future__ import annotations

import pytest
from conftest import benchmark_module


@pytest.fixture(scope="module")
def bench():
    """``benchmarks/bench_knee.py`` (standard library only)."""
    return benchmark_module("bench_knee")


def test_repeated_env_flags_add_up(bench):
    # a second --env used to replace the first: the run went without the first's settings
    args = bench.arguments(["--env", "A=1", "B=x=y", "--env", "C=", "--steps", "5"])
    assert bench.demo_settings(args.env) == {"A": "1", "B": "x=y", "C": ""}
    assert args.steps == 5
    assert bench.demo_settings(bench.arguments([]).env) == {}


@pytest.mark.parametrize("item", ["A", "=1"])
def test_an_env_item_that_is_not_key_value_is_refused(bench, item):
    with pytest.raises(SystemExit, match="KEY=VALUE"):
        bench.demo_settings(["A=1", item])
