"""Intervals calibrated by simulation: pivots, factors, widened intervals, the 1D and 2D runs.

Fixed seeds throughout; tolerances are stated where they are asserted.
"""

import dataclasses
import math

import numpy as np
import pytest
import torch

from irc_torchrl.algorithms import recover2d
from irc_torchrl.algorithms.calibration import (
    FEWEST_REFITS,
    MIN_REFITS,
    TAILS,
    Calibration,
    agent_intervals,
    calibrate_intervals,
    format_factors,
    interval_pivots,
    simulate_at_fits,
    warn_too_few_refits,
)
from irc_torchrl.algorithms.ensemble import load_ensemble_policy
from irc_torchrl.algorithms.fit import FitResult, fit_theta
from irc_torchrl.algorithms.recordings import simulate_recordings
from irc_torchrl.algorithms.recover2d import Recovery2DConfig, predicted_widths, recover_firefly2d
from irc_torchrl.algorithms.recovery import recover_agents, score_recovery
from irc_torchrl.algorithms.simulate import boltzmann_policy, motor_noise_policy, simulate_agents
from irc_torchrl.checks import (
    CALIBRATION,
    INFORMATION,
    PARTICLES,
    SIMULATION,
    STARTS,
    derived_seed,
)
from irc_torchrl.config import AgentsConfig, FitConfig, SimulateConfig
from irc_torchrl.data.trajectories import TRIAL_KEYS
from irc_torchrl.envs.firefly2d import Firefly2DModel
from irc_torchrl.envs.model import sensed_world
from irc_torchrl.modules.actor_critic import FeaturePolicy, censored_action_model
from irc_torchrl.modules.likelihood import BoltzmannActionModel
from irc_torchrl.objectives.fisher import Z95, fisher_intervals
from irc_torchrl.objectives.inverse import InverseRationalLoss

TEMPERATURE = 0.5


def _result(space, theta_hat: torch.Tensor, hessian: torch.Tensor) -> FitResult:
    """A fit result with Wald intervals from ``hessian`` over the free θ (no nuisance)."""
    u = space.to_unconstrained(theta_hat)[:, space.free_mask]
    n = theta_hat.shape[0]
    return FitResult(
        theta_hat=theta_hat,
        nuisance=torch.zeros(n, 0, dtype=theta_hat.dtype),
        log_likelihood=torch.zeros(n, dtype=theta_hat.dtype),
        intervals=fisher_intervals(space, theta_hat, u, hessian),
        converged=torch.ones(n, dtype=torch.bool),
        iterations=1,
        names=space.names,
        information=hessian,
    )


@pytest.fixture(scope="module")
def space2d():
    return Firefly2DModel().theta_space


@pytest.fixture(scope="module")
def wald(space2d):
    """Wald intervals of 64 fits of random θ̂ and curvature, and truths around them."""
    g = torch.Generator().manual_seed(0)
    n, k = 64, len(space2d.free_names)
    theta_hat = space2d.sample((n,), generator=g, dtype=torch.float64)
    scale = torch.exp(3 * torch.rand(n, k, generator=g, dtype=torch.float64))
    result = _result(space2d, theta_hat, torch.diag_embed(scale**2))
    u = space2d.to_unconstrained(theta_hat)
    u[:, space2d.free_mask] += 1.5 * torch.randn(n, k, generator=g, dtype=torch.float64) / scale
    return result, space2d.from_unconstrained(u)


def test_an_interval_covers_exactly_where_its_pivot_is_within_the_quantile(space2d, wald):
    result, truth = wald
    free = space2d.free_mask
    pivot = interval_pivots(space2d, truth, result)
    covered = (result.intervals.low <= truth) & (truth <= result.intervals.high)
    assert 0.5 < covered[:, free].double().mean() < 0.95  # both kinds occur
    assert torch.equal(pivot.abs() <= Z95, covered[:, free])
    # a Wald interval's pivot is the z-score in the fit's coordinates
    z = (space2d.to_unconstrained(truth) - space2d.to_unconstrained(result.theta_hat))[:, free]
    u_sd = (result.information.diagonal(dim1=-2, dim2=-1)) ** -0.5
    torch.testing.assert_close(pivot, z / u_sd)


def test_a_pivot_reads_the_half_width_on_the_truths_side_of_an_asymmetric_interval(space2d):
    """A profile interval need not be symmetric about θ̂: its pivot is the truth's distance
    from θ̂ over the half-width on the truth's side (in the fit's coordinates), so a truth
    2 past θ̂ inside a side of 3 is covered (pivot 2/3 Z95) and one 2 short of θ̂ outside a
    side of 1 is not (pivot −2 Z95)."""
    free = space2d.free_mask
    k = len(space2d.free_names)
    theta_hat = space2d.default(torch.float64).repeat(2, 1)
    result = _result(space2d, theta_hat, torch.eye(k, dtype=torch.float64).repeat(2, 1, 1))
    u_hat = space2d.to_unconstrained(theta_hat)

    def moved(by: float) -> torch.Tensor:
        return space2d.from_unconstrained(u_hat + by * free)

    ends = dataclasses.replace(result.intervals, low=moved(-1.0), high=moved(3.0))
    result = dataclasses.replace(result, intervals=ends)
    truth = torch.cat([moved(2.0)[:1], moved(-2.0)[1:]])
    pivot = interval_pivots(space2d, truth, result)
    expected = torch.tensor([[2 / 3], [-2.0]], dtype=torch.float64).expand(2, k) * Z95
    torch.testing.assert_close(pivot, expected)


