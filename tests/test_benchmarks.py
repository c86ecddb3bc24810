"""The benchmark scripts refuse a bad size, seed or config in one line before any work.

Their figures are measured by running them (docs/benchmarks.md); here, only what a typo
costs: each once ran minutes of work before a traceback (``bench_fit --agents 0`` after 51 s,
``bench_env2d --repeats 0`` a ZeroDivisionError after 136 s).
"""

from __future__ import annotations

import importlib
import sys
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).parent.parent / "benchmarks"


@pytest.fixture()
def bench(monkeypatch):
    """A benchmark script's module, importable as the scripts import ``_common``."""
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    return importlib.import_module


@pytest.mark.parametrize(
    "script, argv, message",
    [
        ("bench_fit", ["--agents", "0"], "argument --agents: expected an integer ≥ 1, got '0'"),
        ("bench_fit", ["--seed", "-1"], "argument --seed: expected an integer ≥ 0, got '-1'"),
        ("bench_lapse", ["--trials", "x"], "argument --trials: expected an integer ≥ 12, got 'x'"),
        ("bench_env2d", ["--repeats", "0"], "argument --repeats: expected an integer ≥ 1"),
        ("bench_actor_precision", ["--threads", "0"], "argument --threads: expected an integer"),
        ("bench_demo1d", ["--seeds", "1", "-2"], "argument --seeds: expected an integer ≥ 0"),
        ("bench_ensemble", ["--seeds", "a"], "argument --seeds: expected an integer ≥ 0"),
        ("bench_ensemble", ["ddpg.gamma=2"], "ddpg.gamma"),
    ],
)
def test_a_bad_argument_is_refused_in_one_line_before_any_work(
    bench, monkeypatch, capsys, script, argv, message
):
    module = bench(script)
    monkeypatch.setattr(sys, "argv", [f"{script}.py", *argv])
    with pytest.raises(SystemExit) as exited:
        module.main()
    assert exited.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert message in err[-1], err
    assert err[-1].startswith(f"{script}.py: error: ")
