"""Particles that enter and leave a coupled run (issue 50, dem.flow with coupling.interface): hot
beads fed at the top of the gas-filled column of openfoam_cases/ergun (its inlet closed: the gas at
rest, open at the top so that the gas the particles displace can leave) fall through the gas,
heat it by convection and are removed near the bottom.

Asserted: the gas's void fraction holds exactly the particles the DEM holds (the centre method
puts each particle's volume in its cell: sum (1 - eps) V = sum of the particle volumes, to
round-off), the enthalpy the particles brought and took (E_flow_particles of coupling.csv) is the
DEM's own H_in - H_out, and the coupled energy balance closes as without inlets: balance_error is
the explicit exchange's mismatch (O(dt / tau) of the exchanged heat) and balance_residual stays at
the solver's tolerance."""
from __future__ import annotations

import math

import numpy as np
import pytest

from test_coupled import copy_case, read_csv, set_inlet_velocity
from coupling import foam_case as fc
from coupling.run import run_case
from dem.final import read as read_final

DEM = """
[simulation]
time_step = 1e-5
output_interval = 0.003
seed = 2

[domain]
min = [0.0, 0.0, 0.0]
max = [0.024, 0.024, 0.12]

[[materials]]
name = "glass"
density = 2500.0
youngs_modulus = 1e7
poisson_ratio = 0.25
restitution = 0.5
friction = 0.3
heat_capacity = 840.0
thermal_conductivity = 1.0

[[particles]]
material = "glass"
count = 20
radius = 0.001
region = { type = "box", min = [0.002, 0.002, 0.07], max = [0.022, 0.022, 0.085] }
temperature = 400.0

[[walls]]
type = "plane"
point = [0.0, 0.0, 0.0]
normal = [0.0, 0.0, 1.0]
material = "glass"

[[walls]]
type = "plane"
point = [0.0, 0.0, 0.0]
normal = [1.0, 0.0, 0.0]
material = "glass"

[[walls]]
type = "plane"
point = [0.024, 0.0, 0.0]
normal = [-1.0, 0.0, 0.0]
material = "glass"

[[walls]]
type = "plane"
point = [0.0, 0.0, 0.0]
normal = [0.0, 1.0, 0.0]
material = "glass"

[[walls]]
type = "plane"
point = [0.0, 0.024, 0.0]
normal = [0.0, -1.0, 0.0]
material = "glass"

[[inlets]]
name = "hot"
material = "glass"
radius = 0.001
rate = 3000.0
region = { type = "box", min = [0.002, 0.002, 0.09], max = [0.022, 0.022, 0.11] }
velocity = [0.0, 0.0, -1.0]
temperature = 400.0
interval = 0.003

[[outlets]]
name = "drain"
type = "box"
min = [0.0, 0.0, 0.0]
max = [0.024, 0.024, 0.06]
interval = 0.003

[thermal]
direct = "none"
convection = "ranz_marshall"
porosity = "global"
initial_temperature = 300.0

[gas]
conductivity = 0.0262
density = 1.2
viscosity = 1.8e-5
heat_capacity = 1005.0
temperature = 300.0

[output]
vtk = false
"""


@pytest.fixture(scope="module")
def fed_box(tmp_path_factory, solver):
    tmp = tmp_path_factory.mktemp("fed")
    case = copy_case("ergun", tmp / "case")
    set_inlet_velocity(case, 0.0)
    fc.set_entries(case / "system" / "controlDict", {"endTime": "0.05"})
    (case / "dem.toml").write_text(DEM)
    (case / "coupling.toml").write_text(
        '[coupling]\ntransport = "socket"\ncoupling_interval = 10\ndrag = "gidaspow_1994"\n'
        'void_fraction = "centre"\nheat = true\noutput_interval = 0.003\n')
    s = run_case(case, tmp / "out", solver=solver, quiet=True)
    return s


def test_the_gas_holds_the_particles_that_came_and_went(fed_box):
    out = fed_box["out"]
    h = read_csv(f"{out}/history.csv")
    assert h["n_in_hot"][-1] > 100 and h["n_out_drain"][-1] > 10
    fa = read_final(f"{out}/final.npz")
    vp = float(np.sum(4.0 / 3.0 * math.pi * fa["radius"] ** 3))
    V = fc.read_cell_volumes(out)
    eps = fc.read_internal_field(f"{out}/0.05/eps", len(V))
    # the last frame was sent one interval before the end, after the last event (t = 0.048 s)
    assert float(np.sum((1.0 - eps) * V)) == pytest.approx(vp, rel=1e-9)
    assert fa["id"].size == int(h["particles"][-1])


def test_coupled_energy_balance_counts_the_fed_enthalpy(fed_box):
    out = fed_box["out"]
    h = read_csv(f"{out}/history.csv")
    c = read_csv(f"{out}/coupling.csv")
    assert c["E_flow_particles"][-1] == pytest.approx(h["H_in"][-1] - h["H_out"][-1], rel=1e-9)
    moved = np.abs(c["E_flow_particles"]).max() + np.abs(c["E_conv_particles"]).max()
    assert np.abs(c["E_conv_particles"]).max() > 1e-3       # the hot beads heated the gas
    # what the bookkeeping explains: the explicit exchange's mismatch and the continuity residual
    # (the gas displaced by the particles leaves by the open top)
    # (the gas displaced by the particles leaves by the open top: E_open), the mismatch O(dt / tau)
    # of the exchanged heat (tau = gas capacity / hA: 1e-4 s against tens of ms)
    conv = np.abs(c["E_conv_particles"]).max()
    assert np.abs(c["E_continuity"]).max() <= 1e-6 * conv
    assert np.abs(c["E_exchange_mismatch"]).max() <= 0.01 * conv
    assert np.abs(c["balance_error"] - c["E_exchange_mismatch"]).max() <= 1e-6 * conv
    assert np.abs(c["balance_residual"]).max() <= 1e-6 * moved
    assert np.all(np.isfinite(c["T_gas"])) and c["T_gas"][-1] > 300.0