def test_a_refit_without_an_interval_has_no_pivot_and_one_exactly_on_the_truth_pivot_zero(
    space2d,
):
    """A parameter the refit leaves without an interval (no curvature: the whole range) has
    a NaN pivot, which no factor counts; a truth exactly at θ̂ has pivot 0 (covered), also
    where the interval has no width there; the others are z-scores (1 sd off: pivot 1)."""
    free = space2d.free_mask
    k = len(space2d.free_names)
    theta_hat = space2d.default(torch.float64).repeat(2, 1)
    hessian = torch.eye(k, dtype=torch.float64).repeat(2, 1, 1)
    hessian[1, 0, 0] = 0.0
    result = _result(space2d, theta_hat, hessian)
    point = result.intervals.low.clone()
    point[0] = theta_hat[0]
    high = result.intervals.high.clone()
    high[0] = theta_hat[0]
    result = dataclasses.replace(
        result, intervals=dataclasses.replace(result.intervals, low=point, high=high)
    )
    u = space2d.to_unconstrained(theta_hat)
    truth = torch.cat([theta_hat[:1], space2d.from_unconstrained(u[1:] + 1.0 * free)])
    pivot = interval_pivots(space2d, truth, result)
    assert torch.equal(pivot[0], torch.zeros(k, dtype=torch.float64))
    assert pivot[1, 0].isnan()
    torch.testing.assert_close(pivot[1, 1:], torch.ones(k - 1, dtype=torch.float64))


def test_a_calibrated_covariance_scales_by_both_parameters_factors(space2d):
    """Factors that differ per parameter scale the covariance of parameters i and j by
    ``c_i c_j`` (the correlations stay), and each standard deviation by its own factor."""
    k = len(space2d.free_names)
    g = torch.Generator().manual_seed(0)
    a = torch.randn(2, k, k, generator=g, dtype=torch.float64)
    theta_hat = space2d.default(torch.float64).repeat(2, 1)
    result = _result(space2d, theta_hat, a @ a.mT + k * torch.eye(k, dtype=torch.float64))
    factor = torch.linspace(0.5, 2.0, k, dtype=torch.float64)
    calibrated = Calibration(space2d.free_names, factor, torch.zeros(1, 1, k)).apply(
        space2d, result
    )
    old, new = result.intervals, calibrated.intervals
    torch.testing.assert_close(new.covariance, old.covariance * factor.unsqueeze(-1) * factor)
    free = space2d.free_mask
    torch.testing.assert_close(new.std[:, free], old.std[:, free] * factor)


def test_the_own_factor_is_the_pivots_95_percent_quantile_at_rank_95_of_m_plus_1(space2d):
    """Weibull's quantile (rank 0.95 (m + 1) of m refits, as NumPy's ``method="weibull"``),
    the refits without an interval left out; of 19 refits the largest, of 18 none."""
    k = len(space2d.free_names)
    pivots = torch.linspace(-4, 4, 2 * 50 * k, dtype=torch.float64).view(2, 50, k)
    calibration = Calibration.from_pivots(space2d.free_names, pivots, tail="own")
    size = pivots.abs().flatten(0, 1).numpy()
    expected = np.quantile(size, 0.95, axis=0, method="weibull") / Z95
    torch.testing.assert_close(calibration.factor, torch.from_numpy(expected))
    pivots[1, :, 0] = torch.nan
    calibration = Calibration.from_pivots(space2d.free_names, pivots, tail="own")
    expected = np.quantile(size[:50, 0], 0.95, method="weibull") / Z95
    assert calibration.factor[0].item() == pytest.approx(expected, rel=1e-9)
    for tail in TAILS:
        few = torch.arange(1.0, 20.0, dtype=torch.float64).view(1, 19, 1).expand(1, 19, k)
        assert calibration_factor(few, tail) == pytest.approx(19 / Z95, rel=1e-12)
        assert math.isinf(calibration_factor(few[:, 1:], tail))
        # 19 with an interval beside a refit without one (NaN, sorted past the largest)
        lacking = torch.cat([few, torch.full((1, 1, k), torch.nan, dtype=torch.float64)], 1)
        assert calibration_factor(lacking, tail) == pytest.approx(19 / Z95, rel=1e-12)


def calibration_factor(pivots: torch.Tensor, tail: str) -> float:
    """The first parameter's factor from ``pivots`` ``[1, m, k]`` of the 2D task's names."""
    names = [f"p{i}" for i in range(pivots.shape[-1])]
    return Calibration.from_pivots(names, pivots.contiguous(), tail).factor[0].item()


