"""ThetaSpace: coordinates, prior, free/fixed parameters, spec, validation, serialisation."""

from __future__ import annotations

import json
import math
import pickle

import numpy as np
import pytest
import torch

from irc_torchrl.envs.firefly1d import firefly1d_theta_space
from irc_torchrl.theta import Parameter, ThetaSpace


def make_space() -> ThetaSpace:
    return ThetaSpace(
        [
            Parameter("gain", 0.5, 1.5, 1.0, "m/step"),
            Parameter("log_noise", -3.0, 0.0, -1.0),
            Parameter("radius", 0.5, 2.0, 1.0),
        ],
        fixed={"radius": 1.25},
    )


def interior(space: ThetaSpace, n: int, dtype: torch.dtype, seed: int = 0) -> torch.Tensor:
    """Points strictly inside every parameter's range (fixed ones included)."""
    g = torch.Generator().manual_seed(seed)
    u = 0.02 + 0.96 * torch.rand(n, space.dim, generator=g, dtype=dtype)
    return space.low(dtype) + u * (space.high(dtype) - space.low(dtype))


@pytest.mark.parametrize("dtype,tol", [(torch.float32, 1e-5), (torch.float64, 1e-12)])
def test_round_trips(dtype, tol):
    space = make_space()
    theta = interior(space, 200, dtype)
    u = space.to_unconstrained(theta)
    assert u.dtype == dtype and torch.isfinite(u).all()
    back = space.from_unconstrained(u)
    torch.testing.assert_close(back, theta, atol=tol * 10, rtol=tol)
    z = space.normalise(theta)
    assert (z > -1).all() and (z < 1).all()
    torch.testing.assert_close(space.denormalise(z), theta, atol=tol * 10, rtol=tol)
    # unconstrained -> natural -> unconstrained for moderate reals
    v = torch.linspace(-6, 6, 25, dtype=dtype).unsqueeze(-1).expand(-1, space.dim)
    torch.testing.assert_close(space.to_unconstrained(space.from_unconstrained(v)), v,
                               atol=1e-3 if dtype == torch.float32 else 1e-8, rtol=0)


def test_normalise_maps_bounds_to_box_edges():
    space = make_space()
    torch.testing.assert_close(space.normalise(space.low()), -torch.ones(3))
    torch.testing.assert_close(space.normalise(space.high()), torch.ones(3))
    mid = (space.low() + space.high()) / 2
    torch.testing.assert_close(space.normalise(mid), torch.zeros(3), atol=1e-6, rtol=0)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_from_unconstrained_respects_bounds_for_extreme_inputs(dtype):
    space = make_space()
    u = torch.tensor([[-1e30] * 3, [1e30] * 3, [-800.0] * 3, [800.0] * 3, [0.0] * 3], dtype=dtype)
    theta = space.from_unconstrained(u)
    assert torch.isfinite(theta).all()
    assert (theta >= space.low(dtype)).all() and (theta <= space.high(dtype)).all()
    assert torch.equal(theta[0], space.low(dtype)) and torch.equal(theta[1], space.high(dtype))
    # the bounds themselves map to finite unconstrained values (clamped logit)
    edges = torch.stack([space.low(dtype), space.high(dtype)])
    assert torch.isfinite(space.to_unconstrained(edges)).all()


def test_sample_within_bounds_reproducible_and_fixed():
    space = make_space()
    a = space.sample((500,), generator=torch.Generator().manual_seed(3))
    b = space.sample((500,), generator=torch.Generator().manual_seed(3))
    c = space.sample((500,), generator=torch.Generator().manual_seed(4))
    assert a.shape == (500, 3) and a.dtype == torch.float32
    torch.testing.assert_close(a, b, rtol=0, atol=0)
    assert not torch.equal(a, c)
    assert (a >= space.low()).all() and (a <= space.high()).all()
    assert (a[:, 2] == 1.25).all()  # fixed
    # free parameters spread over their ranges (uniform prior: 500 draws cover > 90%)
    for i in (0, 1):
        span = (a[:, i].max() - a[:, i].min()) / (space.high()[i] - space.low()[i])
        assert span > 0.9
    d = space.sample((2, 7), dtype=torch.float64)
    assert d.shape == (2, 7, 3) and d.dtype == torch.float64


