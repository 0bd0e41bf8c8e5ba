"""Three porosities of a calendered coating, and what separates them.

A DEM snapshot gives the porosity three ways, which differ by amounts worth knowing
(issue 23; paper section 3.5 quotes one porosity per depth):

- **sphere sum**: ``1 - sum(V_i) / (A h)`` over the spheres' full volumes, h the plate gap.
  Volume where two spheres overlap is counted twice, and a sphere's cap pressed into a
  plate counts although it lies outside the gap: this porosity is too low.
- **voxel image**: the pore fraction of the voxelised union of the spheres between the
  plates (:func:`analysis.microstructure.voxelise`; with partial-volume voxels it converges
  fast in the voxel size). What TauFactor sees.
- **mass balance**: ``1 - M (w_AM / rho_AM + w_CB / rho_CB) / (A h)`` with the coating's
  recipe mass ``M = rho_c A h0`` (``electrode.coating_density``, ``thickness``,
  ``composition``): the porosity of a coating of the recipe's mass and incompressible
  solids at gap h, as an experiment would compute it from a thickness gauge. It differs
  from the sphere sum only by the builder's whole-particle rounding of the recipe (up to
  half a particle per material; breakage conserves each parent's volume).

The gap between the sphere sum and the voxel image is accounted for here, without voxels:
the summed lens volumes of all overlapping sphere pairs (split into AM-AM, AM-CB and CB-CB
pairs) and the caps of spheres that reach past a plate. ``sphere sum + pair overlaps +
plate caps`` is the union's porosity up to the volume where three or more spheres overlap
(counted too often by the pair sum), so its difference from a converged voxel porosity
measures those multiple overlaps plus the voxels' own error.

Lens of two spheres (radii r1, r2, centre distance d, |r1 - r2| < d < r1 + r2)::

    V = pi (r1 + r2 - d)^2 (d^2 + 2 d (r1 + r2) - 3 (r1 - r2)^2) / (12 d)

and the smaller sphere's volume when d <= |r1 - r2|; a cap of height t of a sphere of
radius r: ``pi t^2 (3 r - t) / 3``. All SI.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from calendaring import ConfigError


def lens_volume(r1, r2, d) -> np.ndarray:
    """Volume of the intersection of two spheres (radii r1, r2, centre distance d) [m^3]."""
    r1, r2, d = (np.asarray(a, dtype=float) for a in (r1, r2, d))
    out = np.zeros(np.broadcast(r1, r2, d).shape)
    inside = d <= np.abs(r1 - r2)
    rmin = np.minimum(r1, r2)
    out = np.where(inside, 4.0 / 3.0 * np.pi * rmin**3, out)
    part = (~inside) & (d < r1 + r2)
    with np.errstate(divide="ignore", invalid="ignore"):
        v = (np.pi * (r1 + r2 - d) ** 2 * (d * d + 2 * d * (r1 + r2) - 3 * (r1 - r2) ** 2)
             / (12 * d))
    return np.where(part, v, out)


def cap_volume(r, t) -> np.ndarray:
    """Volume of a spherical cap of height t (clipped to [0, 2 r]) of a sphere of radius r."""
    r = np.asarray(r, dtype=float)
    t = np.clip(np.asarray(t, dtype=float), 0.0, 2 * r)
    return np.pi * t * t * (3 * r - t) / 3.0


def overlapping_pairs(position, radius, cell_x: float, cell_y: float):
    """Index pairs (i < j) of spheres that overlap, laterally periodic, and their centre
    distances [m]."""
    from scipy.spatial import cKDTree

    pos = np.asarray(position, dtype=float).reshape(-1, 3)
    rad = np.asarray(radius, dtype=float).reshape(-1)
    if len(rad) < 2:
        return np.zeros((0, 2), np.int64), np.zeros(0)
    z = pos[:, 2] - pos[:, 2].min()
    span = float(z.max() + 4 * rad.max() + 1e-12)  # no wrap in z: a box longer than the bed
    pts = np.column_stack([np.mod(pos[:, 0], cell_x), np.mod(pos[:, 1], cell_y), z])
    pts[:, 0] = np.where(pts[:, 0] >= cell_x, 0.0, pts[:, 0])  # mod can round up to L
    pts[:, 1] = np.where(pts[:, 1] >= cell_y, 0.0, pts[:, 1])
    tree = cKDTree(pts, boxsize=[cell_x, cell_y, 2 * span])
    pairs = tree.query_pairs(2 * float(rad.max()), output_type="ndarray")
    if len(pairs) == 0:
        return np.zeros((0, 2), np.int64), np.zeros(0)
    delta = pts[pairs[:, 0]] - pts[pairs[:, 1]]
    delta[:, 0] -= cell_x * np.round(delta[:, 0] / cell_x)
    delta[:, 1] -= cell_y * np.round(delta[:, 1] / cell_y)
    d = np.linalg.norm(delta, axis=1)
    keep = d < rad[pairs[:, 0]] + rad[pairs[:, 1]]
    return pairs[keep], d[keep]


def recipe_solid_thickness(config) -> float:
    """Solid volume per unit area of the coating's recipe [m]: rho_c h0 sum_k w_k / rho_k
    (``electrode`` and ``materials`` of a :class:`calendaring.SimConfig`)."""
    el = config.electrode
    return float(el.coating_density * el.thickness
                 * sum(w / config.materials[k].density for k, w in el.composition.items()
                       if w > 0))


def porosity_budget(position, radius, material, cell_x: float, cell_y: float,
                    z_bottom: float, z_top: float, *, solid_thickness: float | None = None,
                    voxel_porosity: float | None = None, cb_index: int = 1) -> dict[str, Any]:
    """The three porosities of a snapshot and the overlap volumes that separate them.

    Args:
        position, radius, material: spheres (SI; material 0 = AM, ``cb_index`` = CB).
        cell_x, cell_y: periodic cell [m]; z_bottom, z_top: plates [m].
        solid_thickness: :func:`recipe_solid_thickness` of the run's configuration, for the
            mass-balance porosity (None: not reported).
        voxel_porosity: a (converged) voxel-image porosity to compare with.

    Returns:
        JSON-friendly dict: ``sphere_sum``, ``mass_balance``, ``voxel`` porosities;
        ``pair_overlap`` (all, ``am_am``, ``am_cb``, ``cb_cb``) and ``plate_caps`` as volume
        fractions of the gap; ``union_estimate`` = sphere sum + pair overlaps + caps;
        ``multiple_overlap_and_voxel_error`` = voxel - union estimate; counts of pairs.
    """
    gap = z_top - z_bottom
    if not gap > 0:
        raise ConfigError("z_top", z_top, f"> z_bottom = {z_bottom} m")
    pos = np.asarray(position, dtype=float).reshape(-1, 3)
    rad = np.asarray(radius, dtype=float).reshape(-1)
    mat = np.asarray(material).reshape(-1)
    volume = cell_x * cell_y * gap
    sphere = float(np.sum(4.0 / 3.0 * np.pi * rad**3))
    pairs, d = overlapping_pairs(pos, rad, cell_x, cell_y)
    lens = lens_volume(rad[pairs[:, 0]], rad[pairs[:, 1]], d) if len(d) else np.zeros(0)
    cb = mat == cb_index
    n_cb = cb[pairs[:, 0]].astype(int) + cb[pairs[:, 1]].astype(int)  # CB spheres per pair
    caps = (cap_volume(rad, z_bottom - (pos[:, 2] - rad))
            + cap_volume(rad, (pos[:, 2] + rad) - z_top))
    caps_total = float(caps.sum())
    out = {
        "sphere_sum": 1.0 - sphere / volume,
        "mass_balance": (None if solid_thickness is None
                         else 1.0 - float(solid_thickness) / gap),
        "voxel": None if voxel_porosity is None else float(voxel_porosity),
        "pair_overlap": float(lens.sum()) / volume,
        "pair_overlap_am_am": float(lens[n_cb == 0].sum()) / volume,
        "pair_overlap_am_cb": float(lens[n_cb == 1].sum()) / volume,
        "pair_overlap_cb_cb": float(lens[n_cb == 2].sum()) / volume,
        "plate_caps": caps_total / volume,
        "overlapping_pairs": len(d),
        "overlapping_pairs_am_cb": int(np.sum(n_cb == 1)),
    }
    out["union_estimate"] = out["sphere_sum"] + out["pair_overlap"] + out["plate_caps"]
    out["multiple_overlap_and_voxel_error"] = (
        None if voxel_porosity is None else float(voxel_porosity) - out["union_estimate"])
    return out
