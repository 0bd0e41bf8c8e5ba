"""The eight calibration parameters of the breakage model: one definition for every package.

The sweep, the dataset builder, the surrogate, the inverse calibration and the sensitivity
analysis all take their names, units, bounds and scaling from :data:`PAPER_SPACE` (the paper's
Table 2 ranges, Table 4 values as the reference point). Values are SI, except the two
percentages (A, R_t), which are percent as in the paper and in ``[breakage]`` configs.

    >>> from calendaring.data.params import PAPER_SPACE as space
    >>> u = space.to_unit(space.reference)        # physical -> [0, 1]^8
    >>> x = space.from_unit(u)                    # and back
    >>> space.check({"d0": 20e-6})                # ConfigError naming key, value and range

See also: :mod:`calendaring.data.design` (designs over this space),
:mod:`calendaring.data.dataset` (stores it as ``parameter_space``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from calendaring.core.errors import ConfigError

SCALES = ("linear", "log")


@dataclass(frozen=True, slots=True)
class Parameter:
    """One calibration parameter: its ``[breakage]`` config key, symbol, unit and bounds.

    ``scale = "log"`` maps ``[lower, upper]`` to ``[0, 1]`` through the logarithm (both bounds
    must then be positive); ``"linear"`` maps it affinely.
    """

    name: str  # key under [breakage]
    symbol: str  # the paper's symbol (plain text)
    unit: str  # SI unit of the value ("%" for the two percentages, "1" for pure numbers)
    lower: float
    upper: float
    reference: float  # the paper's Table 4 optimum
    description: str = ""
    scale: str = "linear"
    display_unit: str = ""  # unit for plots and printed tables ("um" for d0)
    display_factor: float = 1.0  # value x factor = value in display_unit

    def __post_init__(self) -> None:
        if self.scale not in SCALES:
            raise ConfigError(f"{self.name}.scale", self.scale, f"one of {SCALES}")
        if not (math.isfinite(self.lower) and math.isfinite(self.upper)
                and self.lower < self.upper):
            raise ConfigError(f"{self.name}.bounds", (self.lower, self.upper),
                              "finite lower < upper")
        if self.scale == "log" and self.lower <= 0:
            raise ConfigError(f"{self.name}.lower", self.lower, "> 0 with scale = log")


@dataclass(frozen=True)
class ParameterSpace:
    """An ordered set of :class:`Parameter`; arrays use this column order.

    Physical arrays have shape ``(..., n_params)`` in SI units (percent for A and R_t);
    unit arrays have the same shape with every value in ``[0, 1]``.
    """

    parameters: tuple[Parameter, ...]

    def __post_init__(self) -> None:
        names = [p.name for p in self.parameters]
        if len(set(names)) != len(names):
            raise ConfigError("parameters", names, "unique names")

    # ------------------------------------------------------------------ views
    def __len__(self) -> int:
        return len(self.parameters)

    def __iter__(self):
        return iter(self.parameters)

    def __getitem__(self, name: str) -> Parameter:
        for p in self.parameters:
            if p.name == name:
                return p
        raise ConfigError("parameter", name, f"one of {self.names}")

    @property
    def names(self) -> list[str]:
        return [p.name for p in self.parameters]

    @property
    def symbols(self) -> list[str]:
        return [p.symbol for p in self.parameters]

    @property
    def units(self) -> list[str]:
        return [p.unit for p in self.parameters]

    @property
    def lower(self) -> np.ndarray:
        return np.array([p.lower for p in self.parameters])

    @property
    def upper(self) -> np.ndarray:
        return np.array([p.upper for p in self.parameters])

    @property
    def scales(self) -> list[str]:
        return [p.scale for p in self.parameters]

    @property
    def reference(self) -> np.ndarray:
        """The paper's Table 4 optimum, physical units."""
        return np.array([p.reference for p in self.parameters])

    def index(self, name: str) -> int:
        return self.names.index(self[name].name)

    # ------------------------------------------------------------------ transforms
    def _log_mask(self) -> np.ndarray:
        return np.array([p.scale == "log" for p in self.parameters])

    def to_unit(self, x) -> np.ndarray:
        """Physical values ``(..., n)`` -> ``[0, 1]`` (not clipped; see :meth:`check`)."""
        x = np.asarray(x, dtype=float)
        self._check_shape(x)
        lo, hi, lg = self.lower, self.upper, self._log_mask()
        u = (x - lo) / (hi - lo)
        if lg.any():
            with np.errstate(divide="ignore", invalid="ignore"):
                u_log = np.log(x / lo) / np.log(hi / lo)
            u = np.where(lg, u_log, u)
        return u

    def from_unit(self, u) -> np.ndarray:
        """``[0, 1]`` values ``(..., n)`` -> physical values."""
        u = np.asarray(u, dtype=float)
        self._check_shape(u)
        lo, hi, lg = self.lower, self.upper, self._log_mask()
        x = lo + u * (hi - lo)
        if lg.any():
            x = np.where(lg, lo * (hi / lo) ** u, x)
        return x

    def _check_shape(self, a: np.ndarray) -> None:
        if a.ndim == 0 or a.shape[-1] != len(self):
            raise ConfigError("parameters", f"array of shape {a.shape}",
                              f"an array whose last axis has {len(self)} values in the order "
                              f"{self.names}")

    # ------------------------------------------------------------------ checks
    def check(self, values: Mapping[str, float], *, complete: bool = False,
              tol: float = 1e-12) -> dict[str, float]:
        """Validate a ``{name: physical value}`` mapping against names and bounds.

        Raises :class:`ConfigError` naming the key, the value and the allowed range. With
        ``complete``, every parameter must be present. Returns a plain float dict.
        """
        out = {}
        for key, v in values.items():
            p = self[key] if key in self.names else None
            if p is None:
                raise ConfigError("parameter", key, f"one of {self.names}")
            try:
                fv = float(v)
            except (TypeError, ValueError):
                raise ConfigError(key, v, "a number") from None
            span = tol * (p.upper - p.lower)
            if not (math.isfinite(fv) and p.lower - span <= fv <= p.upper + span):
                raise ConfigError(key, fv, f"[{p.lower:g}, {p.upper:g}] {p.unit}")
            out[key] = fv
        if complete:
            missing = [n for n in self.names if n not in out]
            if missing:
                raise ConfigError("parameters", sorted(values), f"all of {self.names} "
                                  f"(missing {missing})")
        return out

    def check_array(self, x, *, tol: float = 1e-12) -> np.ndarray:
        """Validate physical rows ``(..., n)``; raises on the first value out of bounds."""
        x = np.asarray(x, dtype=float)
        self._check_shape(x)
        flat = x.reshape(-1, len(self))
        span = tol * (self.upper - self.lower)
        bad = ~(np.isfinite(flat) & (flat >= self.lower - span) & (flat <= self.upper + span))
        if bad.any():
            row, col = np.argwhere(bad)[0]
            p = self.parameters[col]
            raise ConfigError(p.name, float(flat[row, col]),
                              f"[{p.lower:g}, {p.upper:g}] {p.unit} (row {row})")
        return x

    def as_dict(self, x: Sequence[float]) -> dict[str, float]:
        """One physical row -> ``{name: value}``."""
        x = np.asarray(x, dtype=float)
        self._check_shape(x)
        return {n: float(v) for n, v in zip(self.names, x, strict=True)}

    def from_dict(self, values: Mapping[str, float], default=None) -> np.ndarray:
        """``{name: value}`` -> one physical row, missing names from ``default`` (a row,
        e.g. :attr:`reference`); raises if a name is missing and there is no default."""
        checked = self.check(values, complete=default is None)
        row = np.array(default, dtype=float) if default is not None else np.zeros(len(self))
        for k, v in checked.items():
            row[self.names.index(k)] = v
        return row

    def to_json(self) -> list[dict]:
        """Serialisable description (stored in dataset files and model checkpoints)."""
        return [{"name": p.name, "symbol": p.symbol, "unit": p.unit, "lower": p.lower,
                 "upper": p.upper, "reference": p.reference, "scale": p.scale,
                 "description": p.description, "display_unit": p.display_unit,
                 "display_factor": p.display_factor} for p in self.parameters]

    @classmethod
    def from_json(cls, items: Sequence[Mapping]) -> ParameterSpace:
        return cls(tuple(Parameter(**dict(it)) for it in items))


