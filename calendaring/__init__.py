"""DEM simulation of Li-ion electrode calendering with particle breakage.

This module is the package's public surface: the other packages (``surrogate``, ``inverse``,
``analysis``), the notebooks and the benchmarks import from ``calendaring`` only, e.g.
``from calendaring import read_run, load_preset, run``. The names live in four layers, each
importing only the ones below it (``docs/architecture.md``)::

    calendaring.cli        the command line
    calendaring.data       parameter space, designs, sweeps, digests, datasets
    calendaring.process    electrode recipe, packings, the staged run, run files, plots
    calendaring.engine     Taichi kernels and the Simulation (the only layer importing Taichi)
    calendaring.core       errors, units, atomic files, the configuration, the CLI contract

Names are resolved on first use, so ``import calendaring`` stays light: it starts no Taichi
runtime and imports neither Taichi nor h5py. The runtime is started only by
:func:`init_taichi` (or by the first :class:`Simulation`).
"""

from __future__ import annotations

import importlib
from typing import Any

from calendaring._version import __version__ as __version__

#: public name -> the module that defines it (a module itself where the name is a module)
_SURFACE: dict[str, str] = {}


def _export(module: str, *names: str) -> None:
    for name in names:
        _SURFACE[name] = module


_export("calendaring.core.errors", "ConfigError", "SimulationError")
_export("calendaring.core.units", "to_mpa", "to_um")
_export("calendaring.core.fileio", "atomic_path", "json_safe", "save_figure", "write_h5",
        "write_json", "write_text")
_export("calendaring.core.config", "SimConfig", "format_override", "load_config",
        "load_config_dict", "load_preset", "pair_key", "parse_override", "with_overrides",
        "config_hash", "config_json", "PRESETS")
_export("calendaring.core.cli_contract", "ContractParser", "EXIT_BAD_INPUT", "EXIT_BUG",
        "EXIT_INTERRUPTED", "EXIT_OK", "EXIT_UNSTABLE", "input_file", "input_folder",
        "integer", "output_path", "real", "run_cli")
_export("calendaring.engine.backend", "init_taichi")
_export("calendaring.engine.simulation", "Simulation")
_export("calendaring.engine.contact_params", "damping_ratio", "reduced_modulus")
_export("calendaring.process.electrode", "random_insertion", "recipe", "sample_diameters")
_export("calendaring.process.packing", "Packing", "read_csv", "read_lammps_data", "write_csv",
        "write_lammps_data", "write_vtk")
_export("calendaring.process.plots", "notebook_output", "show_figure")
_export("calendaring.process.run", "CalenderRun", "pool_capacity", "run")
_export("calendaring.process.runfile", "RunFileError", "RunRecord", "Snapshot", "read_run")
_export("calendaring.data.params", "PAPER_SPACE", "Parameter", "ParameterSpace")
_export("calendaring.data.curves", "resample_pressure", "smooth")
_export("calendaring.data.dataset", "Dataset", "DatasetError", "KL_FLOOR", "bin_centres",
        "bin_events", "build_dataset", "centroids", "histogram_edges", "kl_divergence",
        "noise_floor", "read_dataset", "sampled_kl_floor", "synthetic_dataset",
        "write_dataset", "append_runs", "dataset_config", "perfect_model_kl", "seed_means",
        "pressure_components")
_export("calendaring.data.design", "read_design_csv", "write_design_csv")
_export("calendaring.data.sweep", "SweepOptions", "read_manifest", "sweep")
_export("calendaring.cli", "summary")
#: modules exported whole
_MODULES = {"eepa": "calendaring.engine.laws.eepa"}

__all__ = sorted(["__version__", *_SURFACE, *_MODULES])


def __getattr__(name: str) -> Any:
    if name in _MODULES:
        value = importlib.import_module(_MODULES[name])
    elif name in _SURFACE:
        value = getattr(importlib.import_module(_SURFACE[name]), name)
    else:
        raise AttributeError(f"module 'calendaring' has no attribute {name!r}")
    globals()[name] = value  # resolved once
    return value


def __dir__() -> list[str]:
    return __all__
