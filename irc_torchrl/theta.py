"""The space of the agent's internal model parameters θ.

A :class:`ThetaSpace` names bounded parameters and moves θ between three coordinates:
natural units (what the task and the user read), unconstrained reals (what optimisers move)
and the normalised box [-1, 1] (what networks read). It draws θ from a uniform prior, gives
TorchRL's spec, and says which parameters are free and which are fixed.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, fields, replace
from numbers import Integral

import torch
from torchrl.data import Bounded

from irc_torchrl.checks import real, shown

__all__ = ["Parameter", "ThetaSpace"]

#: unconstrained coordinates from which θ is on its bound (an interval's end unbounded by the
#: data, clamped here to stay finite)
_ENDS = 40.0


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
        """Store the bounds and default as floats, refusing what would make θ NaN: a name
        that is not a string, a bound that is not a finite real number, an empty range."""
        if not isinstance(self.name, str) or not self.name.isidentifier():
            raise ValueError(
                "parameter name: expected a Python identifier (letters, digits, underscores: "
                f"the key of a theta.<name>= setting, an item of --free a,b), got {self.name!r}"
            )
        for key in ("unit", "doc"):
            if not isinstance(getattr(self, key), str):
                raise ValueError(
                    f"parameter {self.name!r}: {key} must be a string, got {getattr(self, key)!r}"
                )
        for key in ("low", "high", "default"):
            value = real(f"parameter {self.name!r}: {key}", getattr(self, key))
            if not math.isfinite(value):
                raise ValueError(
                    f"parameter {self.name!r}: {key} must be a finite number, got {value}"
                )
            object.__setattr__(self, key, value)  # frozen: set once, here
        if not self.low < self.high:
            raise ValueError(
                f"parameter {self.name!r}: expected low < high, got [{self.low}, {self.high}]"
            )
        low, high = torch.tensor([self.low, self.high], dtype=torch.float32, device="cpu")
        if not torch.isfinite(high - low):  # θ is float32: past its range θ is NaN normalised
            raise ValueError(
                f"parameter {self.name!r}: expected a range float32 (θ's dtype) holds, within "
                f"±3.4e38 and narrower than it, got [{self.low}, {self.high}]"
            )
        if not low < high:  # a range of one float32 value
            raise ValueError(
                f"parameter {self.name!r}: expected low < high in float32 (θ's dtype), got "
                f"[{self.low}, {self.high}], both {float(low)} in float32"
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
        parameters = tuple(parameters)
        if not parameters:
            raise ValueError("ThetaSpace: expected at least one Parameter, got none")
        for p in parameters:
            if not isinstance(p, Parameter):
                raise ValueError(f"ThetaSpace: expected Parameter entries, got {shown(p)}")
        names = [p.name for p in parameters]
        if len(set(names)) != len(names):
            raise ValueError(f"ThetaSpace: parameter names must be unique, got {names}")
        self.parameters = parameters
        self._index = {name: i for i, name in enumerate(names)}
        if not isinstance(fixed or {}, Mapping):
            raise ValueError(
                f"ThetaSpace: fixed must be a {{name: value}} mapping, got {shown(fixed)}"
            )
        self.fixed = {name: self._fixed_value(name, value) for name, value in (fixed or {}).items()}
        self._bounds_cache: dict[tuple[torch.dtype, torch.device], tuple[torch.Tensor, ...]] = {}

    def _fixed_value(self, name: str, value: object) -> float:
        """``value`` as a plain float within ``name``'s range (a tensor or numpy scalar would
        not survive ``json.dumps(to_config())``)."""
        p = self[name]
        value = real(f"fixed {name}", value)
        if not p.low <= value <= p.high:
            raise ValueError(f"fixed {name}={value} outside its range [{p.low}, {p.high}]")
        return value

    # --- description -----------------------------------------------------------------------
    def __getitem__(self, name: str) -> Parameter:
        if name not in self._index:
            raise KeyError(f"unknown θ parameter {name!r}; valid names: {', '.join(self.names)}")
        return self.parameters[self._index[name]]

    def __len__(self) -> int:
        return len(self.parameters)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, ThetaSpace) and self.to_config() == other.to_config()

    def format(self, theta: torch.Tensor) -> str:
        """One θ ``[d]`` as ``name=value`` pairs, 4 significant digits (for messages)."""
        return ", ".join(f"{name}={value:.4g}" for name, value in self.to_dict(theta).items())

    def difference(self, other: ThetaSpace) -> str:
        """The first way ``other`` differs from this space, in words (``""`` where equal)."""
        if self.names != other.names:
            return f"parameters {other.names} against {self.names}"
        pairs = zip(self.to_config()["parameters"], other.to_config()["parameters"], strict=True)
        for mine, theirs in pairs:
            for key, value in mine.items():
                if theirs[key] != value:
                    return f"{mine['name']}: {key} {theirs[key]!r} against {value!r}"
        if self.fixed != other.fixed:
            return f"fixed {other.to_config()['fixed']} against {self.to_config()['fixed']}"
        return ""

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
        """Every parameter's name, in θ's order."""
        return [p.name for p in self.parameters]

    @property
    def units(self) -> dict[str, str]:
        """Every parameter's unit by name, as figures and tables label them."""
        return {p.name: p.unit for p in self.parameters}

    @property
    def dim(self) -> int:
        """How many parameters θ holds, fixed ones included."""
        return len(self.parameters)

    @property
    def free_names(self) -> list[str]:
        """The names of the parameters not fixed, in θ's order."""
        return [n for n in self.names if n not in self.fixed]

    @property
    def free_mask(self) -> torch.Tensor:
        """Which parameters are free, ``[d]`` bool on the CPU (callers move it to their data)."""
        return torch.tensor([n not in self.fixed for n in self.names], device="cpu")

    def index(self, name: str) -> int:
        """Where ``name`` sits in θ (a KeyError listing the valid names otherwise)."""
        self[name]
        return self._index[name]

    # low, high, default and free_mask live on the CPU unless a device is given: a θ space
    # is a description, and its callers move them to their data
    def low(
        self, dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu"
    ) -> torch.Tensor:
        """The prior's lower bounds, ``[d]``."""
        return torch.tensor([p.low for p in self.parameters], dtype=dtype, device=device)

    def high(
        self, dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu"
    ) -> torch.Tensor:
        """The prior's upper bounds, ``[d]``."""
        return torch.tensor([p.high for p in self.parameters], dtype=dtype, device=device)

    def default(
        self, dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu"
    ) -> torch.Tensor:
        """θ at every parameter's default, fixed parameters at their fixed values."""
        values = [self.fixed.get(p.name, p.default) for p in self.parameters]
        return torch.tensor(values, dtype=dtype, device=device)

    def _bounds(self, like: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(low, high)`` in ``like``'s dtype and device, built once per pair: the env checks
        and normalises θ at every step, and a device's bounds would otherwise be copied there
        each time. Internal: callers of :meth:`low` and :meth:`high` get tensors of their own."""
        key = (like.dtype, like.device)
        if key not in self._bounds_cache:
            with torch.inference_mode(False):  # usable in autograd if first built in a rollout
                self._bounds_cache[key] = (self.low(*key), self.high(*key))
        return self._bounds_cache[key]

    def __getstate__(self) -> dict:
        # a worker process builds its own bounds (a pickled CUDA tensor would start CUDA there)
        return {**self.__dict__, "_bounds_cache": {}}

    # --- free and fixed --------------------------------------------------------------------
    def fix(self, **values: float) -> ThetaSpace:
        """A copy with the named parameters held at the given values (real numbers, stored as
        floats; a 0-d tensor or numpy scalar is converted)."""
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
        low, high = real(f"{name}: low", low), real(f"{name}: high", high)
        new = replace(p, low=low, high=high, default=min(max(p.default, low), high))
        params = [new if q.name == name else q for q in self.parameters]
        return ThetaSpace(params, self.fixed)

    # --- validation ------------------------------------------------------------------------
    def validate(self, theta: torch.Tensor, field: str = "theta") -> torch.Tensor:
        """Return ``theta`` if it is a finite ``[..., dim]`` tensor within bounds, else raise."""
        self._check_shape(theta, field)
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

    def _check_shape(self, theta: torch.Tensor, field: str) -> None:
        """Refuse anything but a tensor whose last dimension holds one entry per parameter."""
        if not isinstance(theta, torch.Tensor):
            raise TypeError(
                f"{field}: expected a tensor of shape [..., {self.dim}], got {type(theta).__name__}"
            )
        if theta.ndim == 0 or theta.shape[-1] != self.dim:
            raise ValueError(
                f"{field}: expected shape [..., {self.dim}] ({', '.join(self.names)}), "
                f"got {list(theta.shape)}"
            )

    def outside(self, theta: torch.Tensor) -> torch.Tensor:
        """Which components of ``theta [..., dim]`` are not finite or lie outside their bounds
        (beyond the tolerance), ``[..., dim]``."""
        low, high = self._bounds(theta)
        slack = self.tolerance * (high - low)
        return ~torch.isfinite(theta) | (theta < low - slack) | (theta > high + slack)

    # --- coordinates -----------------------------------------------------------------------
    def to_unconstrained(self, theta: torch.Tensor) -> torch.Tensor:
        """Natural units to unconstrained reals (a scaled logit per parameter)."""
        self._check_shape(theta, "theta")
        low, high = self._bounds(theta)
        eps = torch.finfo(theta.dtype).eps ** 0.5
        p = ((theta - low) / (high - low)).clamp(eps, 1 - eps)
        return torch.logit(p)

    def from_unconstrained(self, u: torch.Tensor) -> torch.Tensor:
        """Unconstrained reals to natural units; from ±40 on (an interval's end with no bound
        from the data) the bound itself, where the logistic is within 4e-18 of it."""
        self._check_shape(u, "theta (unconstrained)")
        low, high = self._bounds(u)
        natural = low + (high - low) * torch.sigmoid(u)
        return torch.where(u <= -_ENDS, low, torch.where(u >= _ENDS, high, natural))

    def normalise(self, theta: torch.Tensor) -> torch.Tensor:
        """Natural units to the box [-1, 1], the form networks read."""
        self._check_shape(theta, "theta")
        low, high = self._bounds(theta)
        return 2 * (theta - low) / (high - low) - 1

    def denormalise(self, z: torch.Tensor) -> torch.Tensor:
        """The box [-1, 1] to natural units."""
        self._check_shape(z, "theta (normalised)")
        low, high = self._bounds(z)
        return low + (z + 1) * (high - low) / 2

    # --- prior and spec --------------------------------------------------------------------
    def sample(
        self,
        shape: int | Sequence[int] | torch.Size = (),
        generator: torch.Generator | None = None,
        dtype: torch.dtype = torch.float32,
        device: torch.device | str | None = None,
    ) -> torch.Tensor:
        """Draw θ from the uniform prior; fixed parameters take their fixed values (on
        ``device``, else the generator's, else the CPU). An int ``shape`` is a 1-D shape."""
        shape = _shape("sample: shape", shape)
        device = device if device is not None else (generator.device if generator else "cpu")
        u = torch.rand(*shape, self.dim, generator=generator, dtype=dtype, device=device)
        theta = self.low(dtype, device) + u * (self.high(dtype, device) - self.low(dtype, device))
        mask = self.free_mask.to(device)
        return torch.where(mask, theta, self.default(dtype, device))

    def spec(
        self,
        batch_shape: int | Sequence[int] | torch.Size = (),
        device: torch.device | str | None = None,
    ) -> Bounded:
        """TorchRL's spec of θ with the given leading batch dimensions (an int is 1-D)."""
        shape = torch.Size([*_shape("spec: batch_shape", batch_shape), self.dim])
        return Bounded(
            low=self.low(device=device).expand(shape).clone(),
            high=self.high(device=device).expand(shape).clone(),
            shape=shape,
            dtype=torch.float32,
            device=device,
        )

    # --- dictionaries and serialisation ----------------------------------------------------
    def to_dict(self, theta: torch.Tensor) -> dict[str, float] | dict[str, torch.Tensor]:
        """``{name: value}``: floats for a single θ, tensors for a batch. A last dimension
        other than :attr:`dim` is refused, not truncated."""
        self._check_shape(theta, "to_dict: theta")
        if theta.ndim == 1:
            return {n: float(theta[i]) for i, n in enumerate(self.names)}
        return {n: theta[..., i] for i, n in enumerate(self.names)}

    def from_dict(
        self, values: Mapping[str, float], base: torch.Tensor | None = None, field: str = "theta"
    ) -> torch.Tensor:
        """θ with the named values, the rest from ``base`` (default: the defaults); validated.

        Each value must be a real number (a 0-d tensor or numpy scalar counts; a string or a
        bool does not): ``float("1.3")`` would hide a config typed as text.
        """
        if not isinstance(values, Mapping):
            raise ValueError(f"{field}: expected a {{name: number}} mapping, got {shown(values)}")
        if base is not None:
            self._check_shape(base, f"{field}: base")
        theta = (self.default(torch.float64) if base is None else base.to(torch.float64)).clone()
        for name, value in values.items():
            if name not in self._index:
                raise KeyError(
                    f"{field}: unknown θ parameter {name!r}; valid names: {', '.join(self.names)}"
                )
            theta[..., self._index[name]] = real(f"{field}: {name}", value)
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
    def from_config(cls, config: Mapping, field: str = "theta_space") -> ThetaSpace:
        """The θ space :meth:`to_config` described. A malformed description (a checkpoint's,
        say) is a one-line ValueError naming ``field``, not a KeyError or TypeError."""
        form = "{'parameters': [{name, low, high, default, ...}], 'fixed': {name: value}}"
        parameters = config.get("parameters") if isinstance(config, Mapping) else None
        if not isinstance(parameters, (list, tuple)):
            raise ValueError(f"{field}: expected {form}, got {shown(config)}")
        if not isinstance(config.get("fixed", {}), Mapping):
            raise ValueError(
                f"{field}: fixed: expected {{name: value}}, got {shown(config['fixed'])}"
            )
        try:
            params = [_parameter_from_config(p) for p in config["parameters"]]
            return cls(params, config.get("fixed", {}))
        except (KeyError, TypeError, ValueError) as error:
            message = str(error.args[0]) if error.args else type(error).__name__
            raise ValueError(f"{field}: {message}") from None


def _parameter_from_config(entry: object) -> Parameter:
    """One :class:`Parameter` from its :meth:`ThetaSpace.to_config` entry, refusing missing
    or unknown keys by name (``Parameter(**entry)`` would raise a bare TypeError)."""
    names = [f.name for f in fields(Parameter)]
    if not isinstance(entry, Mapping):
        raise ValueError(f"parameter entry: expected a mapping of {names}, got {shown(entry)}")
    problems = [f"unknown key {k!r}" for k in entry if k not in names]
    problems += [f"missing key {k!r}" for k in ("name", "low", "high", "default") if k not in entry]
    if problems:
        raise ValueError(
            f"parameter entry {entry.get('name')!r}: {', '.join(problems)}; expected the keys "
            f"{names[:4]}, optionally {names[4:]}"
        )
    return Parameter(**entry)


def _shape(field: str, shape: int | Iterable[int]) -> tuple[int, ...]:
    """``shape`` as a tuple of sizes ≥ 0; an int is a 1-D shape."""
    sizes = (shape,) if isinstance(shape, Integral) else shape
    if not isinstance(sizes, Iterable) or isinstance(sizes, (str, torch.Tensor)):
        raise ValueError(f"{field}: expected an int or a sequence of ints, got {shown(shape)}")
    sizes = tuple(sizes)
    if not all(isinstance(n, Integral) and not isinstance(n, bool) and n >= 0 for n in sizes):
        raise ValueError(f"{field}: expected sizes that are integers ≥ 0, got {shown(shape)}")
    return tuple(int(n) for n in sizes)
