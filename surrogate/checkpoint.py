"""Self-describing surrogate checkpoints (one file per model or deep ensemble).

A checkpoint is a ``torch.save`` dictionary of plain types and tensors, loadable with
``torch.load(weights_only=True)`` (no pickled code):

==================  ==========================================================
key                 content
==================  ==========================================================
format, version     "calendaring-surrogate", :data:`CHECKPOINT_VERSION`
software_version    ``calendaring.__version__`` and ``torch.__version__``
created             UTC time stamp
architecture        :meth:`ModelConfig.to_dict`
members             list of ``state_dict`` (one per ensemble member)
normalisation       cbrt_min, cbrt_max [Pa^(1/3)] fitted on the training split
parameter_space     JSON of :meth:`ParameterSpace.to_json`
depth               (196,) float64 [m]
load_edges          (31,) float64 [N]; ``load_scale`` "log" or "linear"
diameter_edges      (31,) float64 [m]
info                JSON: dataset fingerprint and path, split run ids, training
                    configuration, loss tables, histories, metrics
snapshots           {epoch: {pressure_true, pressure_pred, dist_true, dist_pred}}
                    float32 samples of the first member for the Fig. 5 PCA figure
==================  ==========================================================

Writes are atomic (temporary name in the same folder, then ``os.replace``).
"""

from __future__ import annotations

import datetime
import hashlib
import json
from pathlib import Path

import numpy as np
import torch

from calendaring import __version__, atomic_path

FORMAT = "calendaring-surrogate"
CHECKPOINT_VERSION = 1
_REQUIRED = ("format", "checkpoint_version", "architecture", "members", "normalisation",
             "parameter_space", "depth", "load_edges", "diameter_edges")


class CheckpointError(ValueError):
    """A model file that cannot be used (names the file and the reason)."""

    def __init__(self, path: str | Path, reason: str) -> None:
        self.path = Path(path)
        self.reason = reason
        super().__init__(f"{path}: {reason}")


def json_default(obj):
    """JSON encoder for NumPy scalars and arrays."""
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.floating):
        return float(obj)
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def software_version() -> dict[str, str]:
    return {"calendaring": __version__, "torch": str(torch.__version__)}


def write_checkpoint(path: str | Path, obj: dict) -> Path:
    """Write a checkpoint dictionary atomically; fills format, version and time stamp."""
    path = Path(path)
    obj = dict(obj)
    obj.setdefault("format", FORMAT)
    obj.setdefault("checkpoint_version", CHECKPOINT_VERSION)
    obj.setdefault("software_version", software_version())
    obj.setdefault("created", datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"))
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        torch.save(obj, tmp)
    return path


def read_checkpoint(path: str | Path) -> dict:
    """Load and check a checkpoint dictionary; raises :class:`CheckpointError`."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(path, "no such file")
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:
        raise CheckpointError(path, f"not a readable surrogate checkpoint ({err})") from None
    if not isinstance(obj, dict) or obj.get("format") != FORMAT:
        fmt = obj.get("format") if isinstance(obj, dict) else type(obj).__name__
        raise CheckpointError(path, f"not a surrogate checkpoint (format = {fmt!r}, expected "
                                    f"{FORMAT!r}); make one with `surrogate train`")
    if int(obj.get("checkpoint_version", -1)) != CHECKPOINT_VERSION:
        raise CheckpointError(path, f"checkpoint_version {obj.get('checkpoint_version')} is not "
                                    f"supported (this reader knows {CHECKPOINT_VERSION})")
    missing = [k for k in _REQUIRED if k not in obj]
    if missing:
        raise CheckpointError(path, f"missing entries {missing}")
    if not obj["members"]:
        raise CheckpointError(path, "no model weights (members is empty)")
    return obj


# entries that say when and by what a checkpoint was written, not what it computes
_VOLATILE = ("created", "info", "snapshots", "software_version")


def checkpoint_fingerprint(path: str | Path) -> str:
    """sha256 over what a checkpoint computes with: the weights, the GP, the normalisation,
    the architecture, the axes and the parameter space, not its time stamp, training
    record or snapshots. A model retrained with the same seed, data and settings (training
    is deterministic on the CPU) has the same fingerprint, where its file's sha256 differs."""
    obj = read_checkpoint(path)
    h = hashlib.sha256()

    def feed(x) -> None:
        if isinstance(x, torch.Tensor):
            x = x.detach().cpu().contiguous().numpy()
        if isinstance(x, np.ndarray):
            h.update(f"array {x.dtype} {x.shape}".encode())
            h.update(np.ascontiguousarray(x).tobytes())
        elif isinstance(x, dict):
            h.update(b"{")
            for k in sorted(x, key=str):
                h.update(repr(k).encode())
                feed(x[k])
            h.update(b"}")
        elif isinstance(x, (list, tuple)):
            h.update(b"[")
            for v in x:
                feed(v)
            h.update(b"]")
        else:
            h.update(repr(x).encode())

    feed({k: v for k, v in obj.items() if k not in _VOLATILE})
    return h.hexdigest()


def info_to_json(info: dict) -> str:
    return json.dumps(info, default=json_default)


def snapshots_to_tensors(snapshots: dict[int, dict[str, np.ndarray]]) -> dict:
    return {str(int(e)): {k: torch.as_tensor(np.asarray(v, np.float32)) for k, v in s.items()}
            for e, s in snapshots.items()}


def snapshots_from_tensors(obj: dict) -> dict[int, dict[str, np.ndarray]]:
    return {int(e): {k: v.numpy() for k, v in s.items()} for e, s in (obj or {}).items()}


__all__ = ["CHECKPOINT_VERSION", "FORMAT", "CheckpointError", "checkpoint_fingerprint",
           "info_to_json", "json_default", "read_checkpoint", "snapshots_from_tensors",
           "snapshots_to_tensors", "software_version", "write_checkpoint"]