PAPER_SPACE = ParameterSpace((
    Parameter("damage_constant", "gamma", "1", 1.0, 10.0, 5.549,
              "damage constant (damage law, Eq. 36)"),
    Parameter("e_inf", "E_inf", "J/kg", 1500.0, 3500.0, 2161.0,
              "E50 size-effect parameter (Eq. 33)"),
    Parameter("d0", "d0", "m", 4.0e-6, 12.0e-6, 9.396e-6,
              "E50 size-effect parameter (Eq. 33)", display_unit="um", display_factor=1e6),
    Parameter("phi", "phi", "1", 0.1, 3.5, 2.587, "E50 size-effect exponent (Eq. 33)"),
    Parameter("sigma_e", "sigma_E", "1", 0.1, 1.0, 0.947,
              "standard deviation of ln E* (Eq. 31)"),
    Parameter("alpha_percentage", "A", "%", 20.0, 85.0, 34.274,
              "largest t10, alpha percentage (Eq. 39)"),
    Parameter("b_prime", "b'", "1", 0.01, 0.1, 0.030, "t10 fracture parameter (Eq. 39)"),
    Parameter("truncation_ratio", "R_t", "%", 80.0, 100.0, 89.928,
              "truncation ratio of the fracture-energy distribution (Eq. 31)"),
))
"""The paper's Table 2 design ranges, linear scale as in its LHS, Table 4 values as reference."""

__all__ = ["PAPER_SPACE", "SCALES", "Parameter", "ParameterSpace"]
