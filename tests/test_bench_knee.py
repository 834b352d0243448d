"""``benchmarks/bench_knee.py``'s command line: every ``--env`` setting reaches the demo."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def bench():
    """``benchmarks/bench_knee.py`` as a module (standard library only)."""
    spec = importlib.util.spec_from_file_location(
        "bench_knee", ROOT / "benchmarks" / "bench_knee.py"
    )
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # (its dataclasses look their module up there)
    spec.loader.exec_module(module)
    return module


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