def test_fix_free_with_range():
    space = make_space()
    assert space.free_names == ["gain", "log_noise"]
    assert space.free_mask.tolist() == [True, True, False]
    fixed = space.fix(gain=0.7)
    assert fixed.free_names == ["log_noise"]
    assert fixed.default()[0].item() == pytest.approx(0.7)
    assert (fixed.sample((50,))[:, 0] == torch.tensor(0.7)).all()
    assert space.free_names == ["gain", "log_noise"]  # a copy, the original is unchanged
    assert set(fixed.free("gain").free_names) == {"gain", "log_noise"}
    assert fixed.free("gain").fixed == {"radius": 1.25}
    assert fixed.free().fixed == {}
    with pytest.raises(KeyError, match="nope"):
        space.fix(nope=1.0)
    with pytest.raises(ValueError, match="gain"):
        space.fix(gain=5.0)
    narrow = space.with_range("gain", 0.8, 0.9)
    assert narrow["gain"].low == 0.8 and narrow["gain"].high == 0.9
    assert narrow["gain"].default == pytest.approx(0.9)  # default clipped into the new range
    draws = narrow.sample((200,), generator=torch.Generator().manual_seed(0))
    assert (draws[:, 0] >= 0.8).all() and (draws[:, 0] <= 0.9).all()
    assert space["gain"].low == 0.5
    with pytest.raises(ValueError):
        space.with_range("gain", 2.0, 1.0)


def test_spec_shape_and_bounds():
    space = make_space()
    spec = space.spec((4, 2))
    assert spec.shape == (4, 2, 3)
    torch.testing.assert_close(spec.space.low, space.low().expand(4, 2, 3))
    torch.testing.assert_close(spec.space.high, space.high().expand(4, 2, 3))
    assert spec.is_in(space.sample((4, 2)))
    assert not spec.is_in(space.high().expand(4, 2, 3) + 1)
    assert space.spec().shape == (3,)


def test_validate_errors_name_the_parameter():
    space = make_space()
    good = space.default()
    assert space.validate(good) is good
    with pytest.raises(ValueError, match=r"\[\.\.\., 3\]"):
        space.validate(torch.zeros(2, 4))
    with pytest.raises(ValueError, match="theta"):
        space.validate(torch.tensor(1.0))
    bad = good.clone()
    bad[1] = float("nan")
    with pytest.raises(ValueError, match="log_noise"):
        space.validate(bad)
    bad = good.expand(5, 3).clone()
    bad[3, 0] = 1.7
    with pytest.raises(ValueError, match="gain=1.7"):
        space.validate(bad, field="my_field")
    with pytest.raises(ValueError, match="my_field"):
        space.validate(bad, field="my_field")
    with pytest.raises(TypeError):
        space.validate([1.0, -1.0, 1.0])
    # within the tolerance passes
    edge = space.high().clone()
    edge[0] += 0.5 * space.tolerance
    space.validate(edge)


def test_from_dict_and_to_dict():
    space = make_space()
    theta = space.from_dict({"gain": 0.6})
    torch.testing.assert_close(theta, torch.tensor([0.6, -1.0, 1.25]))
    assert space.to_dict(theta) == pytest.approx({"gain": 0.6, "log_noise": -1.0, "radius": 1.25})
    with pytest.raises(KeyError) as info:
        space.from_dict({"gian": 1.0})
    assert "gian" in str(info.value) and "gain, log_noise, radius" in str(info.value)
    with pytest.raises(ValueError, match="gain"):
        space.from_dict({"gain": 9.0})
    batch = space.to_dict(space.sample((4,)))
    assert set(batch) == {"gain", "log_noise", "radius"} and batch["gain"].shape == (4,)