def test_too_few_refits_for_any_factor_are_warned_of_before_any_refit(recwarn):
    """3 agents × 2 datasets: 6 refits, no factor; 10 × 2: 20, a factor; 0: no calibration."""
    with pytest.warns(UserWarning, match=r"calibrate=2: 3 agent\(s\) × 2 dataset\(s\) give 6 "):
        warn_too_few_refits(3, 2)
    warn_too_few_refits(10, 2)
    warn_too_few_refits(3, 0)
    assert not recwarn.list


@pytest.mark.parametrize("m", [12, 19, 36, 80])
def test_a_factor_covers_a_new_pivot_95_percent_of_the_time_at_any_count(m):
    """20,000 sets of m Gaussian pivots and a new one each: the factor read from the m covers
    the new one in 95% of sets ± 3 binomial s.e. (measured 0.951, 0.949, 0.953 at m = 19, 36,
    80); with 12 there is no factor (it covers always). The interpolated quantile it replaced
    covered 0.939 at m = 80, 0.892 at m = 12."""
    generator = torch.Generator().manual_seed(m)
    pivots = torch.randn(1, m + 1, 20_000, dtype=torch.float64, generator=generator)
    # each set one "parameter" of its own: the own tail reads each apart
    names = [f"p{i}" for i in range(20_000)]
    factor = Calibration.from_pivots(names, pivots[:, :m].contiguous(), "own").factor
    covered = (pivots[0, m].abs() <= factor * Z95).double().mean().item()
    if m < FEWEST_REFITS:
        assert factor.isinf().all()
    else:
        assert covered == pytest.approx(0.95, abs=3 * (0.95 * 0.05 / 20_000) ** 0.5)


@pytest.mark.parametrize("tail", ["shrunk", "own"])
def test_refits_without_intervals_or_missing_with_zero_width_give_no_factor(space2d, tail):
    names = space2d.free_names
    pivots = torch.randn(2, 50, len(names), generator=torch.Generator().manual_seed(0))
    pivots = pivots.double()
    # refits without an interval do not count; with none, nothing vouches for the intervals
    pivots[1, :, 0], pivots[:, :, 1] = torch.nan, torch.nan
    calibration = Calibration.from_pivots(names, pivots, tail)
    assert calibration.factor[0].isfinite() and calibration.factor[1].isinf()
    assert calibration.to_dict()["tail"] == tail
    # more than 5% of refits missing with zero-width intervals (infinite pivots): infinite
    pivots[:, :10, 2] = torch.inf
    assert Calibration.from_pivots(names, pivots, tail).factor[2].isinf()
    for bad in (pivots[0], pivots[..., :3]):
        with pytest.raises(ValueError, match="pivots: expected"):
            Calibration.from_pivots(names, bad, tail)
    with pytest.raises(ValueError, match="tail: expected one of"):
        Calibration.from_pivots(names, pivots, "pooled")


def _t_pivots(scales: torch.Tensor, n_agents: int, seed: int, df: float = 3.0) -> torch.Tensor:
    """Pivots of 2 datasets × ``n_agents``: Student-t draws times each parameter's scale."""
    torch.manual_seed(seed)
    t = torch.distributions.StudentT(torch.tensor(df, dtype=torch.float64))
    return t.sample((2, n_agents, len(scales))) * scales


def test_shrunk_tails_are_shared_where_parameters_differ_by_scale_alone():
    """8 parameters whose pivots are one Student-t (3 dof) at scales 0.5–4, 2 × 40 refits:
    each own 95% quantile over the median rests on 4 refits and scatters (sd of its log over
    the parameters 0.06–0.22 on 10 seeds), the shrunk ones agree (asserted: under a third of
    that; measured: under 0.001). Each factor scales with its parameter's pivots, and the same
    pivots give the same factors (the bootstrap is seeded)."""
    names = [f"p{i}" for i in range(8)]
    scales = torch.linspace(0.5, 4, 8, dtype=torch.float64)
    for seed in range(10):
        pivots = _t_pivots(scales, 40, seed)
        median = pivots.abs().flatten(0, 1).quantile(0.5, dim=0)
        own, shrunk = (
            (Calibration.from_pivots(names, pivots, tail).factor / median).log().std()
            for tail in ("own", "shrunk")
        )
        assert own > 0.05 and shrunk < own / 3, (seed, own, shrunk)
    pivots = _t_pivots(scales, 40, 0)
    factor = Calibration.from_pivots(names, pivots, "shrunk").factor
    assert torch.equal(factor, Calibration.from_pivots(names, pivots.clone(), "shrunk").factor)
    doubled = pivots.clone()
    doubled[..., 3] *= 2
    expected = factor.clone()
    expected[3] *= 2
    torch.testing.assert_close(Calibration.from_pivots(names, doubled, "shrunk").factor, expected)


def test_shrunk_tails_stay_their_own_where_the_refits_show_they_differ():
    """Four parameters with Gaussian pivots and four with Cauchy ones (95% quantile over
    median 2.9 against 19), 2 × 2000 refits: the tails differ by far more than their noise,
    so the shrunk factors are the own ones within 3% (measured 1.3%)."""
    names = [f"p{i}" for i in range(8)]
    torch.manual_seed(1)
    gaussian = torch.randn(2, 2000, 4, dtype=torch.float64)
    cauchy = torch.distributions.Cauchy(0.0, 1.0).sample((2, 2000, 4)).double()
    pivots = torch.cat([gaussian, cauchy], -1)
    own = Calibration.from_pivots(names, pivots, "own").factor
    torch.testing.assert_close(
        Calibration.from_pivots(names, pivots, "shrunk").factor, own, rtol=0.03, atol=0
    )


