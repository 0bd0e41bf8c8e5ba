"""Training data for the surrogate: splits, normalisation and a torch ``Dataset``.

The inputs are the eight parameters scaled to ``[0, 1]`` by the dataset's
:class:`~calendaring.data.params.ParameterSpace`; the targets are the smoothed pressure in
normalised cube-root units (paper section 2.3) and the 30 x 30 breakage histogram.

The normalisation statistics (``cbrt_min``, ``cbrt_max`` [Pa^(1/3)]) are fitted on the
training rows only (:meth:`Normalisation.fit`), never on validation, test or held-out rows,
and travel with the model in its checkpoint. The file's own global statistics are not used.

Rows: by default only ``role == "train"`` rows are split 8:1:1 and used for fitting;
``replicate`` rows (repeated seeds at a few parameter sets) are kept apart for the noise
floor and as an extra test set, ``holdout`` rows are never trained on.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from calendaring import ConfigError, Dataset

TRAIN_ROLES_DEFAULT = ("train",)
# refine: runs near a calibration's posterior, added by `inverse refine`
TRAINABLE_ROLES = ("train", "replicate", "refine")


@dataclass(frozen=True, slots=True)
class Normalisation:
    """Cube-root min-max scaling ``x = (cbrt(P) - cbrt_min) / (cbrt_max - cbrt_min)``.

    Attributes are in Pa^(1/3). Works on NumPy arrays and torch tensors alike.
    """

    cbrt_min: float
    cbrt_max: float

    def __post_init__(self) -> None:
        if not (np.isfinite(self.cbrt_min) and np.isfinite(self.cbrt_max)
                and self.cbrt_max > self.cbrt_min):
            raise ConfigError("normalisation", (self.cbrt_min, self.cbrt_max),
                              "finite cbrt_min < cbrt_max [Pa^(1/3)]")

    @classmethod
    def fit(cls, pressure: np.ndarray) -> Normalisation:
        """Statistics of the pressures ``(n, m)`` [Pa] (the training rows only)."""
        c = np.cbrt(np.asarray(pressure, dtype=float))
        return cls(float(c.min()), float(c.max()))

    @property
    def span(self) -> float:
        return self.cbrt_max - self.cbrt_min

    def normalise(self, p):
        """Pa -> normalised units (NumPy or torch)."""
        if isinstance(p, torch.Tensor):
            c = torch.sign(p) * torch.abs(p) ** (1.0 / 3.0)
            return (c - self.cbrt_min) / self.span
        return (np.cbrt(np.asarray(p, dtype=float)) - self.cbrt_min) / self.span

    def denormalise(self, x):
        """Normalised units -> Pa (NumPy or torch); the inverse of :meth:`normalise`."""
        c = x * self.span + self.cbrt_min
        return c * c * c  # not c**3: a general power, 5x slower on NumPy arrays

    def to_dict(self) -> dict:
        return {"cbrt_min": self.cbrt_min, "cbrt_max": self.cbrt_max, "unit": "Pa^(1/3)"}

    @classmethod
    def from_dict(cls, d: dict) -> Normalisation:
        return cls(float(d["cbrt_min"]), float(d["cbrt_max"]))


def trainable_rows(ds: Dataset, roles: tuple[str, ...] = TRAIN_ROLES_DEFAULT) -> np.ndarray:
    """Indices of the rows that may be split for training (``holdout`` never)."""
    roles = tuple(roles)
    if "holdout" in roles:
        raise ConfigError("train_roles", roles, f"a subset of {TRAINABLE_ROLES}; "
                                                "holdout rows are never trained on")
    for r in roles:
        if r not in TRAINABLE_ROLES:
            raise ConfigError("train_roles", r, f"one of {TRAINABLE_ROLES}")
    idx = np.nonzero(np.isin(ds.role, roles))[0]
    if len(idx) < 3:
        raise ConfigError("dataset rows", f"{len(idx)} rows with role in {roles}",
                          "at least 3 rows to split 8:1:1")
    return idx


def split_indices(n: int, seed: int = 0, fractions: tuple[float, float, float] = (0.8, 0.1, 0.1)
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Seeded random split of ``range(n)`` into train / validation / test (8:1:1).

    Validation and test get ``round(fraction * n)`` rows each, at least one each when
    ``n >= 3``; the training set gets the rest. Each part is sorted.
    """
    if abs(sum(fractions) - 1.0) > 1e-9 or min(fractions) < 0:
        raise ConfigError("split", fractions, "three non-negative fractions summing to 1")
    if n < 3:
        raise ConfigError("split", n, "at least 3 rows")
    perm = np.random.default_rng(seed).permutation(n)
    n_val = max(1, round(fractions[1] * n)) if fractions[1] > 0 else 0
    n_test = max(1, round(fractions[2] * n)) if fractions[2] > 0 else 0
    val, test, train = perm[:n_val], perm[n_val:n_val + n_test], perm[n_val + n_test:]
    return np.sort(train), np.sort(val), np.sort(test)


def has_events(ds: Dataset) -> np.ndarray:
    """Rows whose histogram is a distribution (at least one event); others carry no KL."""
    return (np.asarray(ds.n_events) > 0) & (ds.histogram.sum(axis=(1, 2)) > 0)


class SurrogateDataset(torch.utils.data.Dataset):
    """Rows of a :class:`~calendaring.data.dataset.Dataset` as float32 tensors.

    Items are ``(u (8,), p_norm (196,), dist (30, 30), kl_weight ())``: unit parameters,
    pressure normalised with ``norm``, the histogram, and 1.0 for rows with events (0.0 for
    a run without breakage, whose empty histogram is left out of the KL term).
    """

    def __init__(self, ds: Dataset, norm: Normalisation, rows: np.ndarray | None = None):
        rows = np.arange(len(ds)) if rows is None else np.asarray(rows)
        sub = ds.subset(rows)
        self.rows = rows
        self.u = torch.as_tensor(sub.unit_params, dtype=torch.float32)  # (n, 8)
        self.p = torch.as_tensor(norm.normalise(sub.pressure), dtype=torch.float32)  # (n, 196)
        self.d = torch.as_tensor(sub.histogram, dtype=torch.float32)  # (n, 30, 30)
        self.w = torch.as_tensor(has_events(sub), dtype=torch.float32)  # (n,)

    @classmethod
    def from_file(cls, path, norm: Normalisation, rows: np.ndarray | None = None
                  ) -> SurrogateDataset:
        """Read a dataset file (:func:`calendaring.data.dataset.read_dataset`, which raises
        ``DatasetError`` naming a missing dataset) and wrap ``rows`` of it."""
        from calendaring import read_dataset

        return cls(read_dataset(path), norm, rows)

    def __len__(self) -> int:
        return len(self.u)

    def __getitem__(self, i):
        return self.u[i], self.p[i], self.d[i], self.w[i]

    def tensors(self) -> tuple[torch.Tensor, ...]:
        return self.u, self.p, self.d, self.w


__all__ = ["TRAINABLE_ROLES", "TRAIN_ROLES_DEFAULT", "Normalisation", "SurrogateDataset",
           "has_events", "split_indices", "trainable_rows"]
