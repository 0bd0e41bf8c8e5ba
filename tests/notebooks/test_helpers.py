"""The notebooks' output helpers in ``calendaring.process.plots``."""

from __future__ import annotations

import struct

import pytest

from calendaring.process.plots import NOTEBOOK_OUT_ENV, notebook_output, show_figure


def test_notebook_output_under_the_environment_folder(tmp_path, monkeypatch):
    monkeypatch.setenv(NOTEBOOK_OUT_ENV, str(tmp_path / "nb"))
    out = notebook_output("20_calendering_run")
    assert out == tmp_path / "nb" / "20_calendering_run"
    assert out.is_dir()
    assert notebook_output("20_calendering_run") == out  # an existing folder is kept


def test_show_figure_writes_the_png_at_its_dpi_and_closes_the_figure(tmp_path):
    pytest.importorskip("IPython")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(2.0, 1.0))
    ax.plot([0, 1], [0, 1])
    n_open = len(plt.get_fignums())
    path = show_figure(fig, tmp_path / "line.png", dpi=120)
    assert path == tmp_path / "line.png"
    head = path.read_bytes()[:24]
    assert head[:8] == b"\x89PNG\r\n\x1a\n"
    assert struct.unpack(">II", head[16:24]) == (240, 120)  # 2 x 1 inches at 120 dpi
    assert len(plt.get_fignums()) == n_open - 1
    assert not list(tmp_path.glob(".*tmp*"))  # the temporary name was renamed away