def test_config_round_trip_and_equality():
    space = firefly1d_theta_space()
    config = json.loads(json.dumps(space.to_config()))
    again = ThetaSpace.from_config(config)
    assert again == space
    assert again.names == space.names and again.fixed == space.fixed
    torch.testing.assert_close(again.low(), space.low())
    assert again != space.fix(g_a=1.0)
    assert again != space.with_range("g_a", 0.6, 1.5)
    assert space["log_sigma0"].low == pytest.approx(math.log(0.05))


def test_construction_errors():
    with pytest.raises(ValueError, match="unique"):
        ThetaSpace([Parameter("a", 0, 1, 0.5), Parameter("a", 0, 1, 0.5)])
    with pytest.raises(ValueError, match="low < high"):
        Parameter("a", 1, 0, 0.5)
    with pytest.raises(ValueError, match="default"):
        Parameter("a", 0, 1, 2.0)
    with pytest.raises(ValueError, match="a=3"):
        ThetaSpace([Parameter("a", 0, 1, 0.5)], fixed={"a": 3})


@pytest.mark.parametrize(
    "name, low, high, message",
    [
        ("effort=cost", 0.0, 1.0, r"parameter name: expected a Python identifier .*'effort=cost'"),
        ("obs,sigma", 0.0, 1.0, r"got 'obs,sigma'"),
        ("obs sigma", 0.0, 1.0, r"got 'obs sigma'"),
        ("", 0.0, 1.0, r"got ''"),
        ("k", 300.0, 300.00001, r"'k': expected low < high in float32 \(θ's dtype\), got "
         r"\[300\.0, 300\.00001\], both 300\.0 in float32"),
        ("k", -1e39, 1e39, r"'k': expected a range float32 \(θ's dtype\) holds, within "
         r"±3\.4e38 and narrower than it, got \[-1e\+39, 1e\+39\]"),
        ("k", -3e38, 3e38, r"'k': expected a range float32"),
    ],
)  # fmt: skip
def test_parameter_refuses_a_name_settings_cannot_address_and_a_range_float32_cannot_hold(
    name, low, high, message
):
    """`theta.effort=cost=0.2` and `--free obs,sigma` could not name such parameters; a range
    of one float32 value made θ NaN when normalised."""
    with pytest.raises(ValueError, match=message):
        Parameter(name, low, high, low)
    assert Parameter("σ_v", 0.0, 1.0, 0.5).name == "σ_v"  # an identifier of any script


@pytest.mark.parametrize(
    "low, high, default, message",
    [
        (-math.inf, math.inf, 0.0, "'a': low must be a finite number"),
        (0.0, math.nan, 0.5, "'a': high must be a finite number"),
        ("0", 1.0, 0.5, "'a': low: expected a real number, got '0'"),
        (0.0, 1.0, None, "'a': default: expected a real number, got None"),
        (0.0, 1.0, True, "'a': default: expected a real number, got True"),
    ],
)
def test_parameter_refuses_bounds_that_are_not_finite_numbers(low, high, default, message):
    """An infinite range made sample() return NaN; a string bound failed on comparison."""
    with pytest.raises(ValueError, match=message):
        Parameter("a", low, high, default)


def test_parameter_stores_plain_floats():
    p = Parameter("a", np.float32(0.0), torch.tensor(2.0), 1)
    assert all(type(v) is float for v in (p.low, p.high, p.default))
    json.dumps(ThetaSpace([p]).to_config())
    with pytest.raises(ValueError, match="name"):
        Parameter(3, 0.0, 1.0, 0.5)


def test_theta_near_its_bound_survives_the_unconstrained_round_trip_in_float64():
    """The logit's clamp is float64's (√eps of the range): a θ 1e-6 of the range inside a bound
    (a start or an interval's end there) comes back where it was, not moved inwards."""
    space = ThetaSpace([Parameter("a", 2.0, 4.0, 3.0)])
    theta = torch.tensor([[2.0 + 2e-6], [4.0 - 2e-6]], dtype=torch.float64)
    back = space.from_unconstrained(space.to_unconstrained(theta))
    torch.testing.assert_close(back, theta, rtol=0, atol=1e-12)


