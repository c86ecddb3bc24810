"""The recovery experiment's scores: coverage with its binomial interval, z-score calibration."""

from __future__ import annotations

import pytest
import torch

from irc_torchrl.algorithms.fit import FitResult
from irc_torchrl.algorithms.recovery import coverage_interval, format_parameters, score_recovery
from irc_torchrl.objectives.fisher import Intervals
from irc_torchrl.theta import Parameter, ThetaSpace


def _fit_of(hat: torch.Tensor, intervals: Intervals) -> FitResult:
    """A converged fit of five agents over θ = (a, b) with the given θ̂ and intervals."""
    return FitResult(
        theta_hat=hat,
        nuisance=torch.zeros(5, 1),
        log_likelihood=torch.zeros(5),
        intervals=intervals,
        converged=torch.ones(5, dtype=torch.bool),
        iterations=1,
        names=["a", "b"],
        information=torch.eye(2).expand(5, 2, 2),
    )


@pytest.mark.parametrize(
    ("covered", "n", "expected"),
    [(38, 40, (0.8308, 0.9939)), (0, 10, (0.0, 0.3085)), (10, 10, (0.6915, 1.0))],
)
def test_coverage_interval_is_clopper_pearson(covered, n, expected):
    """Against tabulated exact (Clopper-Pearson) 95% intervals, the ends included."""
    assert coverage_interval(covered, n) == pytest.approx(expected, abs=1e-4)


@pytest.mark.parametrize(("covered", "n"), [(41, 40), (-1, 40), (0, 0)])
def test_coverage_interval_rejects_impossible_counts(covered, n):
    with pytest.raises(ValueError, match="covered"):
        coverage_interval(covered, n)


def test_scores_report_coverage_interval_and_z_calibration():
    """Five agents, one free parameter a with std 0.1: θ̂ − θ* of 0, 0.1, 0.2 and −0.3 give
    z = 0, 1, 2, −3, intervals ±0.196 cover the first two; the fifth is unidentified (std inf,
    an interval over the whole range that covers) and has no z; b is fixed (std 0)."""
    truth = torch.tensor([[1.0, 5.0]] * 5)
    hat = truth + torch.tensor([[0.0, 0], [0.1, 0], [0.2, 0], [-0.3, 0], [0.5, 0]])
    std = torch.tensor([[0.1, 0.0]] * 4 + [[float("inf"), 0.0]])
    intervals = Intervals(
        std=std,
        low=torch.where(std.isinf(), -10.0, hat - 1.96 * std),
        high=torch.where(std.isinf(), 10.0, hat + 1.96 * std),
        identified=std.isfinite(),
        covariance=torch.zeros(5, 2, 2),
        profiled=torch.zeros(5, 2, dtype=torch.bool),
    )
    result = _fit_of(hat, intervals)
    space = ThetaSpace([Parameter("a", 0.0, 2.0, 1.0), Parameter("b", 0.0, 10.0, 5.0)], {"b": 5.0})
    scores = score_recovery(space, truth, result)["parameters"]
    assert list(scores) == ["a"]
    a = scores["a"]
    assert a["coverage"] == 0.6
    assert a["coverage_ci"] == pytest.approx(coverage_interval(3, 5))
    # z = 0, 1, 2, -3: median 0.5, absolute deviations 0.5, 0.5, 1.5, 3.5 with median 1
    assert a["z_median"] == pytest.approx(0.5, abs=1e-6)
    assert a["z_robust_sd"] == pytest.approx(1.4826, rel=1e-5)
    header, row = format_parameters(scores)
    assert row.split()[:3] == ["a", "0.60", "{:.2f}–{:.2f}".format(*coverage_interval(3, 5))]


def test_scores_read_each_free_parameters_own_column_and_take_medians_against_the_truth():
    """Five agents, a fixed at 1 (θ's first column) and b free: each score is a hand-computed
    median over agents of b alone, errors relative to θ* (not θ̂), an interval covering a truth
    on either of its ends, and the agents' entries carry their own θ*. The error relative to
    b's prior range [0, 20] is the median |err| over 20."""
    truth_b = torch.tensor([2.0, 4.0, 1.0, 5.0, 10.0])
    error_b = torch.tensor([0.2, -0.4, 0.3, 1.0, -4.0])  # |err| 0.2 0.4 0.3 1 4; /θ* .1 .1 .3 .2 .4
    truth = torch.stack([torch.ones(5), truth_b], -1)
    hat = torch.stack([torch.ones(5), truth_b + error_b], -1)
    # b's intervals: covering, ending on θ* (high, then low), missing above, missing below
    low_b = torch.tensor([1.9, 3.0, 1.0, 5.5, 2.0])
    high_b = torch.tensor([2.3, 4.0, 1.6, 6.3, 9.0])  # widths 0.4 1.0 0.6 0.8 7.0
    std_b = torch.tensor([0.1, 0.2, 0.1, 0.5, 2.0])  # z = 2, −2, 3, 2, −2
    intervals = Intervals(
        std=torch.stack([torch.zeros(5), std_b], -1),
        low=torch.stack([torch.ones(5), low_b], -1),
        high=torch.stack([torch.ones(5), high_b], -1),
        identified=torch.tensor([[True, True]] * 4 + [[True, False]]),
        covariance=torch.zeros(5, 2, 2),
        profiled=torch.tensor([[False, False], [False, False], [False, True], [False, False],
                               [False, False]]),
    )  # fmt: skip
    result = _fit_of(hat, intervals)
    space = ThetaSpace([Parameter("a", 0.0, 2.0, 1.0), Parameter("b", 0.0, 20.0, 5.0)], {"a": 1.0})
    summary = score_recovery(space, truth, result)
    b = summary["parameters"]["b"]
    assert list(summary["parameters"]) == ["b"]
    assert b["coverage"] == 0.6 and b["coverage_ci"] == pytest.approx(coverage_interval(3, 5))
    assert b["median_abs_error"] == pytest.approx(0.4)
    assert b["median_rel_error"] == pytest.approx(0.2)
    assert b["median_range_error"] == pytest.approx(0.02)
    assert b["median_ci_width"] == pytest.approx(0.8)
    assert b["z_median"] == pytest.approx(2.0)
    assert b["identified_fraction"] == 0.8 and b["profiled_fraction"] == 0.2
    assert [agent["theta_true"]["b"] for agent in summary["agents"]] == truth_b.tolist()
    row = format_parameters(summary["parameters"])[1].split()
    assert row[0] == "b" and row[-4:] == ["0.4000", "0.2000", "0.0200", "0.8000"]
    # a parameter that may be negative (a logarithm) has no relative error: n/a, not |err|/|θ*|
    signed = ThetaSpace([space["a"], Parameter("b", -10.0, 20.0, 5.0)], {"a": 1.0})
    b = score_recovery(signed, truth, result)["parameters"]["b"]
    assert b["median_rel_error"] is None and b["median_abs_error"] == pytest.approx(0.4)
    assert format_parameters({"b": b})[1].split()[-4:] == ["0.4000", "n/a", "0.0133", "0.8000"]