def test_a_factor_on_few_refits_says_how_many_datasets_would_pin_it(space2d):
    # the refits a factor rests on are counted per parameter (those with an interval); below
    # MIN_REFITS the table says so and how many datasets would reach it
    names = space2d.free_names
    pivots = torch.ones(2, 10, len(names), dtype=torch.float64)
    pivots[1, :4, 0] = torch.nan  # four refits without an interval for the first parameter
    pivots[..., 1] = torch.nan  # none for the second: more refits would not give it a factor
    entry = Calibration.from_pivots(names, pivots, "shrunk").to_dict()
    assert list(entry["refits"].values()) == [16, 0] + [20] * (len(names) - 2)
    caution = (
        f"rests on 16 refit(s) only; about {MIN_REFITS} pin a 95% quantile, and with fewer "
        f"than {FEWEST_REFITS} a parameter gets none: calibrate=5)"
    )
    assert format_factors(entry).endswith(caution)
    # 16 refits are too few for any factor, none are too few for more datasets to mend
    assert f"{names[0]} none, {names[1]} none, {names[2]} 0.51" in format_factors(entry)
    pivots[1, :4, 0] = 1.0
    caution = f"rests on 20 refit(s) only; about {MIN_REFITS} pin a 95% quantile: calibrate=4)"
    assert format_factors(Calibration.from_pivots(names, pivots, "shrunk").to_dict()).endswith(
        caution
    )
    enough = Calibration.from_pivots(names, torch.ones(1, MIN_REFITS, len(names))).to_dict()
    assert "refits" not in format_factors(enough)


@pytest.mark.parametrize("factor", [0.5, 1.0, 2.5])
def test_calibrated_intervals_cover_where_the_pivot_is_within_factor_times_z95(
    space2d, wald, factor
):
    result, truth = wald
    free = space2d.free_mask
    k = len(space2d.free_names)
    calibration = Calibration(space2d.free_names, torch.full((k,), factor), torch.zeros(1, 1, k))
    calibrated = calibration.apply(space2d, result)
    iv = calibrated.intervals
    covered = (iv.low <= truth) & (truth <= iv.high)
    pivot = interval_pivots(space2d, truth, result)
    assert torch.equal(covered[:, free], pivot.abs() <= factor * Z95 * (1 + 1e-9))
    # scaled about θ̂ in the fit's coordinates; the standard deviations scale alike
    torch.testing.assert_close(interval_pivots(space2d, truth, calibrated), pivot / factor)
    torch.testing.assert_close(iv.std, result.intervals.std * factor)
    torch.testing.assert_close(iv.covariance, result.intervals.covariance * factor**2)
    assert (iv.low <= calibrated.theta_hat).all() and (calibrated.theta_hat <= iv.high).all()
    if factor == 1.0:
        torch.testing.assert_close(iv.low, result.intervals.low)
        torch.testing.assert_close(iv.high, result.intervals.high)


@pytest.mark.parametrize("factor", [1.0, 1.7])
def test_an_interval_end_on_the_bound_of_theta_stays_there_as_it_widens(space2d, factor):
    """Profile intervals end exactly on θ's bound where the likelihood never falls far enough
    (a truth there is covered); widening keeps such ends (the round trip through the clamped
    unconstrained coordinates moved them inside by ~1e-8 of the range, uncovering it)."""
    theta_hat = space2d.default(torch.float64).repeat(2, 1)
    k = len(space2d.free_names)
    result = _result(space2d, theta_hat, torch.eye(k, dtype=torch.float64).repeat(2, 1, 1))
    free = space2d.free_mask
    low, high = (b(torch.float64).expand(2, -1) for b in (space2d.low, space2d.high))
    ends = dataclasses.replace(
        result.intervals,
        low=torch.where(free, low, result.intervals.low),
        high=torch.where(free, high, result.intervals.high),
    )
    result = dataclasses.replace(result, intervals=ends)
    calibration = Calibration(space2d.free_names, torch.full((k,), factor), torch.zeros(1, 1, k))
    calibrated = calibration.apply(space2d, result)
    assert torch.equal(calibrated.intervals.low, ends.low)
    assert torch.equal(calibrated.intervals.high, ends.high)


