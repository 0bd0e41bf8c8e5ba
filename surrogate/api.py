"""The surrogate's Python interface: :func:`load` a checkpoint, then ``predict``.

    >>> import surrogate
    >>> m = surrogate.load("model.pt")            # one model or a deep ensemble
    >>> pred = m.predict({"d0": 9e-6, "phi": [1.0, 2.0]})   # missing names: reference values
    >>> pred.pressure.shape, pred.distribution.shape         # (2, 196) [Pa], (2, 30, 30)

A model trained with ``--pressure-head gp`` carries a PCA + GP pressure branch
(:class:`~surrogate.gp.GPPressure`): its pressure comes from the GP, its distribution from
the network(s), and ``*_std`` / ``pressure_normalised_var`` are the GP's latent variance
(for a single network too) instead of the member spread.

Physical parameter values are validated against the checkpoint's
:class:`~calendaring.data.params.ParameterSpace` (:class:`ConfigError` naming the key, the value
and the allowed range). Pressures come back in Pa, distributions as probabilities
[load bin, diameter bin]; an ensemble adds the member spread (``*_std``).
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from calendaring import ConfigError, Dataset, ParameterSpace, bin_centres, pressure_components
from surrogate.checkpoint import (
    CheckpointError,
    info_to_json,
    read_checkpoint,
    snapshots_from_tensors,
    snapshots_to_tensors,
    write_checkpoint,
)
from surrogate.data import Normalisation
from surrogate.ensemble import ensemble_forward
from surrogate.gp import GPPressure
from surrogate.model import DualBranchMLP, ModelConfig

PREDICT_BATCH = 2048  # rows per forward pass in predict()
# Arithmetic of the forward pass in predict(): float32 (the trained weights) or bfloat16
# autocast (matrix products in bfloat16, accumulated in float32; 1.5-2 times the rows per
# second on CPUs with AVX512-BF16 or AMX, slower on CPUs without them). On the reference
# model bfloat16 moved the normalised pressures by an MSE of about 1e-6 and the
# distributions by a KL of about 2e-5, against model errors of 9e-4 and 0.65
# (benchmarks/bench_surrogate.py measures both).
PRECISIONS = ("float32", "bfloat16")


@dataclass
class Prediction:
    """Surrogate outputs for ``n`` parameter sets (SI units).

    ``pressure`` is ``pressure_from_normalised(pressure_normalised)``, the ensemble mean
    taken in normalised units; ``pressure_std`` is the standard deviation of the members'
    pressures in Pa (None for a single model), ``pressure_normalised_var`` the member
    variance in normalised units (with a GP pressure branch both are the GP's: its latent
    variance, and the standard deviation in Pa to first order). ``defaulted`` names the
    parameters that were not given and took the space's reference values.
    """

    params: np.ndarray  # (n, 8) physical
    pressure: np.ndarray  # (n, 196) Pa
    pressure_normalised: np.ndarray  # (n, 196)
    distribution: np.ndarray  # (n, 30, 30), rows sum to 1
    pressure_std: np.ndarray | None = None  # (n, 196) Pa
    pressure_normalised_var: np.ndarray | None = None  # (n, 196)
    distribution_std: np.ndarray | None = None  # (n, 30, 30)
    defaulted: list[str] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.params)


class SurrogateModel:
    """A trained single model or deep ensemble with its normalisation and metadata.

    Build one with :meth:`from_training` or :func:`load`; the interface is the same for
    both kinds (``is_ensemble`` tells them apart).
    """

    def __init__(self, members: Sequence[DualBranchMLP], normalisation: Normalisation,
                 space: ParameterSpace, depth, load_edges, diameter_edges,
                 load_scale: str = "log", info: dict | None = None,
                 snapshots: dict | None = None, pressure_gp: GPPressure | None = None):
        if not members:
            raise ConfigError("members", 0, "at least one model")
        self.members = list(members)
        for m in self.members:
            m.eval()
        self.config: ModelConfig = self.members[0].config
        self.normalisation = normalisation
        self.space = space
        self.depth = np.asarray(depth, dtype=float)
        self.load_edges = np.asarray(load_edges, dtype=float)
        self.diameter_edges = np.asarray(diameter_edges, dtype=float)
        self.load_scale = load_scale
        self.info = dict(info or {})
        self.snapshots = dict(snapshots or {})
        self.pressure_gp = pressure_gp
        if pressure_gp is not None:
            pressure_gp.eval()
            if pressure_gp.shape["n_pressure"] != self.config.n_pressure or \
                    pressure_gp.shape["n_inputs"] != len(space):
                raise ConfigError("pressure_gp shape", pressure_gp.shape,
                                  f"{self.config.n_pressure} depths and {len(space)} inputs "
                                  "(the network's)")

    # ------------------------------------------------------------------ description
    @property
    def is_ensemble(self) -> bool:
        return len(self.members) > 1

    @property
    def n_members(self) -> int:
        return len(self.members)

    @property
    def pressure_head(self) -> str:
        """"gp" when the pressure comes from a PCA + GP branch, else "mlp"."""
        return "mlp" if self.pressure_gp is None else "gp"

    def member(self, i: int) -> SurrogateModel:
        """Ensemble member ``i`` as a single model (same normalisation, space and bins)."""
        if not 0 <= int(i) < self.n_members:
            raise ConfigError("member", i, f"an index in [0, {self.n_members - 1}]")
        return SurrogateModel([self.members[int(i)]], self.normalisation, self.space,
                              self.depth, self.load_edges, self.diameter_edges,
                              self.load_scale, self.info, pressure_gp=self.pressure_gp)

    @property
    def load_centres(self) -> np.ndarray:
        return bin_centres(self.load_edges, self.load_scale)

    @property
    def diameter_centres(self) -> np.ndarray:
        return bin_centres(self.diameter_edges, "linear")

    def __repr__(self) -> str:
        kind = f"ensemble of {self.n_members}" if self.is_ensemble else "single model"
        if self.pressure_gp is not None:
            kind += f", PCA + GP pressure ({self.pressure_gp.shape['n_components']} components)"
        return (f"SurrogateModel({kind}, {len(self.space)} inputs, {len(self.depth)} depths, "
                f"{self.config.dist_shape} bins)")

    # ------------------------------------------------------------------ units
    def pressure_from_normalised(self, x):
        """Normalised cube-root units -> Pa (NumPy or torch)."""
        return self.normalisation.denormalise(x)

    def normalise_pressure(self, p):
        """Pa -> normalised cube-root units (NumPy or torch)."""
        return self.normalisation.normalise(p)

    # ------------------------------------------------------------------ forward passes
    def torch_forward(self, u: torch.Tensor, distribution: bool = True
                      ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
        """Differentiable forward pass in eval mode (no dropout).

        Args:
            u: ``(n, 8)`` float32 unit parameters in ``[0, 1]``.
            distribution: False skips the distribution head (``dist`` is then None); the
                pressure outputs are the same either way.

        Returns:
            ``p_norm (n, 196)``, ``dist (n, 30, 30)``, ``p_norm_var (n, 196)`` (ensemble
            member variance, normalised units) or None for a single model; with a GP
            pressure branch its mean and latent variance.
        """
        for m in self.members:
            m.eval()
        if self.pressure_gp is not None:  # the networks serve the distribution only
            d = ensemble_forward(self.members, u)[1] if distribution else None
            p, p_var = self.pressure_gp(u)
            return p, d, p_var
        p, d, p_var, _ = ensemble_forward(self.members, u, distribution)
        return p, d, p_var

    def predict_unit(self, u, batch_size: int = PREDICT_BATCH,
                     precision: str = "float32") -> Prediction:
        """:meth:`predict` from unit parameters ``(n, 8)`` in ``[0, 1]``."""
        u = np.asarray(u, dtype=float)
        if u.ndim == 1:
            u = u[None, :]
        if u.ndim != 2 or u.shape[1] != len(self.space):
            raise ConfigError("u", f"array of shape {u.shape}",
                              f"shape (n, {len(self.space)}) in the order {self.space.names}")
        bad = ~(np.isfinite(u) & (u >= -1e-9) & (u <= 1 + 1e-9))
        if bad.any():
            r, c = np.argwhere(bad)[0]
            raise ConfigError(f"u[{r}, {c}] ({self.space.names[c]})", float(u[r, c]),
                              "[0, 1] (unit-scaled parameter)")
        return self._predict(u, self.space.from_unit(u), [], batch_size, precision)

    def predict(self, params, *, defaults: str | None = "reference",
                batch_size: int = PREDICT_BATCH, precision: str = "float32") -> Prediction:
        """Predict from physical parameter values.

        Args:
            params: ``{name: scalar or 1-D array}`` (arrays of one common length; scalars
                broadcast) or an array ``(n, 8)`` / ``(8,)`` in the space's column order, in
                physical units (SI; percent for A and R_t).
            defaults: "reference" fills names missing from a mapping with the space's
                reference values (listed in :attr:`Prediction.defaulted`); None requires all.
            batch_size: rows per forward pass.
            precision: "float32" (default) or "bfloat16": the forward pass under bfloat16
                autocast, for bulk screening on CPUs with native bfloat16 (see
                :data:`PRECISIONS`); outputs are float64 either way.

        Raises:
            ConfigError: an unknown name, a value outside the bounds, a wrong shape, an
                unknown precision.
        """
        x, defaulted = self._rows(params, defaults)
        return self._predict(self.space.to_unit(x), x, defaulted, batch_size, precision)

    def _rows(self, params, defaults) -> tuple[np.ndarray, list[str]]:
        names = self.space.names
        if isinstance(params, Mapping):
            cols, n = {}, 1
            for key, v in params.items():
                if key not in names:
                    raise ConfigError("parameter", key, f"one of {names}")
                try:
                    a = np.atleast_1d(np.asarray(v, dtype=float))
                except (TypeError, ValueError):
                    raise ConfigError(key, v, "a number or a 1-D array of numbers") from None
                if a.ndim != 1 or len(a) == 0:
                    raise ConfigError(key, f"array of shape {a.shape}", "a scalar or 1-D array")
                if len(a) != 1:
                    if n not in (1, len(a)):
                        raise ConfigError(key, f"{len(a)} values",
                                          f"1 or {n} values (the other parameters' length)")
                    n = len(a)
                cols[key] = a
            missing = [k for k in names if k not in cols]
            if missing and defaults is None:
                raise ConfigError("parameters", sorted(cols), f"all of {names} (missing "
                                                              f"{missing})")
            if defaults not in (None, "reference"):
                raise ConfigError("defaults", defaults, "'reference' or None")
            x = np.tile(self.space.reference, (n, 1))
            for key, a in cols.items():
                x[:, names.index(key)] = a
            return self.space.check_array(x), missing
        x = np.asarray(params, dtype=float)
        if x.ndim == 1:
            x = x[None, :]
        if x.ndim != 2:
            raise ConfigError("params", f"array of shape {x.shape}", f"(n, {len(names)})")
        return self.space.check_array(x), []

    @torch.inference_mode()
    def _predict(self, u: np.ndarray, x: np.ndarray, defaulted: list[str],
                 batch_size: int, precision: str = "float32") -> Prediction:
        if precision not in PRECISIONS:
            raise ConfigError("precision", precision, f"one of {PRECISIONS}")
        for m in self.members:
            m.eval()
        n = len(u)
        ut = torch.as_tensor(u, dtype=torch.float32)
        low = precision == "bfloat16"

        def run(member, ub):
            if not low:
                return member(ub)
            with torch.autocast("cpu", dtype=torch.bfloat16):
                p, d = member(ub)
            return p.float(), d.float()

        p_mean, d_mean, p_var, p_std_pa, d_std = [], [], [], [], []
        for s in range(0, max(n, 1), max(int(batch_size), 1)):
            ub = ut[s:s + batch_size]
            if not self.is_ensemble:
                p, d = run(self.members[0], ub)
                p_mean.append(p)
                d_mean.append(d)
                continue
            outs = [run(m, ub) for m in self.members]
            p = torch.stack([o[0] for o in outs])  # (m, b, 196)
            d = torch.stack([o[1] for o in outs])  # (m, b, 30, 30)
            p_mean.append(p.mean(0))
            d_mean.append(d.mean(0))
            p_var.append(p.var(0, unbiased=False))
            p_std_pa.append(self.pressure_from_normalised(p.double()).std(0, unbiased=False))
            d_std.append(d.std(0, unbiased=False))

        if self.pressure_gp is not None:
            p_mean, p_var, p_std_pa = [], [], []
            span = self.normalisation.span
            for s in range(0, max(n, 1), max(int(batch_size), 1)):
                p, v = self.pressure_gp(ut[s:s + batch_size].double())
                c = p * span + self.normalisation.cbrt_min  # cbrt(P)
                p_mean.append(p)
                p_var.append(v)
                p_std_pa.append(3.0 * c * c * span * v.sqrt())  # |dP/dx| sd, to first order

        def cat(parts, dtype=np.float64):
            if not parts:
                return None
            return (parts[0] if len(parts) == 1 else torch.cat(parts)).numpy().astype(dtype)

        p_norm = cat(p_mean)
        return Prediction(
            params=x, pressure=self.pressure_from_normalised(p_norm),
            pressure_normalised=p_norm, distribution=cat(d_mean),
            pressure_std=cat(p_std_pa), pressure_normalised_var=cat(p_var),
            distribution_std=cat(d_std), defaulted=list(defaulted))

    # ------------------------------------------------------------------ persistence
    @classmethod
    def from_training(cls, results, ds: Dataset, info: dict | None = None) -> SurrogateModel:
        """Wrap :class:`~surrogate.train.TrainResult` (one or a list: an ensemble)."""
        results = list(results) if isinstance(results, list | tuple) else [results]
        r0 = results[0]
        split_ids = {k: [str(ds.run_id[i]) for i in v] for k, v in r0.rows.items()}
        meta = {
            "dataset": {"fingerprint": ds.fingerprint, "path": str(ds.path or ""),
                        "n_rows": len(ds), "stroke_m": ds.stroke,
                        "train_roles": list(r0.config.train_roles),
                        "roles_present": sorted(set(map(str, ds.role)))},
            "split": split_ids,
            "train_config": r0.config.to_dict(),
            "members": [{"member": r.config.member, "seed": r.config.seed,
                         "loss_table": r.loss_table, "history": r.history.to_dict(),
                         "train_seconds": r.seconds} for r in results],
            "n_parameters_per_member": r0.model.n_parameters(),
        }
        pc = pressure_components(ds)
        if pc is not None:  # what one curve of this dataset can tell (inverse reports it)
            meta["dataset"]["pressure_components"] = {
                k: pc[k] for k in ("resolved", "tested", "alpha", "groups", "dof_bed_to_bed",
                                   "signal_share_resolved")} | {
                "noise_share": [c["noise_share"] for c in pc["components"]]}
        meta.update(info or {})
        gp = None
        if getattr(r0.config, "pressure_head", "mlp") == "gp":
            from surrogate.gp import fit_pressure_gp

            rows = np.sort(np.concatenate([r0.rows["train"], r0.rows["val"]]))
            gp, meta["pressure_gp"] = fit_pressure_gp(
                ds.unit_params[rows], r0.normalisation.normalise(ds.pressure[rows]),
                r0.config.gp_components, r0.config.seed)
            meta["pressure_gp"]["rows"] = "the training and validation split"
        return cls([r.model for r in results], r0.normalisation, ds.space, ds.depth,
                   ds.load_edges, ds.diameter_edges, ds.load_scale, meta, r0.snapshots,
                   pressure_gp=gp)

    def save(self, path: str | Path) -> Path:
        """Write the self-describing checkpoint atomically (see :mod:`surrogate.checkpoint`)."""
        return write_checkpoint(path, {
            "architecture": self.config.to_dict(),
            "members": [m.state_dict() for m in self.members],
            "normalisation": self.normalisation.to_dict(),
            "parameter_space": json.dumps(self.space.to_json()),
            "depth": torch.as_tensor(self.depth, dtype=torch.float64),
            "load_edges": torch.as_tensor(self.load_edges, dtype=torch.float64),
            "diameter_edges": torch.as_tensor(self.diameter_edges, dtype=torch.float64),
            "load_scale": self.load_scale,
            "info": info_to_json(self.info),
            "snapshots": snapshots_to_tensors(self.snapshots),
            **({} if self.pressure_gp is None else {"pressure_gp": {
                "shape": dict(self.pressure_gp.shape),
                "state": self.pressure_gp.state_dict()}}),
        })


def load(path: str | Path) -> SurrogateModel:
    """Load a checkpoint written by :meth:`SurrogateModel.save` (or ``surrogate train``).

    Raises:
        CheckpointError: missing file, wrong format or version, unusable contents.
    """
    obj = read_checkpoint(path)
    try:
        cfg = ModelConfig.from_dict(dict(obj["architecture"]))
        members = []
        for state in obj["members"]:
            m = DualBranchMLP(cfg)
            m.load_state_dict(state)
            members.append(m)
        space = ParameterSpace.from_json(json.loads(obj["parameter_space"]))
        gp = None
        if obj.get("pressure_gp") is not None:
            gp = GPPressure(**{k: int(v) for k, v in obj["pressure_gp"]["shape"].items()})
            gp.load_state_dict(obj["pressure_gp"]["state"])
        model = SurrogateModel(
            members, Normalisation.from_dict(obj["normalisation"]), space,
            obj["depth"].numpy(), obj["load_edges"].numpy(), obj["diameter_edges"].numpy(),
            str(obj.get("load_scale", "log")), json.loads(obj.get("info", "{}")),
            snapshots_from_tensors(obj.get("snapshots")), pressure_gp=gp)
    except CheckpointError:
        raise
    except Exception as err:
        raise CheckpointError(path, f"unusable contents ({err})") from None
    model.info["path"] = str(path)
    return model


__all__ = ["PRECISIONS", "PREDICT_BATCH", "Prediction", "SurrogateModel", "load"]