def test_to_dict_refuses_a_last_dimension_other_than_dim():
    """Twelve entries for a 3-parameter space used to come back as the first three."""
    space = make_space()
    for theta in (torch.ones(12), torch.ones(4, 2), torch.tensor(1.0)):
        with pytest.raises(ValueError, match=r"to_dict: theta: expected shape \[\.\.\., 3\]"):
            space.to_dict(theta)


@pytest.mark.parametrize(
    "method, field",
    [
        ("normalise", "theta"),
        ("denormalise", r"theta \(normalised\)"),
        ("to_unconstrained", "theta"),
        ("from_unconstrained", r"theta \(unconstrained\)"),
    ],
)
def test_coordinate_maps_refuse_a_last_dimension_other_than_dim(method, field):
    """A [n, 2] θ of a 3-parameter space broadcast against the bounds (a torch size error) or,
    as [n, 1], came back as three made-up parameters."""
    space = make_space()
    for theta in (torch.zeros(4, 2), torch.zeros(4, 1), torch.tensor(0.5)):
        with pytest.raises(ValueError, match=rf"^{field}: expected shape \[\.\.\., 3\]"):
            getattr(space, method)(theta)
    assert getattr(space, method)(torch.zeros(4, 3)).shape == (4, 3)


@pytest.mark.parametrize("value", ["1.3", True, [1.3], None, torch.tensor([1.0, 1.2])])
def test_from_dict_refuses_values_that_are_not_real_numbers(value):
    with pytest.raises(ValueError, match="my_field: gain: expected a real number"):
        make_space().from_dict({"gain": value}, field="my_field")


def test_from_dict_accepts_numeric_scalars_and_refuses_a_malformed_base():
    space = make_space()
    for value in (1, np.float32(0.75), torch.tensor(0.75, dtype=torch.float64)):
        assert space.from_dict({"gain": value})[0].item() == pytest.approx(float(value))
    with pytest.raises(ValueError, match=r"theta: base: expected shape \[\.\.\., 3\]"):
        space.from_dict({"gain": 1.0}, base=torch.zeros(2))
    with pytest.raises(ValueError, match="mapping"):
        space.from_dict([("gain", 1.0)])


def test_fix_stores_plain_floats_and_refuses_non_numbers():
    """A tensor stored raw made json.dumps(to_config()) fail long after fix()."""
    space = make_space()
    for value in (torch.tensor(0.75), np.float32(0.75), np.float64(0.75), 1):
        fixed = space.fix(gain=value)
        assert type(fixed.fixed["gain"]) is float
        assert fixed.fixed["gain"] == pytest.approx(float(value))
        json.dumps(fixed.to_config())
    for value in ("0.75", True, torch.tensor([0.75, 0.8]), None):
        with pytest.raises(ValueError, match="fixed gain: expected a real number"):
            space.fix(gain=value)