def test_calibration_keeps_fixed_parameters_and_intervals_over_the_whole_range(space2d):
    space = space2d.fix(g_v=1.0)
    theta_hat = space.default(torch.float64).repeat(2, 1)
    hessian = torch.eye(len(space.free_names), dtype=torch.float64).repeat(2, 1, 1) * 1e4
    hessian[1, 0, 0] = 0.0  # no curvature: agent 1's first free parameter has no interval
    result = _result(space, theta_hat, hessian)
    k = len(space.free_names)
    calibrated = Calibration(space.free_names, torch.full((k,), 0.5), torch.zeros(1, 1, k)).apply(
        space, result
    )
    fixed = space.index("g_v")
    assert (calibrated.intervals.low[:, fixed] == 1.0).all()
    assert (calibrated.intervals.high[:, fixed] == 1.0).all()
    first = space.index(space.free_names[0])
    assert calibrated.intervals.std[1, first].isinf()
    assert calibrated.intervals.low[1, first] == result.intervals.low[1, first]
    assert calibrated.intervals.high[1, first] == result.intervals.high[1, first]
    assert not calibrated.intervals.identified[1, first]
    zero = Calibration(space.free_names, torch.zeros(k), torch.zeros(1, 1, k)).apply(space, result)
    assert zero.intervals.std[1, first].isinf() and not zero.intervals.std.isnan().any()
    # an infinite factor (no refit had an interval) leaves no interval for that parameter
    factor = torch.ones(k)
    factor[1] = torch.inf
    void = Calibration(space.free_names, factor, torch.zeros(1, 1, k)).apply(space, result)
    second = space.index(space.free_names[1])
    assert void.intervals.std[:, second].isinf().all()
    assert (void.intervals.low[:, second] == space[space.free_names[1]].low).all()
    assert (void.intervals.high[:, second] == space[space.free_names[1]].high).all()
    assert not void.intervals.identified[:, second].any()
    assert void.intervals.covariance[:, 1, :].isinf().all()
    assert void.intervals.covariance[:, :, 1].isinf().all()
    assert void.intervals.covariance[0, 2, 2].isfinite()
    torch.testing.assert_close(void.intervals.low[0, first], result.intervals.low[0, first])
    with pytest.raises(ValueError, match="space: expected the free parameters"):
        Calibration(space2d.free_names, torch.ones(k + 1), torch.zeros(1, 1, k + 1)).apply(
            space, result
        )


def test_calibrating_honest_intervals_leaves_them_nearly_as_they_are(firefly1d_model, trained_q):
    """On the 1D task the likelihood is exact and the Wald intervals honest, so the factors
    come out near 1. 12 agents from the prior (seed 0), 100 trials each (seed 1), calibrated on
    3 datasets each (36 pivots per parameter), each fitted from the best of 16 screened draws.
    Tolerance: factors in [0.7, 1.5] (measured 1.35 for g_a and 1.03 for log σ₀; 1.01 and 0.76
    with the quantile the Weibull rank replaced; from the best two of the draws, the same to
    0.003); intervals narrowed 3-fold beforehand come out with
    factors exactly 3 times as large (the pivots scale with the half-widths)."""
    model, space = firefly1d_model, firefly1d_model.theta_space
    policy = boltzmann_policy(model, trained_q, TEMPERATURE)

    def fit(theta: torch.Tensor, seed: int) -> FitResult:
        trials = simulate_agents(model, policy, theta, 100, task_theta=space.default(), seed=seed)
        loss = InverseRationalLoss(
            model, BoltzmannActionModel(trained_q, TEMPERATURE), n_agents=theta.shape[0]
        )
        return fit_theta(loss, trials, n_starts=1, n_screen=16, seed=0)

    theta_true = space.sample((12,), generator=torch.Generator().manual_seed(0))
    result = fit(theta_true, 1)
    k = len(space.free_names)
    narrowing = Calibration(space.free_names, torch.full((k,), 1 / 3), torch.zeros(1, 1, k))

    def refit(i: int) -> dict[str, FitResult]:
        honest = fit(result.theta_hat.float(), 100 + i)
        return {"honest": honest, "narrow": narrowing.apply(space, honest)}

    calibrations = calibrate_intervals(space, result.theta_hat.float(), refit, 3)
    factor = calibrations["honest"].factor
    assert ((factor > 0.7) & (factor < 1.5)).all(), factor
    torch.testing.assert_close(calibrations["narrow"].factor, 3 * factor)
    with pytest.raises(ValueError, match="n_datasets: expected an integer ≥ 1"):
        calibrate_intervals(space, result.theta_hat.float(), refit, 0)


def test_motor_noise_may_differ_per_agent_and_action_dimension():
    # each agent acts with its own noise: the residual about the actor's output, where that
    # lies 3 sd or more inside the bounds (clipping cannot truncate it), has that sd (within
    # 10%; 470-1540 actions each, measured within 0.5%)
    actor, model, _ = load_ensemble_policy("firefly2d")
    theta = model.theta_space.sample((2,), generator=torch.Generator().manual_seed(0))
    std = torch.tensor([[[0.05, 0.2]], [[0.15, 0.1]]])
    trials = simulate_agents(model, motor_noise_policy(actor, model.action_spec, std), theta, 100)
    steps = torch.arange(trials.shape[-1]).view(1, 1, -1, 1).expand(*trials.shape, 1)
    features = model.belief_features(
        trials["belief", "mean"], trials["belief", "cov"], trials["target"], steps, trials["theta"]
    )
    with torch.no_grad():
        output = FeaturePolicy(actor)(features)
    residual = trials["action"] - output
    inside = (output.abs() < 1 - 3 * std.unsqueeze(1)) & trials["mask"].unsqueeze(-1)
    for agent in range(2):
        for dim in range(2):
            r = residual[agent][..., dim][inside[agent][..., dim]]
            assert r.std().item() == pytest.approx(std[agent, 0, dim].item(), rel=0.1)
    with pytest.raises(ValueError, match="motor_noise: expected positive"):
        motor_noise_policy(actor, model.action_spec, torch.tensor([0.1, 0.0]))


