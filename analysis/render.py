"""Off-screen 3-D pictures of run snapshots (pyvista): particles by diameter (paper Fig. 1)
and the bond network by bond state (paper Fig. 6).

Rendering needs an OpenGL context without a display. VTK >= 9.4 falls back to an EGL window
(Mesa ``libegl-mesa0`` + ``libgl1-mesa-dri`` give a software one); when no display is set
this module asks VTK for EGL directly. If no context can be made and ``Xvfb`` exists, a
virtual X server is started (``pyvista.start_xvfb``); otherwise :class:`RenderError` says
what to install. Lengths are drawn in micrometres (display only); nothing is ever shown on
screen.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np

from calendaring import ConfigError

#: Bond-state colours (Fig. 6: intact blue, never bonded white, broken red).
BOND_COLOURS = {"contact, never bonded": "white", "intact": "#1f5fd6",
                "failed in tension": "#e02020", "failed in shear": "#ff9a1f"}
BOND_STATES = {0: "intact", 1: "failed in tension", 2: "failed in shear"}  # 3: removed
CB_COLOUR = "#9a9a9a"


_EGL = "vtkEGLRenderWindow"


class RenderError(RuntimeError):
    """No off-screen OpenGL context could be made (names the packages to install)."""


def _pyvista():
    """Import pyvista for off-screen use (EGL when there is no display)."""
    if not os.environ.get("DISPLAY") and "VTK_DEFAULT_OPENGL_WINDOW" not in os.environ:
        os.environ["VTK_DEFAULT_OPENGL_WINDOW"] = _EGL
    import pyvista

    pyvista.OFF_SCREEN = True
    return pyvista


def _record_and_snapshot(run_file, snapshot):
    from calendaring import RunRecord, read_run

    record = run_file if isinstance(run_file, RunRecord) else read_run(run_file)
    if not record.snapshots:
        raise ConfigError("snapshot", snapshot, f"a snapshot, but {record.path} has none")
    if isinstance(snapshot, (int, np.integer)) and not isinstance(snapshot, bool):
        if not 0 <= snapshot < len(record.snapshots):
            raise ConfigError("snapshot", snapshot,
                              f"an index in [0, {len(record.snapshots) - 1}]")
        return record, record.snapshots[int(snapshot)]
    if isinstance(snapshot, float):
        return record, record.snapshot_near(snapshot)
    raise ConfigError("snapshot", snapshot, "a snapshot index (int) or a depth [m] (float)")


def _box(pv, record, snap, plotter) -> None:
    """Cell outline and the two plates as transparent planes (um)."""
    lx, ly = record.cell_x * 1e6, record.cell_y * 1e6
    z0, z1 = snap.z_bottom * 1e6, snap.z_top * 1e6
    plotter.add_mesh(pv.Box(bounds=(0, lx, 0, ly, z0, z1)).outline(), color="black",
                     line_width=1)
    for z in (z0, z1):
        plane = pv.Plane(center=(lx / 2, ly / 2, z), direction=(0, 0, 1), i_size=lx,
                         j_size=ly)
        plotter.add_mesh(plane, color="#c8d8e8", opacity=0.25)


def _screenshot(pv, plotter, out_png) -> Path:
    out = Path(out_png)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.stem}.tmp-{os.getpid()}.png")
    try:
        plotter.camera_position = "iso"
        plotter.camera.elevation = -10
        plotter.reset_camera()
        plotter.camera.zoom(1.1)
        plotter.screenshot(str(tmp))
    finally:
        plotter.close()
    if not tmp.is_file() or tmp.stat().st_size == 0:
        tmp.unlink(missing_ok=True)
        raise RenderError(f"the renderer wrote no image for {out}")
    os.replace(tmp, out)
    return out


def _plotter(pv, window_size, background):
    """An off-screen plotter; starts Xvfb once if no context can be made otherwise."""
    try:
        p = pv.Plotter(off_screen=True, window_size=window_size)
        p.set_background(background)
        p.ren_win.Render()  # fails here when there is no GL context
        return p
    except Exception as err:  # no EGL/OSMesa/X context
        if shutil.which("Xvfb"):
            if os.environ.get("VTK_DEFAULT_OPENGL_WINDOW") == _EGL:
                del os.environ["VTK_DEFAULT_OPENGL_WINDOW"]  # an X window on the Xvfb display
            pv.start_xvfb()
            p = pv.Plotter(off_screen=True, window_size=window_size)
            p.set_background(background)
            return p
        raise RenderError(
            f"no off-screen OpenGL context ({err}); install Mesa's EGL/DRI drivers "
            "(Debian: apt-get install -y libegl-mesa0 libgl1-mesa-dri) or Xvfb "
            "(apt-get install -y xvfb)") from err


def render_particles(run_file, snapshot, out_png, *, window_size=(1200, 1000),
                     show_plates: bool = True) -> Path:
    """Render a snapshot's spheres (Fig. 1): AM coloured by diameter [um], CB grey.

    Args:
        run_file: run file path (or a ``RunRecord``), read with ``read_run``.
        snapshot: snapshot index (int) or calendering depth [m] (float, the nearest).
        out_png: PNG to write (atomically).
        window_size: image size in pixels.
        show_plates: draw the cell outline and the plates.

    Returns:
        The PNG path.
    """
    pv = _pyvista()
    record, snap = _record_and_snapshot(run_file, snapshot)
    pos = np.asarray(snap.position) * 1e6
    pos[:, 0] = np.mod(pos[:, 0], record.cell_x * 1e6)
    pos[:, 1] = np.mod(pos[:, 1], record.cell_y * 1e6)
    diam = 2e6 * np.asarray(snap.radius)
    is_cb = np.asarray(snap.material) == 1
    p = _plotter(pv, window_size, "white")
    sphere = pv.Sphere(radius=0.5, theta_resolution=20, phi_resolution=20)
    for mask, kind in ((~is_cb, "AM"), (is_cb, "CB")):
        if not mask.any():
            continue
        cloud = pv.PolyData(pos[mask])
        cloud["diameter [um]"] = diam[mask]
        glyphs = cloud.glyph(geom=sphere, scale="diameter [um]", orient=False)
        if kind == "AM":
            p.add_mesh(glyphs, scalars="diameter [um]", cmap="viridis", smooth_shading=True,
                       scalar_bar_args={"title": "AM diameter [um]", "color": "black",
                                        "vertical": True, "position_x": 0.86,
                                        "position_y": 0.2, "height": 0.6})
        else:
            p.add_mesh(glyphs, color=CB_COLOUR, smooth_shading=True)
    if show_plates:
        _box(pv, record, snap, p)
    p.add_text(f"depth {snap.depth * 1e6:.1f} um, {len(diam)} particles", font_size=10,
               color="black")
    return _screenshot(pv, p, out_png)


def _contact_pairs(pos, rad, cell_x, cell_y):
    """Touching particle pairs (i < j) under lateral periodicity (minimum image)."""
    from scipy.spatial import cKDTree

    z = pos[:, 2] - pos[:, 2].min()
    zbox = 2.0 * (z.max() + 4 * rad.max()) + 1e-12  # no wrapping in z
    x, y = np.mod(pos[:, 0], cell_x), np.mod(pos[:, 1], cell_y)
    x[x >= cell_x] = 0.0  # mod of a tiny negative number can round up to the cell length
    y[y >= cell_y] = 0.0
    pts = np.column_stack([x, y, z])
    tree = cKDTree(pts, boxsize=[cell_x, cell_y, zbox])
    pairs = tree.query_pairs(2.0 * rad.max(), output_type="ndarray")
    if len(pairs) == 0:
        return pairs.reshape(0, 2)
    d = _minimum_image(pts[pairs[:, 1]] - pts[pairs[:, 0]], cell_x, cell_y)
    touching = np.linalg.norm(d, axis=1) < rad[pairs[:, 0]] + rad[pairs[:, 1]]
    return pairs[touching]


def _minimum_image(d, cell_x, cell_y):
    d = np.array(d, dtype=float)
    d[:, 0] -= cell_x * np.round(d[:, 0] / cell_x)
    d[:, 1] -= cell_y * np.round(d[:, 1] / cell_y)
    return d


def bond_segments(record, snap) -> dict[str, np.ndarray]:
    """Segments [m] per category of :data:`BOND_COLOURS`: (k, 2, 3) end points (the second
    end is the minimum periodic image of the first's partner). Bonds whose particle was
    removed by breakage (state 3) are left out."""
    pos = np.asarray(snap.position, float)
    rad = np.asarray(snap.radius, float)
    slot = {int(i): k for k, i in enumerate(snap.id)}
    out = {name: [] for name in BOND_COLOURS}
    bonded = set()
    b = snap.bonds or {"id_a": [], "id_b": [], "state": []}
    for a, c, s in zip(b["id_a"], b["id_b"], b["state"], strict=True):
        ia, ic = slot.get(int(a)), slot.get(int(c))
        if ia is None or ic is None:
            continue
        bonded.add((min(ia, ic), max(ia, ic)))
        name = BOND_STATES.get(int(s))
        if name is not None:
            out[name].append((ia, ic))
    for i, j in _contact_pairs(pos, rad, record.cell_x, record.cell_y):
        if (min(i, j), max(i, j)) not in bonded:
            out["contact, never bonded"].append((i, j))
    seg = {}
    for name, pairs in out.items():
        pr = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
        p0 = pos[pr[:, 0]]
        p1 = p0 + _minimum_image(pos[pr[:, 1]] - p0, record.cell_x, record.cell_y)
        seg[name] = np.stack([p0, p1], axis=1)
    return seg


def render_bonds(run_file, snapshot, out_png, *, window_size=(1200, 1000),
                 show_particles: bool = False) -> Path:
    """Render the bond network of a snapshot (Fig. 6): segments between bonded or touching
    particle centres, intact bonds blue, failed red (tension) / orange (shear), touching
    pairs that never had a bond white.

    Args:
        run_file: run file path (or a ``RunRecord``).
        snapshot: snapshot index (int) or depth [m] (float, the nearest).
        out_png: PNG to write (atomically).
        window_size: image size in pixels.
        show_particles: also draw the spheres, faint.
    """
    pv = _pyvista()
    record, snap = _record_and_snapshot(run_file, snapshot)
    if snap.bonds is None:
        raise ConfigError("snapshot", snapshot, "a snapshot with bonds (the run has none)")
    seg = bond_segments(record, snap)
    p = _plotter(pv, window_size, "#2b2b2b")
    if show_particles:
        cloud = pv.PolyData(np.asarray(snap.position) * 1e6)
        cloud["d"] = 2e6 * np.asarray(snap.radius)
        p.add_mesh(cloud.glyph(geom=pv.Sphere(radius=0.5), scale="d", orient=False),
                   color="#888888", opacity=0.15)
    counts = []
    for name, s in seg.items():
        counts.append(f"{name}: {len(s)}")
        if not len(s):
            continue
        pts = s.reshape(-1, 3) * 1e6
        lines = np.column_stack([np.full(len(s), 2), np.arange(0, 2 * len(s), 2),
                                 np.arange(1, 2 * len(s), 2)]).ravel()
        p.add_mesh(pv.PolyData(pts, lines=lines), color=BOND_COLOURS[name], line_width=2,
                   label=name)
    lx, ly = record.cell_x * 1e6, record.cell_y * 1e6
    p.add_mesh(pv.Box(bounds=(0, lx, 0, ly, snap.z_bottom * 1e6, snap.z_top * 1e6))
               .outline(), color="#bbbbbb", line_width=1)
    removed = int(np.sum(np.asarray(snap.bonds["state"]) == 3))
    counts.append(f"removed with a broken particle (not drawn): {removed}")
    p.add_legend(bcolor="#2b2b2b", border=False, size=(0.32, 0.18), face="line")
    p.add_text(f"depth {snap.depth * 1e6:.1f} um\n" + "\n".join(counts), font_size=8,
               color="white")
    return _screenshot(pv, p, out_png)