def test_empty_space_is_refused_and_an_int_shape_is_one_dimensional():
    with pytest.raises(ValueError, match="at least one Parameter"):
        ThetaSpace([])
    with pytest.raises(ValueError, match="Parameter entries"):
        ThetaSpace([{"name": "a", "low": 0, "high": 1, "default": 0.5}])
    space = make_space()
    assert space.sample(5).shape == (5, 3)
    assert space.sample(torch.Size([2, 4])).shape == (2, 4, 3)
    assert space.spec(4).shape == (4, 3)
    for shape in ((-1,), (2.5,), "ab", True):
        with pytest.raises(ValueError, match="sample: shape"):
            space.sample(shape)


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda c: c.pop("parameters"), r"expected \{'parameters'"),
        (lambda c: c["parameters"][0].update(foo=1), "parameter entry 'gain': unknown key 'foo'"),
        (lambda c: c["parameters"][0].pop("high"), "parameter entry 'gain': missing key 'high'"),
        (lambda c: c["parameters"][0].update(low="a"), "'gain': low: expected a real"),
        (lambda c: c["parameters"].append("gain"), "parameter entry: expected a mapping"),
        (lambda c: c.update(fixed={"zz": 1.0}), "unknown θ parameter 'zz'"),
        (lambda c: c.update(fixed={"gain": "1"}), "fixed gain: expected a real number"),
        (lambda c: c.update(fixed=[1.0]), r"fixed: expected \{name: value\}"),
    ],
)
def test_from_config_refuses_a_malformed_description_naming_the_field(edit, message):
    config = make_space().to_config()
    edit(config)
    with pytest.raises(ValueError, match=f"^where: (parameter )?{message}"):
        ThetaSpace.from_config(config, field="where")


def test_fix_overrides_a_fixed_value_and_with_range_keeps_the_rest_of_the_space():
    """Re-fixing a fixed parameter takes the new value (the 1D task's goal radius, fixed at 1 by
    default); a new range keeps the other parameters fixed and clips the default only if it
    falls outside the range, to the nearer end."""
    space = make_space()
    refixed = space.fix(radius=1.5)
    assert refixed.fixed == {"radius": 1.5} and refixed.default()[2].item() == 1.5
    assert (refixed.sample((20,))[:, 2] == 1.5).all()
    assert firefly1d_theta_space().fix(goal_radius=1.5).fixed["goal_radius"] == 1.5
    wide = space.with_range("gain", 0.6, 1.4)
    assert wide.fixed == {"radius": 1.25} and wide.free_names == ["gain", "log_noise"]
    assert wide["gain"].default == 1.0  # inside the new range: kept
    assert space.with_range("gain", 1.2, 1.4)["gain"].default == 1.2  # below it: the low end
    assert space.with_range("gain", 0.6, 0.8)["gain"].default == 0.8  # above it: the high end


def test_validate_accepts_both_bounds_and_the_tolerance_beyond_each_but_no_more():
    """The prior's own bounds are valid θ on both sides; so is a slip within the tolerance
    (relative to the range); twice the tolerance beyond either bound is refused."""
    space = make_space()
    span = space.high() - space.low()
    for edge, sign in ((space.low(), -1), (space.high(), 1)):
        space.validate(edge.clone())
        space.validate(edge + sign * 0.5 * space.tolerance * span)
        with pytest.raises(ValueError, match="gain="):
            space.validate(edge + sign * 2 * space.tolerance * span * torch.tensor([1.0, 0, 0]))


def test_units_name_each_parameters_own_unit():
    space = ThetaSpace(
        [Parameter("gain", 0.5, 2.0, 1.0, "m/s"), Parameter("noise", 0.0, 1.0, 0.1)]
    )
    assert space.units == {"gain": "m/s", "noise": ""}


def test_coordinate_maps_keep_each_dtypes_bounds_and_callers_get_their_own_tensors():
    # the maps build their bounds once per dtype and device: float64 must not reuse the float32
    # bounds built first (0.1 and 0.7 are not float32 numbers), an edit of what `low()` returns
    # must not reach them, and a used space pickles as a fresh one (a worker builds its own)
    space = ThetaSpace([Parameter("a", 0.1, 0.7, 0.3), Parameter("b", -0.3, 0.9, 0.0)])
    fresh = pickle.dumps(space)
    space.normalise(space.low(torch.float32))
    edges = torch.stack([space.low(torch.float64), space.high(torch.float64)])
    assert space.normalise(edges).tolist() == [[-1.0, -1.0], [1.0, 1.0]]
    assert not space.outside(edges).any()
    space.low()[0] = 0.5
    assert space.normalise(space.low())[0] == -1 and not space.outside(space.low()).any()
    assert pickle.dumps(space) == fresh