def test_agents_simulated_at_fits_lapse_at_each_ones_fitted_rate():
    """Calibration's simulated agents act with each fit's own motor noise and lapse rate: with
    rates fitted at 0.3 and at the floor (0.0012) and a motor noise of 0.005, the fraction of
    actions 0.05 or more from the actor's output (a lapse; the noise stays within 10 sd) is
    about 0.3 × P(the lapse's draw lands that far), and nearly 0 (measured 0.268 of 1714
    action dimensions, lapses ending trials early, and 0.0011 of 4600)."""
    actor, model, _ = load_ensemble_policy("firefly2d")
    space = model.theta_space
    action_model = censored_action_model(actor, model, lapse=0.01, fit_lapse=True)
    theta_hat = space.sample((2,), generator=torch.Generator().manual_seed(0)).double()
    logit = torch.tensor([[math.log(0.3 / 0.2)], [-6.0]], dtype=torch.float64)
    nuisance = torch.cat([torch.full((2, 2), math.log(0.005), dtype=torch.float64), logit], -1)
    result = dataclasses.replace(
        _result(space, theta_hat, torch.eye(len(space.free_names)).expand(2, -1, -1).double()),
        nuisance=nuisance,
    )
    world = space.default().expand(2, -1)
    trials = simulate_at_fits(model, actor, action_model, result, world, 100, seed=0)
    steps = torch.arange(trials.shape[-1]).view(1, 1, -1, 1).expand(*trials.shape, 1)
    features = model.belief_features(
        trials["belief", "mean"], trials["belief", "cov"], trials["target"], steps, trials["theta"]
    )
    with torch.no_grad():
        output = FeaturePolicy(actor)(features)
    far = (trials["action"] - output).abs() >= 0.05
    recorded = trials["mask"].unsqueeze(-1).expand_as(far)
    fraction = [far[i][recorded[i]].double().mean().item() for i in range(2)]
    # a lapse's draw (uniform over [-2, 2], clipped) lands within 0.05 of the output with
    # probability 0.1/4 inside the bounds, more where the output sits on a bound
    assert 0.3 * 0.8 < fraction[0] < 0.3 * (1 - 0.1 / 4) + 0.03
    assert fraction[1] < 0.01
    # each acts at its own θ̂ in its own world, sensing as noisily as its θ̂ says
    assert torch.equal(trials["theta"][:, 0, 0], theta_hat.float())
    sensed = sensed_world(model, world, theta_hat.float())
    assert torch.equal(trials["task_theta"][:, 0, 0], sensed)
    assert not torch.equal(sensed, world)


def test_recovery_reports_intervals_calibrated_on_simulated_refits():
    """``calibrate=1`` on a tiny run (2 agents × 11 trials, map, 4 iterations): each
    parameter's calibrated coverage is what its pivot and factor say, and every calibrated
    interval holds θ̂ inside θ's bounds. Two refits are too few for a 95% quantile (19 are
    the fewest), so no factor is known (null) and the intervals span θ's range: nothing
    vouches for them."""
    config = Recovery2DConfig(
        n_prior_agents=2, n_mistaken_agents=0, n_trials=11, methods="map", calibrate=1,
        fit=FitConfig(n_screen=2, n_starts=1, max_iter=4, curvature="bfgs",
                      covariance="sandwich"),
    )  # fmt: skip
    trials, summary, fits = recover_firefly2d(config)
    space = Firefly2DModel().theta_space
    calibrated = summary["methods"]["map"]["calibrated"]
    assert calibrated["n_datasets"] == 1 and list(calibrated["factor"]) == space.free_names
    assert calibrated["tail"] == config.calibration_tail == "own"
    # no refit with an interval: no factor (null in the JSON), the intervals the whole range
    factor = torch.tensor(
        [torch.inf if c is None else c for c in calibrated["factor"].values()], dtype=torch.float64
    )
    assert factor.isinf().all()
    truth = trials["theta"][:, 0, 0].double()
    pivot = interval_pivots(space, truth, fits["map"])
    for j, name in enumerate(space.free_names):
        inside = (pivot[:, j].abs() <= factor[j] * Z95 * (1 + 1e-9)) | pivot[:, j].isnan()
        expected = inside.double().mean().item()
        assert calibrated["parameters"][name]["coverage"] == pytest.approx(expected)
        hats = fits["map"].theta_hat[:, space.index(name)]
        for agent, hat in zip(calibrated["agents"], hats, strict=True):
            low, high = agent["ci_low"][name], agent["ci_high"][name]
            assert space[name].low <= low <= hat.item() <= high <= space[name].high
            assert high - low == pytest.approx(space[name].high - space[name].low)
    assert summary["timings"]["calibrate_s"] > 0


