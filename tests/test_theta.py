"""ThetaSpace: coordinates, prior, free/fixed parameters, spec, validation, serialisation."""

from __future__ import annotations

import json
import math

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
    torch.testing.assert_close(theta[0], space.low(dtype))
    torch.testing.assert_close(theta[1], space.high(dtype))
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
