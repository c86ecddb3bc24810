"""The space of the agent's internal model parameters θ.

A :class:`ThetaSpace` names bounded parameters and moves θ between three coordinates:
natural units (what the task and the user read), unconstrained reals (what optimisers move)
and the normalised box [-1, 1] (what networks read). It draws θ from a uniform prior, gives
TorchRL's spec, and says which parameters are free and which are fixed.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import torch
from torchrl.data import Bounded

__all__ = ["Parameter", "ThetaSpace"]


@dataclass(frozen=True)
class Parameter:
    """One named parameter of θ with its prior range ``[low, high]`` in natural units."""

    name: str
    low: float
    high: float
    default: float
    unit: str = ""
    doc: str = ""

    def __post_init__(self) -> None:
        if not self.low < self.high:
            raise ValueError(
                f"parameter {self.name!r}: expected low < high, got [{self.low}, {self.high}]"
            )
        if not self.low <= self.default <= self.high:
            raise ValueError(
                f"parameter {self.name!r}: default {self.default} outside [{self.low}, {self.high}]"
            )


class ThetaSpace:
    """Named bounded parameters, some free (sampled and fitted) and some fixed.

    Args:
        parameters: the parameters, in the order of θ's last dimension.
        fixed: values of the parameters held fixed; the others are free.

    Examples:
        >>> space = ThetaSpace([Parameter("gain", 0.5, 1.5, 1.0)])
        >>> space.to_dict(space.sample((), generator=torch.Generator().manual_seed(0)))
        {'gain': 0.996...}
    """

    #: a θ component may sit this far (relative to the range) outside its bounds and still pass
    tolerance = 1e-5

    def __init__(
        self, parameters: Sequence[Parameter], fixed: Mapping[str, float] | None = None
    ) -> None:
        names = [p.name for p in parameters]
        if len(set(names)) != len(names):
            raise ValueError(f"ThetaSpace: parameter names must be unique, got {names}")
        self.parameters = tuple(parameters)
        self._index = {name: i for i, name in enumerate(names)}
        fixed = dict(fixed or {})
        for name, value in fixed.items():
            p = self[name]
            if not p.low <= value <= p.high:
                raise ValueError(f"fixed {name}={value} outside its range [{p.low}, {p.high}]")
        self.fixed = fixed

    # --- description -----------------------------------------------------------------------
    def __getitem__(self, name: str) -> Parameter:
        if name not in self._index:
            raise KeyError(f"unknown θ parameter {name!r}; valid names: {', '.join(self.names)}")
        return self.parameters[self._index[name]]

    def __len__(self) -> int:
        return len(self.parameters)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, ThetaSpace) and self.to_config() == other.to_config()

    def __repr__(self) -> str:
        parts = [
            f"{p.name}={self.fixed[p.name]}"
            if p.name in self.fixed
            else f"{p.name}∈[{p.low}, {p.high}]"
            for p in self.parameters
        ]
        return f"ThetaSpace({', '.join(parts)})"

    @property
    def names(self) -> list[str]:
        return [p.name for p in self.parameters]

    @property
    def dim(self) -> int:
        return len(self.parameters)

    @property
    def free_names(self) -> list[str]:
        return [n for n in self.names if n not in self.fixed]

    @property
    def free_mask(self) -> torch.Tensor:
        """Which parameters are free, ``[d]`` bool on the CPU (callers move it to their data)."""
        return torch.tensor([n not in self.fixed for n in self.names], device="cpu")

    def index(self, name: str) -> int:
        self[name]
        return self._index[name]

    # low, high, default and free_mask live on the CPU unless a device is given: a θ space
    # is a description, and its callers move them to their data
    def low(self, dtype: torch.dtype = torch.float32, device="cpu") -> torch.Tensor:
        return torch.tensor([p.low for p in self.parameters], dtype=dtype, device=device)

    def high(self, dtype: torch.dtype = torch.float32, device="cpu") -> torch.Tensor:
        return torch.tensor([p.high for p in self.parameters], dtype=dtype, device=device)

    def default(self, dtype: torch.dtype = torch.float32, device="cpu") -> torch.Tensor:
        """θ at every parameter's default, fixed parameters at their fixed values."""
        values = [self.fixed.get(p.name, p.default) for p in self.parameters]
        return torch.tensor(values, dtype=dtype, device=device)

    # --- free and fixed --------------------------------------------------------------------
    def fix(self, **values: float) -> ThetaSpace:
        """A copy with the named parameters held at the given values."""
        for name in values:
            self[name]
        return ThetaSpace(self.parameters, {**self.fixed, **values})

    def free(self, *names: str) -> ThetaSpace:
        """A copy with the named parameters free (all of them when no name is given)."""
        for name in names:
            self[name]
        keep = {} if not names else {k: v for k, v in self.fixed.items() if k not in names}
        return ThetaSpace(self.parameters, keep)

    def with_range(self, name: str, low: float, high: float) -> ThetaSpace:
        """A copy whose parameter ``name`` has the prior range ``[low, high]``."""
        p = self[name]
        new = replace(p, low=low, high=high, default=min(max(p.default, low), high))
        params = [new if q.name == name else q for q in self.parameters]
        return ThetaSpace(params, self.fixed)

    # --- validation ------------------------------------------------------------------------
    def validate(self, theta: torch.Tensor, field: str = "theta") -> torch.Tensor:
        """Return ``theta`` if it is a finite ``[..., dim]`` tensor within bounds, else raise."""
        if not isinstance(theta, torch.Tensor):
            raise TypeError(
                f"{field}: expected a tensor of shape [..., {self.dim}], got {type(theta).__name__}"
            )
        if theta.ndim == 0 or theta.shape[-1] != self.dim:
            raise ValueError(
                f"{field}: expected shape [..., {self.dim}] ({', '.join(self.names)}), "
                f"got {list(theta.shape)}"
            )
        if not theta.is_floating_point():
            raise TypeError(f"{field}: expected a floating-point tensor, got {theta.dtype}")
        bad = self.outside(theta)
        if bad.any():
            i = int(bad.reshape(-1, self.dim).any(0).nonzero()[0])
            p = self.parameters[i]
            value = theta.reshape(-1, self.dim)[bad.reshape(-1, self.dim)[:, i], i][0].item()
            raise ValueError(
                f"{field}: {p.name}={value:.6g} is outside its space [{p.low}, {p.high}]"
            )
        return theta

    def outside(self, theta: torch.Tensor) -> torch.Tensor:
        """Which components of ``theta [..., dim]`` are not finite or lie outside their bounds
        (beyond the tolerance), ``[..., dim]``."""
        low, high = self.low(theta.dtype, theta.device), self.high(theta.dtype, theta.device)
        slack = self.tolerance * (high - low)
        return ~torch.isfinite(theta) | (theta < low - slack) | (theta > high + slack)

    # --- coordinates -----------------------------------------------------------------------
    def to_unconstrained(self, theta: torch.Tensor) -> torch.Tensor:
        """Natural units to unconstrained reals (a scaled logit per parameter)."""
        low, high = self.low(theta.dtype, theta.device), self.high(theta.dtype, theta.device)
        eps = torch.finfo(theta.dtype).eps ** 0.5
        p = ((theta - low) / (high - low)).clamp(eps, 1 - eps)
        return torch.logit(p)

    def from_unconstrained(self, u: torch.Tensor) -> torch.Tensor:
        """Unconstrained reals to natural units."""
        low, high = self.low(u.dtype, u.device), self.high(u.dtype, u.device)
        return low + (high - low) * torch.sigmoid(u)

    def normalise(self, theta: torch.Tensor) -> torch.Tensor:
        """Natural units to the box [-1, 1], the form networks read."""
        low, high = self.low(theta.dtype, theta.device), self.high(theta.dtype, theta.device)
        return 2 * (theta - low) / (high - low) - 1

    def denormalise(self, z: torch.Tensor) -> torch.Tensor:
        """The box [-1, 1] to natural units."""
        low, high = self.low(z.dtype, z.device), self.high(z.dtype, z.device)
        return low + (z + 1) * (high - low) / 2

    # --- prior and spec --------------------------------------------------------------------
    def sample(
        self,
        shape: Sequence[int] | torch.Size = (),
        generator: torch.Generator | None = None,
        dtype: torch.dtype = torch.float32,
        device=None,
    ) -> torch.Tensor:
        """Draw θ from the uniform prior; fixed parameters take their fixed values (on
        ``device``, else the generator's, else the CPU)."""
        device = device if device is not None else (generator.device if generator else "cpu")
        u = torch.rand(*shape, self.dim, generator=generator, dtype=dtype, device=device)
        theta = self.low(dtype, device) + u * (self.high(dtype, device) - self.low(dtype, device))
        mask = self.free_mask.to(device)
        return torch.where(mask, theta, self.default(dtype, device))

    def spec(self, batch_shape: Sequence[int] | torch.Size = (), device=None) -> Bounded:
        """TorchRL's spec of θ with the given leading batch dimensions."""
        shape = torch.Size([*batch_shape, self.dim])
        return Bounded(
            low=self.low(device=device).expand(shape).clone(),
            high=self.high(device=device).expand(shape).clone(),
            shape=shape,
            dtype=torch.float32,
            device=device,
        )

    # --- dictionaries and serialisation ----------------------------------------------------
    def to_dict(self, theta: torch.Tensor) -> dict[str, float] | dict[str, torch.Tensor]:
        """``{name: value}``: floats for a single θ, tensors for a batch."""
        if theta.ndim == 1:
            return {n: float(theta[i]) for i, n in enumerate(self.names)}
        return {n: theta[..., i] for i, n in enumerate(self.names)}

    def from_dict(
        self, values: Mapping[str, float], base: torch.Tensor | None = None, field: str = "theta"
    ) -> torch.Tensor:
        """θ with the named values, the rest from ``base`` (default: the defaults); validated."""
        theta = (self.default(torch.float64) if base is None else base.to(torch.float64)).clone()
        for name, value in values.items():
            if name not in self._index:
                raise KeyError(
                    f"{field}: unknown θ parameter {name!r}; valid names: {', '.join(self.names)}"
                )
            theta[..., self._index[name]] = float(value)
        return self.validate(theta.float(), field)

    def to_config(self) -> dict:
        """A plain, JSON-able description (for checkpoints and summaries)."""
        return {
            "parameters": [
                {"name": p.name, "low": p.low, "high": p.high, "default": p.default, "unit": p.unit}
                for p in self.parameters
            ],
            "fixed": dict(sorted(self.fixed.items())),
        }

    @classmethod
    def from_config(cls, config: Mapping) -> ThetaSpace:
        params = [Parameter(**{k: v for k, v in p.items()}) for p in config["parameters"]]
        return cls(params, config.get("fixed", {}))