def test_a_recovery_calibrates_each_method_on_refits_simulated_at_the_last_methods_fits(
    monkeypatch,
):
    """Map then marginal, calibrate=10 (20 refits: a factor needs 19), every fit replaced by
    θ̂ drawn from the prior (a draw of its own per fit, Wald sd 0.5 in the fit's
    coordinates): the datasets are simulated at the
    marginal's θ̂, each agent in its recorded world, each dataset by a seed of its own; each
    marginal fit starts from map's θ̂ of the same data; each method's recovered beliefs are
    those under its own θ̂, and its calibrated intervals and coverage its own fit's widened
    by the factors of its own refits."""
    space = Firefly2DModel().theta_space
    k = len(space.free_names)
    fits, simulated = [], []

    def fit(loss, held, **kwargs):
        n = held.shape[0]
        g = torch.Generator().manual_seed(len(fits))
        theta = space.sample((n,), generator=g, dtype=torch.float64)
        result = dataclasses.replace(
            _result(space, theta, 4 * torch.eye(k, dtype=torch.float64).expand(n, k, k)),
            nuisance=torch.full((n, 2), math.log(0.1), dtype=torch.float64),
            information=torch.eye(k + 2, dtype=torch.float64).expand(n, k + 2, k + 2),
        )
        fits.append((loss.method, kwargs["starts"], result))
        return result

    def simulate(model, actor, action_model, result, world, n_trials, seed, senses):
        assert senses == config.senses
        simulated.append((result.theta_hat, world, n_trials, seed))
        return simulate_at_fits(model, actor, action_model, result, world, n_trials, seed, senses)

    monkeypatch.setattr(recover2d, "fit_theta", fit)
    monkeypatch.setattr(recover2d, "simulate_at_fits", simulate)
    monkeypatch.setattr(recover2d, "_truth_check", lambda *args: {})
    config = Recovery2DConfig(
        n_prior_agents=1, n_mistaken_agents=1, n_trials=3, calibrate=10,
        fit=FitConfig(covariance="hessian"),
    )  # fmt: skip
    trials, summary, results = recover_firefly2d(config)
    assert [method for method, _, _ in fits] == ["map", "marginal"] * 11  # the data, 10 refits
    for (_, _, by_map), (_, starts, _) in zip(fits[::2], fits[1::2], strict=True):
        assert torch.equal(starts, by_map.theta_hat)
    marginal = results["marginal"]
    assert marginal is fits[1][2]
    world = trials["task_theta"][:, 0, 0]
    truth = trials["theta"][:, 0, 0]
    # the mistaken agent's: the default but for its senses, its own
    assert torch.equal(world[1], sensed_world(Firefly2DModel(), space.default(), truth[1]))
    for theta, at, n_trials, _ in simulated:
        assert torch.equal(theta, marginal.theta_hat) and torch.equal(at, world)
        assert n_trials == 3
    seeds = [seed for *_, seed in simulated]
    assert seeds == [derived_seed(config.seed, CALIBRATION, i) for i in range(10)]
    assert len(set(seeds)) == 10
    actor, model, _ = load_ensemble_policy("firefly2d")
    action_model = recover2d._recovery_action_model(config, actor, model)
    for i, method in enumerate(("map", "marginal")):
        loss = InverseRationalLoss(model, action_model, n_agents=2, method=method)
        result, held = results[method], trials.select(*TRIAL_KEYS)
        with torch.no_grad():
            beliefs = loss.recovered_beliefs(result.theta_hat, result.nuisance, held)
        assert torch.equal(trials[method, "belief", "mean"], beliefs["belief", "mean"])
        refits = [result for _, _, result in fits[2 + i :: 2]]
        pivots = [interval_pivots(space, marginal.theta_hat.float(), r) for r in refits]
        expected = Calibration.from_pivots(space.free_names, torch.stack(pivots))
        assert expected.factor.isfinite().all()  # 20 refits: every interval scaled
        calibrated = expected.apply(space, results[method])
        entry = summary["methods"][method]["calibrated"]
        assert entry["factor"] == pytest.approx(expected.to_dict()["factor"])
        assert entry["agents"] == agent_intervals(calibrated)
        scores = score_recovery(space, truth, calibrated)["parameters"]
        assert entry["parameters"] == scores


def test_neighbouring_seeds_derive_streams_that_share_no_seed():
    """Recovery draws 0-9 with calibrate=80: no calibration dataset of one draw is simulated
    with a seed another draw's streams use (``seed + 1000 + i`` gave draw 4's dataset i + 1
    draw 5's dataset i), every derived seed is one torch takes, and a seed derives the same
    seeds on every machine."""
    streams = {
        draw: [derived_seed(draw, CALIBRATION, i) for i in range(80)]
        + [derived_seed(draw, s) for s in (SIMULATION, STARTS)]
        for draw in range(10)
    }
    every = [seed for seeds in streams.values() for seed in seeds]
    assert len(set(every)) == len(every) == 820
    assert all(0 <= seed < 2**63 for seed in every)
    torch.Generator().manual_seed(max(every))
    # pinned: a change of the construction would change every draw's data
    assert derived_seed(0, 1) == 1445747666553143162
    assert derived_seed(4, CALIBRATION, 0) == 4283610659707493945


