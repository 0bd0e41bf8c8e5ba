"""CPU and CUDA backends run the same physics: the tiny preset with breakage on both, in two
processes (Taichi runs one backend per process), from one settled bed (packed once on the
CPU: settling is the most chaotic stage of a run), gives the same pressure curve.

Skipped without an NVIDIA GPU (no ``nvidia-smi`` or Taichi cannot start CUDA). The pair
forces are summed per particle in a fixed order on both backends, so the curves differ only
by floating-point contraction and math-library rounding, which a DEM run amplifies slowly:
the comparison is of the curve before the first breakage, where it must agree to 1e-6, and
of the whole curve, to 5 % RMS of its mean.
"""

import shutil
import subprocess
import sys

import numpy as np
import pytest

from calendaring.process.runfile import read_run


def _cuda_ok() -> bool:
    if shutil.which("nvidia-smi") is None:
        return False
    code = ("import taichi as ti; ti.init(arch=ti.cuda, log_level=ti.ERROR); "
            "print('ARCH', ti.lang.impl.current_cfg().arch == ti.cuda)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=300)
    return proc.returncode == 0 and "ARCH True" in proc.stdout


pytestmark = pytest.mark.skipif(not _cuda_ok(), reason="needs an NVIDIA GPU with CUDA")


def _cli(*args) -> None:
    proc = subprocess.run([sys.executable, "-m", "calendaring.cli", *args], capture_output=True,
                          text=True, timeout=1800)
    assert proc.returncode == 0, proc.stderr[-2000:]


def _run(arch: str, bed, out) -> None:
    _cli("run", "--preset", "tiny", "--threads", "1", "--set", f"numerics.arch={arch}",
         "--set", f'electrode.packing="{bed}"', "--quiet", "--out", str(out))


def test_cpu_and_cuda_pressure_curves_agree(tmp_path):
    bed = tmp_path / "bed.csv"
    _cli("pack", "--preset", "tiny", "--seed", "0", "--out", str(bed))
    _run("cpu", bed, tmp_path / "cpu.h5")
    _run("cuda", bed, tmp_path / "cuda.h5")
    cpu, gpu = read_run(tmp_path / "cpu.h5"), read_run(tmp_path / "cuda.h5")
    assert cpu.config.numerics.arch == "cpu" and gpu.config.numerics.arch == "cuda"
    d_cpu, p_cpu = cpu.pressure["depth"], cpu.pressure["value"]
    d_gpu, p_gpu = gpu.pressure["depth"], gpu.pressure["value"]
    np.testing.assert_allclose(d_gpu, d_cpu, rtol=0, atol=1e-12)
    first = min(cpu.breakage["depth"].min() if len(cpu.breakage["depth"]) else d_cpu[-1],
                gpu.breakage["depth"].min() if len(gpu.breakage["depth"]) else d_gpu[-1])
    before = d_cpu < first
    assert before.sum() >= 5
    np.testing.assert_allclose(p_gpu[before], p_cpu[before], rtol=1e-6,
                               atol=1e-6 * np.abs(p_cpu).max())
    rms = np.sqrt(np.mean((p_gpu - p_cpu) ** 2)) / np.mean(np.abs(p_cpu))
    assert rms < 0.05, f"RMS difference {rms:.3g} of the mean pressure"
