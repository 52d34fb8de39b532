"""The fluid force on each particle by term in a coupled run's VTK frames (issue 51, item 4):
``fluid_drag`` beta (u_f - u_p) and ``fluid_pressure`` -V_p grad p (model A), adding up to
``fluid_force`` (coupling.diagnostics._fluid_fields_now), through `coupling run` on
benchmarks/ergun_column.py's held column (680 beads of 1 mm, 1 mm cells, the gas at 0.45 U_mf).

In a held bed the particles carry the whole pressure drop: the gas's momentum balance, eps grad p
= K (u_p - u_f) per cell, summed with the particles' -V_p grad p, gives sum_p F_p = -int grad p dV
= dp A. Of it the pressure-gradient term is the solid volume's share, sum V_p (-dp/dz), and the
drag the rest: each is asserted against the column's own pressure drop and measured packing.
"""
import math
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
for p in (ROOT, ROOT / "benchmarks"):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

import coupled_drag as cd  # noqa: E402
import ergun_column as EC  # noqa: E402

N = 680
DZ = 1e-3
END = 0.05


@pytest.fixture(scope="module")
def held_frame(tmp_path_factory, solver):
    import meshio
    work = tmp_path_factory.mktemp("fluid_terms")
    x = EC.bed(N)
    m = EC.measure(x, N)
    u = 0.45 * cd.minimum_fluidization(m["eps_core"])
    case, out = work / "case", work / "out"
    EC.write(case, x, DZ, u, "cell", False, END)
    dem = case / "dem.toml"
    dem.write_text(dem.read_text().replace("vtk = false", "vtk = true"))
    code, text, d = cd.run(case, out)
    assert code == 0, text[-3000:]
    frames = sorted((out / "vtk").glob("*.vtu")) or sorted(out.rglob("*.vtu"))
    assert frames, sorted(p.name for p in out.iterdir())
    f = meshio.read(frames[-1])
    dp, _ = EC.bed_drop(d, DZ, END - 10e-3)
    return f.point_data, dp, x, m, u


def test_the_terms_add_up_to_the_fluid_force(held_frame):
    pd, _, _, _, _ = held_frame
    assert {"fluid_force", "fluid_drag", "fluid_pressure"} <= set(pd)
    assert "fluid_lift" not in pd and "fluid_virtual_mass" not in pd   # (off in this case: not written)
    F, Fd, Fp = pd["fluid_force"], pd["fluid_drag"], pd["fluid_pressure"]
    assert F.shape == (N, 3)
    assert np.abs(F - (Fd + Fp)).max() <= 1e-12 * np.abs(F).max()


def test_held_bed_carries_the_pressure_drop_by_its_terms(held_frame):
    """sum F_z = dp A (to 2 %: the drop is read between the bottom and top cell centres, less the
    gas hydrostatics; the plate cell below the bed holds gas only). The pressure term's share of it
    is the solid's: per slab of one diameter its solid fraction 1 - eps_i times its part of the
    drop, Ergun's gradient at eps_i (the bed's measured profile, as ergun_column's reference
    takes it), so sum F_p,z / sum F_z = sum (1 - eps_i) E(eps_i) / sum E(eps_i), to 3 % (the
    cells' void fraction against the exact slab volumes, the ends' rough layers)."""
    pd, dp, x, m, u = held_frame
    area = cd.L * cd.L
    F, Fd, Fp = pd["fluid_force"], pd["fluid_drag"], pd["fluid_pressure"]
    assert dp > 0
    assert F[:, 2].sum() == pytest.approx(dp * area, rel=0.02)
    assert np.all(Fd[:, 2] > 0) and np.all(Fp[:, 2] > 0)     # the gas rises through the bed: both push up
    assert np.abs(F[:, :2]).max() < 1e-6 * np.abs(F[:, 2]).max()   # a 1-D column: no side force
    eps = np.asarray(m["eps_slabs"])
    E = cd.ergun_gradient(u, eps)
    ref = float(((1.0 - eps) * E).sum() / E.sum())
    share = Fp[:, 2].sum() / F[:, 2].sum()
    print(f"sum F_z / (dp A) = {F[:, 2].sum() / (dp * area):.4f}; pressure share {share:.4f} against {ref:.4f}")
    assert share == pytest.approx(ref, rel=0.03), (share, ref)
    assert 0.5 < share < 0.7