class _Seen(Exception):
    """Raised by a stand-in once it has seen the seed it was given: the run need go no further."""


def test_every_command_draws_its_noise_from_streams_derived_from_its_seed(
    monkeypatch, tmp_path, firefly1d_model, trained_q
):
    """``irc simulate``, the 1D recovery and ``predicted_widths`` took ``seed + 1`` (and the
    1D fit's starts ``seed + 2``, the widths' Fisher draws the seed of θ* itself): the seed
    that draws the next run's θ*. Each stream is now derived from the run's seed, as the 2D
    recovery's are."""
    seen = []

    def stand_in(*args, seed, **kwargs):
        seen.append(seed)
        raise _Seen

    def simulate(*args, seed, **kwargs):
        seen.append(seed)
        return simulate_agents(*args, seed=seed, **kwargs)

    monkeypatch.setattr("irc_torchrl.algorithms.recordings.simulate_agents", stand_in)
    config = SimulateConfig(n_agents=1, n_trials=1)
    with pytest.raises(_Seen):
        simulate_recordings(config, tmp_path, seed=4, progress=False)
    monkeypatch.setattr("irc_torchrl.algorithms.recovery.simulate_agents", simulate)
    monkeypatch.setattr("irc_torchrl.algorithms.recovery.fit_theta", stand_in)
    agents = AgentsConfig(n_agents=1, n_trials=1)
    with pytest.raises(_Seen):
        recover_agents(firefly1d_model, trained_q, agents, FitConfig(), seed=4)
    monkeypatch.setattr(recover2d, "expected_intervals", stand_in)
    actor, model, _ = load_ensemble_policy("firefly2d")
    with pytest.raises(_Seen):
        predicted_widths(model, actor, n_trials=(1,), n_agents=1, seed=4)
    assert seen == [derived_seed(4, stream) for stream in (SIMULATION, SIMULATION, STARTS)] + [
        derived_seed(4, INFORMATION)
    ]
    assert not set(seen) & {4, 5, 6}


def test_a_fit_result_prints_one_line_per_agent(space2d):
    """The dataclass's repr printed every tensor in full (27,190 characters for 40 agents):
    one header line, then each agent's θ̂ with its interval, the unconverged marked."""
    theta_hat = space2d.default(torch.float64).expand(2, -1).clone()
    result = _result(
        space2d, theta_hat, 100 * torch.eye(len(space2d.free_names)).expand(2, -1, -1).double()
    )
    result.converged[1] = False
    lines = repr(result).splitlines()
    assert lines[0] == "FitResult(2 agents, 1 iterations, 1 converged)"
    assert lines[1].startswith("  agent 0: g_v=1.2 [1.1") and "(not converged)" not in lines[1]
    assert lines[2].endswith(" (not converged)") and len(lines) == 3


def test_the_particle_check_scores_the_truth_at_the_agents_own_motor_noise(monkeypatch):
    """Like the truth check, the particle check's second point is the agents' own (θ*, ν*):
    at θ̂'s nuisance ν̂ (here 0.3, the agents' 0.1) a fitted motor noise would be compared
    with the truth's, and (θ̂, ν̂) with (θ*, ν̂)."""
    space = Firefly2DModel().theta_space
    k = len(space.free_names)
    eye, checked = torch.eye(k, dtype=torch.float64), {}

    def fit(loss, held, **kwargs):
        n = held.shape[0]
        return dataclasses.replace(
            _result(space, space.default().double().expand(n, -1), 4 * eye.expand(n, k, k)),
            nuisance=torch.full((n, 2), math.log(0.3), dtype=torch.float64),
        )

    def check(loss, held, theta, nuisance, n_particles, seed):
        checked[len(checked)] = (theta, nuisance, seed)
        zeros = torch.zeros(held.shape[0])
        keys = ("particle_log_likelihood", "approximation_gap", "min_effective_particles")
        return dict.fromkeys(keys, zeros)

    monkeypatch.setattr(recover2d, "fit_theta", fit)
    monkeypatch.setattr(recover2d, "particle_check", check)
    monkeypatch.setattr(recover2d, "_truth_check", lambda *args: {})
    config = Recovery2DConfig(
        n_prior_agents=2, n_mistaken_agents=0, n_trials=2, methods="marginal", particles=8,
        motor_noise=0.1, calibrate=0, fit=FitConfig(covariance="hessian"),
    )  # fmt: skip
    trials, _, results = recover_firefly2d(config)
    (at_hat, hat_noise, seed), (at_true, true_noise, same_seed) = checked.values()
    assert torch.equal(at_hat, results["marginal"].theta_hat)
    assert torch.equal(hat_noise, results["marginal"].nuisance)
    assert torch.equal(at_true, trials["theta"][:, 0, 0])
    assert torch.allclose(true_noise.exp(), torch.tensor(0.1, dtype=true_noise.dtype))
    assert seed == same_seed == derived_seed(config.seed, PARTICLES)
