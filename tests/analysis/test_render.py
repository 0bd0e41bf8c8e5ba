"""Off-screen renders of a snapshot (Fig. 1) and of its bond network (Fig. 6)."""

import numpy as np
import pytest

from analysis.render import RenderError, bond_segments, render_bonds, render_particles
from calendaring.core.errors import ConfigError
from calendaring.process.runfile import read_run
from tests.analysis import write_small_run


@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    return write_small_run(tmp_path_factory.mktemp("render") / "small.h5")


def _render_or_skip(fn, *args, **kwargs):
    try:
        return fn(*args, **kwargs)
    except RenderError as err:  # only when no off-screen GL context exists at all
        pytest.skip(f"no off-screen OpenGL context on this machine: {err}")


def _image(path):
    import matplotlib.image as mpimg

    return mpimg.imread(path)


def test_render_particles_writes_a_picture(small_run, tmp_path):
    out = _render_or_skip(render_particles, small_run, 1, tmp_path / "particles.png",
                          window_size=(400, 320))
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    img = _image(out)
    assert img.shape[:2] == (320, 400)
    # not a blank canvas: many distinct colours (diameter colour map, grey CB, shading)
    assert len(np.unique(img.reshape(-1, img.shape[-1]), axis=0)) > 50
    assert not list(tmp_path.glob(".*tmp*"))  # written atomically, no leftovers


def test_render_bonds_writes_a_picture(small_run, tmp_path):
    out = _render_or_skip(render_bonds, small_run, 0.0, tmp_path / "bonds.png",
                          window_size=(400, 320))
    img = _image(out)
    assert img.shape[:2] == (320, 400)
    rgb = img[..., :3].reshape(-1, 3)
    blue = (rgb[:, 2] > 0.6) & (rgb[:, 0] < 0.3)  # intact bonds are drawn blue
    red = (rgb[:, 0] > 0.7) & (rgb[:, 1] < 0.3) & (rgb[:, 2] < 0.3)  # failed in tension
    assert blue.sum() > 20 and red.sum() > 5


def test_bond_segments_follow_the_bond_states_and_the_minimum_image(small_run):
    record = read_run(small_run)
    snap = record.snapshots[1]
    seg = bond_segments(record, snap)
    state = snap.bonds["state"]
    assert len(seg["intact"]) == np.sum(state == 0)
    assert len(seg["failed in tension"]) == np.sum(state == 1)
    assert len(seg["failed in shear"]) == np.sum(state == 2)
    for s in seg.values():
        d = np.abs(s[:, 1] - s[:, 0])
        assert np.all(d[:, 0] <= record.cell_x / 2 + 1e-12)
        assert np.all(d[:, 1] <= record.cell_y / 2 + 1e-12)
    # touching pairs drawn white really touch (under the periodic minimum image)
    slot = {tuple(np.round(p, 15)): k for k, p in enumerate(snap.position)}
    for a, b in seg["contact, never bonded"]:
        i = slot[tuple(np.round(a, 15))]
        assert np.linalg.norm(b - a) < snap.radius[i] + snap.radius.max()


def test_bad_snapshot_is_a_clear_error(small_run, tmp_path):
    with pytest.raises(ConfigError, match="snapshot"):
        render_particles(small_run, 7, tmp_path / "x.png")
