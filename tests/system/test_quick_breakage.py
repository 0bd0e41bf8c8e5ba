"""A whole quick-preset calendering with breakage (about 3 minutes on 2 cores).

Spec T18 over a real run: the active-material volume (hence mass) of parents and fragments
is conserved to 1e-9 relative, porosity still follows the mass balance, bonds never come
back, and the energy ledger still closes with breakage in it.
"""

import numpy as np
import pytest

from calendaring.core.config import load_preset, with_overrides
from calendaring.process.run import CalenderRun
from calendaring.process.runfile import read_run

# the slow tier (bash scripts/test.sh --slow; CI runs it): a whole quick-preset run, about 2 minutes
pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    cfg = with_overrides(load_preset("quick"), {"output.checkpoint_interval": 0.0})
    out = tmp_path_factory.mktemp("quick") / "quick.h5"
    return read_run(CalenderRun(cfg, out, progress=False, preset="quick").execute())


def test_quick_run_conserves_active_material_and_follows_the_mass_balance(quick_run):
    rec = quick_run
    assert len(rec.breakage["parent_id"]) > 10  # the quick preset breaks particles
    first = rec.snapshots[0]
    h0 = rec.thickness
    vol0 = np.sum(first.radius**3)
    am0 = np.sum(first.radius[first.material == 0] ** 3)
    phi0 = first.porosity(rec.cell_x, rec.cell_y)
    for snap in rec.snapshots:
        am = np.sum(snap.radius[snap.material == 0] ** 3)
        assert abs(am / am0 - 1) < 1e-9
        assert abs(np.sum(snap.radius**3) / vol0 - 1) < 1e-9
        h = snap.z_top - snap.z_bottom
        expected = 1 - (1 - phi0) * h0 / h  # solid volume conserved: exact mass balance
        assert snap.porosity(rec.cell_x, rec.cell_y) == pytest.approx(expected, abs=1e-9)
    assert len(rec.snapshots[-1].id) > len(first.id)
    s = rec.series
    assert np.all(np.diff(s["bonds_intact"]) <= 0)  # T18: bonds are never re-created
    assert np.all(s["bonds_intact"] + s["bonds_failed_normal"] + s["bonds_failed_shear"]
                  + s["bonds_removed"] == rec.info["bonds_created"])
    assert s["bonds_removed"][-1] > 0  # bonds of broken particles go with them


def test_quick_run_energy_ledger_closes_with_breakage(quick_run):
    e = quick_run.energy
    work = e["plate_work"][-1] - e["plate_work"][0]
    assert work > 0 and e["breakage"][-1] > 0
    # everything the plates put in is kinetic, stored, dissipated or removed by breakage
    assert abs(e["total"][-1] - e["total"][0]) < 0.05 * work
