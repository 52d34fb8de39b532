"""thermoDemFoam (OpenFOAM side of the CFD-DEM coupling) driven by a tiny fake DEM peer.

The session fixture installs OpenFOAM if needed (scripts/install_openfoam.sh, needs root
on Debian 12 -- CI does it) and builds the solver (scripts/build_openfoam_solver.sh,
cached on the sha256 of the sources). Nothing is skipped.
"""
from __future__ import annotations

import os
import signal
import struct
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from coupling import foam_case as fc  # noqa: E402
from coupling.exchange import (  # noqa: E402
    CouplingError, FileExchange, SocketExchange, decode_frame, encode_frame,
)

RHO, CP, NU = 1.2, 1005.0, 1.5e-5
MU = RHO * NU


# --------------------------------------------------------------------------- fixtures

def make_case(tmp_path: Path, template: str, *, n_steps: int, dt: float,
              name: str | None = None, g=None) -> tuple[Path, np.ndarray, np.ndarray]:
    case = fc.copy_template(template, tmp_path / (name or template))
    fc.set_entries(case / "system" / "controlDict",
                   {"deltaT": dt, "endTime": repr(n_steps * dt), "writeInterval": n_steps})
    if g is not None:
        fc.set_entries(case / "constant" / "g", {"value": f"({g[0]} {g[1]} {g[2]})"})
    fc.block_mesh(case)
    return case, fc.read_cell_centres(case), fc.read_cell_volumes(case)


def zero_inputs(n):
    return dict(eps=np.ones(n), Ksl=np.zeros(n), Us=np.zeros((n, 3)),
                Simp=np.zeros(n), Sexp=np.zeros(n))


def run_coupled(case: Path, solver: Path, n_steps: int, inputs, *, transport="file",
                nprocs=1, timeout=30.0, send_velocity="cell"):
    """Fake DEM: receive step 0, then (send n, receive n) for n = 1..n_steps."""
    if transport == "file":
        fc.write_coupling_dict(case, "file", timeout=timeout, send_velocity=send_velocity)
        ex = FileExchange(case / "coupling", timeout=timeout)
    else:
        ex = SocketExchange(port=0, timeout=timeout)
        fc.write_coupling_dict(case, "socket", port=ex.port, timeout=timeout,
                               send_velocity=send_velocity)
    if nprocs > 1:
        fc.decompose(case, nprocs, method="simple")
    fc.check_case(case)
    proc = fc.start_solver(case, nprocs=nprocs, solver=solver)
    ex.peer_process = proc
    try:
        out = [ex.receive(0)]
        for s in range(1, n_steps + 1):
            ex.send(s, inputs(s, out[-1]), time_value=0.0, final=(s == n_steps))
            out.append(ex.receive(s))
        assert ex.peer_final
        rc = proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        ex.close()
    assert rc == 0, (case / "log.thermoDemFoam").read_text()[-3000:]
    return out


def layers(C: np.ndarray):
    """Cell indices grouped by z layer (blockMesh order), bottom to top."""
    z = np.round(C[:, 2], 9)
    levels = np.unique(z)
    return levels, [np.flatnonzero(z == lv) for lv in levels]


# --------------------------------------------------------------------------- protocol

def test_frame_roundtrip_and_errors(tmp_path):
    n = 7
    rng = np.random.default_rng(1)
    f = dict(eps=rng.random(n), Ksl=rng.random(n), Us=rng.random((n, 3)),
             Simp=rng.random(n), Sexp=rng.random(n))
    buf = encode_frame(1, 5, f, time_value=0.25, flags=1)
    assert len(buf) == 56 + 8 * 7 * n + 8    # header, columns, scalar count (no scalars)
    h, g = decode_frame(buf)
    assert (h["step"], h["n_cells"], h["n_fields"], h["time"], h["flags"]) == (5, n, 7, 0.25, 1)
    for k in f:
        assert np.array_equal(f[k], g[k])
    assert g["scalars"].size == 0
    # the scalars after the columns (the gas's energy ledger in CFD -> DEM frames)
    led = np.array([1.5, -2.25, 3e9])
    g2 = decode_frame(encode_frame(1, 5, dict(f, scalars=led)))[1]
    assert np.array_equal(g2["scalars"], led) and np.array_equal(g2["Sexp"], f["Sexp"])
    with pytest.raises(ValueError, match="does not match header"):
        decode_frame(encode_frame(1, 5, dict(f, scalars=led))[:-8])
    # the same bytes arrive through both transports
    a = FileExchange(tmp_path / "x", side="cfd", timeout=2)
    b = FileExchange(tmp_path / "x", side="dem", timeout=2, clean=False)
    b.send(3, f)
    got = a.receive(3)
    assert all(np.array_equal(f[k], got[k]) for k in f)
    with pytest.raises(CouplingError, match=r"peer: DEM, coupling step 4"):
        a.timeout = 0.3
        a.receive(4)
    b.send(6, f)
    with pytest.raises(CouplingError, match="received step 6, expected 7"):
        _rename_and_receive(a, tmp_path / "x", 6, 7)


def _rename_and_receive(ex, d, have, want):
    os.replace(d / f"to_cfd_{have:08d}.bin", d / f"to_cfd_{want:08d}.bin")
    return ex.receive(want)


def test_check_case_names_file(tmp_path):
    case = fc.copy_template("ergun", tmp_path / "c")
    fc.write_coupling_dict(case, "file")
    fc.check_case(case)
    (case / "constant" / "transportProperties").write_text(
        (case / "constant" / "transportProperties").read_text().replace("1.5e-05", "-1"))
    with pytest.raises(fc.CaseError, match=r"transportProperties: non-physical gas property nu"):
        fc.check_case(case)
    case = fc.copy_template("ergun", tmp_path / "d")
    fc.write_coupling_dict(case, "file")
    (case / "0" / "eps").unlink()
    with pytest.raises(fc.CaseError, match=r"0/eps: missing field"):
        fc.check_case(case)
    case = fc.copy_template("ergun", tmp_path / "e")
    fc.write_coupling_dict(case, "file")
    (case / "0" / "T").write_text((case / "0" / "T").read_text().replace("xWalls", "sideWalls"))
    with pytest.raises(fc.CaseError, match=r"0/T: missing boundary condition for patch\(es\) \['xWalls'\]"):
        fc.check_case(case)
    # turbulence: the file is required (laminar by default); RAS needs 0/nut
    case = fc.copy_template("ergun", tmp_path / "f")
    fc.write_coupling_dict(case, "file")
    turb = case / "constant" / "turbulenceProperties"
    text = turb.read_text()
    turb.unlink()
    with pytest.raises(fc.CaseError, match=r"turbulenceProperties: missing .*simulationType laminar"):
        fc.check_case(case)
    turb.write_text(text.replace("simulationType  laminar;", "simulationType  turbulent;"))
    with pytest.raises(fc.CaseError, match=r"turbulenceProperties: simulationType 'turbulent' unknown"):
        fc.check_case(case)
    turb.write_text(text.replace("simulationType  laminar;", "simulationType  RAS;"))
    with pytest.raises(fc.CaseError, match=r"0/nut: missing field 'nut'"):
        fc.check_case(case)
    tp = case / "constant" / "transportProperties"
    turb.write_text(text)
    tp.write_text(tp.read_text().replace("transportModel  Newtonian;", ""))
    with pytest.raises(fc.CaseError, match=r"transportProperties: entry 'transportModel' missing"):
        fc.check_case(case)


# --------------------------------------------------------------------------- (a) plain flow

def test_a_empty_channel_reproduces_pimpleFoam(tmp_path, solver):
    """eps = 1, Ksl = 0: thermoDemFoam == pimpleFoam (laminar), and mass is conserved."""
    n_steps, dt = 40, 1e-3
    case, C, V = make_case(tmp_path, "fluidized_bed_heating", n_steps=n_steps, dt=dt,
                           name="channel", g=(0, 0, 0))
    n = len(V)
    ref = tmp_path / "pimple"
    import shutil
    shutil.copytree(case, ref)

    out = run_coupled(case, solver, n_steps, lambda s, fl: zero_inputs(n), send_velocity="flux")

    # mass balance: superficial flux through bottom/middle/top layers = inflow
    levels, lay = layers(C)
    dz = levels[1] - levels[0]
    area = V / dz
    inflow = 2.0 * area[lay[0]].sum()  # template inlet velocity 2 m/s
    for fl in out[1:]:
        for idx in (lay[0], lay[len(lay) // 2], lay[-1]):
            q = (fl["U"][idx, 2] * area[idx]).sum()
            assert q == pytest.approx(inflow, rel=1e-7)

    # the same case with OpenFOAM's pimpleFoam (laminar)
    (ref / "constant" / "turbulenceProperties").write_text(
        "FoamFile { version 2.0; format ascii; class dictionary; object turbulenceProperties; }\n"
        "simulationType laminar;\n")
    fv = ref / "system" / "fvSchemes"
    fv.write_text(fv.read_text().replace(
        "div(phi,T)", "div((nuEff*dev2(T(grad(U))))) Gauss linear;\n    div(phi,T)"))
    fc.run_foam(["pimpleFoam"], ref, log="log.pimpleFoam")
    tname = f"{n_steps * dt:g}"
    U_ref = fc.read_internal_field(ref / tname / "U", n)
    U_our = fc.read_internal_field(case / tname / "U", n)
    p_ref = fc.read_internal_field(ref / tname / "p", n)
    p_our = fc.read_internal_field(case / tname / "p", n)
    assert np.abs(U_our - U_ref).max() < 1e-8 * 2.0
    assert np.abs(p_our - p_ref).max() < 1e-8 * np.abs(p_ref).max()
    # developing laminar flow: no-slip side walls slow the gas near them
    assert U_our[:, 2].max() > 2.0 > U_our[:, 2].min()


def _turbulence_field(cls: str, obj: str, dims: str, value: float, patches: dict) -> str:
    bcs = "\n".join(f"    {name}\n    {{\n        {bc}\n    }}" for name, bc in patches.items())
    return (
        "FoamFile { version 2.0; format ascii; class " + cls + "; location \"0\"; object "
        + obj + "; }\n"
        f"dimensions {dims};\ninternalField uniform {value!r};\nboundaryField\n{{\n{bcs}\n}}\n")


def set_k_epsilon(case: Path, k_in: float, eps_in: float) -> None:
    """Switch the fluidized_bed_heating template to RAS kEpsilon with wall functions."""
    (case / "constant" / "turbulenceProperties").write_text(
        "FoamFile { version 2.0; format ascii; class dictionary; object turbulenceProperties; }\n"
        "simulationType RAS;\nRAS\n{\n    RASModel kEpsilon;\n    turbulence on;\n"
        "    printCoeffs on;\n}\n")
    z = "zeroGradient"
    (case / "0" / "k").write_text(_turbulence_field(
        "volScalarField", "k", "[0 2 -2 0 0 0 0]", k_in, {
            "inlet": f"type fixedValue; value uniform {k_in!r};",
            "outlet": f"type inletOutlet; inletValue uniform {k_in!r}; value uniform {k_in!r};",
            "xWalls": f"type kqRWallFunction; value uniform {k_in!r};",
            "yWalls": f"type {z};"}))
    (case / "0" / "epsilon").write_text(_turbulence_field(
        "volScalarField", "epsilon", "[0 2 -3 0 0 0 0]", eps_in, {
            "inlet": f"type fixedValue; value uniform {eps_in!r};",
            "outlet": f"type inletOutlet; inletValue uniform {eps_in!r}; value uniform {eps_in!r};",
            "xWalls": f"type epsilonWallFunction; value uniform {eps_in!r};",
            "yWalls": f"type {z};"}))
    (case / "0" / "nut").write_text(_turbulence_field(
        "volScalarField", "nut", "[0 2 -1 0 0 0 0]", 0.0, {
            "inlet": "type calculated; value uniform 0;",
            "outlet": "type calculated; value uniform 0;",
            "xWalls": "type nutkWallFunction; value uniform 0;",
            "yWalls": "type calculated; value uniform 0;"}))
    fv = case / "system" / "fvSchemes"
    fv.write_text(fv.read_text().replace(
        "div(phi,T)", "div(phi,k)   Gauss limitedLinear 1;\n"
        "    div(phi,epsilon) Gauss limitedLinear 1;\n    div(phi,T)"))
    fs = case / "system" / "fvSolution"
    fs.write_text(fs.read_text().replace(
        '    "T(Final)?"',
        '    "(k|epsilon)(Final)?"\n    {\n        solver smoothSolver;\n'
        '        smoother symGaussSeidel;\n        tolerance 1e-10;\n        relTol 0;\n    }\n\n'
        '    "T(Final)?"', 1))


def test_a_empty_channel_k_epsilon(tmp_path, solver):
    """simulationType RAS (kEpsilon, wall functions): runs, nut > 0, mass is conserved."""
    n_steps, dt = 20, 1e-3
    case, C, V = make_case(tmp_path, "fluidized_bed_heating", n_steps=n_steps, dt=dt,
                           name="channel_kEpsilon", g=(0, 0, 0))
    n = len(V)
    # inlet: 5 % turbulence intensity at 2 m/s, mixing length 5 mm
    k_in = 1.5 * (0.05 * 2.0) ** 2
    eps_in = 0.09 ** 0.75 * k_in ** 1.5 / 5e-3
    set_k_epsilon(case, k_in, eps_in)

    out = run_coupled(case, solver, n_steps, lambda s, fl: zero_inputs(n), send_velocity="flux")

    log = (case / "log.thermoDemFoam").read_text()
    assert "Selecting RAS turbulence model kEpsilon" in log
    levels, lay = layers(C)
    dz = levels[1] - levels[0]
    area = V / dz
    inflow = 2.0 * area[lay[0]].sum()
    for fl in out[1:]:
        assert all(np.all(np.isfinite(a)) for a in fl.values())
        for idx in (lay[0], lay[len(lay) // 2], lay[-1]):
            q = (fl["U"][idx, 2] * area[idx]).sum()
            assert q == pytest.approx(inflow, rel=1e-7)
    tname = f"{n_steps * dt:g}"
    nut = fc.read_internal_field(case / tname / "nut", n)
    k = fc.read_internal_field(case / tname / "k", n)
    assert np.all(nut > 0) and np.all(k > 0)
    assert nut.max() > NU          # the eddy viscosity matters: nuEff = nu + nut
    U = fc.read_internal_field(case / tname / "U", n)
    assert U[:, 2].max() > 2.0 > U[:, 2].min()


# --------------------------------------------------------------------------- (b) Ergun

def ergun_ksl(eps, d, u_sup):
    """Model-A drag coefficient from Ergun: Ksl = eps^2 (dp/L) / U_sup  [kg/(m^3 s)]."""
    return 150 * MU * (1 - eps) ** 2 / (eps * d ** 2) + 1.75 * RHO * (1 - eps) * abs(u_sup) / (eps * d)


def test_b_packed_bed_pressure_drop(tmp_path, solver):
    """Bed (eps 0.4, Ergun Ksl) resting on the inlet, sharp top, freeboard above."""
    n_steps, dt = 300, 1e-4
    case, C, V = make_case(tmp_path, "ergun", n_steps=n_steps, dt=dt)
    n = len(V)
    u_sup, d, e_bed, h_bed = 0.5, 2e-3, 0.4, 0.06
    in_bed = C[:, 2] < h_bed
    eps = np.where(in_bed, e_bed, 1.0)
    ksl = np.where(in_bed, ergun_ksl(e_bed, d, u_sup), 0.0)
    fc.write_eps(case, eps)

    def inputs(s, fl):
        x = zero_inputs(n)
        x["eps"], x["Ksl"] = eps, ksl
        return x

    fl = run_coupled(case, solver, n_steps, inputs)[-1]
    levels, lay = layers(C)
    dz = levels[1] - levels[0]
    mean = lambda a: np.array([a[idx].mean() for idx in lay])  # noqa: E731
    p, uz, k, e = mean(fl["p"]), mean(fl["U"][:, 2]), mean(ksl), mean(eps)
    # pressure drop from the bottom cell centre to the top cell, minus hydrostatics
    dp = p[0] - p[-1] - RHO * 9.81 * (levels[-1] - levels[0])
    # integral of the drag Ksl U / eps (model A) over the same span (midpoint rule)
    w = np.full(len(lay), dz)
    w[0] = w[-1] = 0.5 * dz
    integral = (k * uz / e * w).sum()
    assert dp == pytest.approx(integral, rel=0.01)
    # Ergun over the bed below the bottom cell centre ... bed top
    l_bed = h_bed - levels[0]
    ergun_grad = (150 * MU * (1 - e_bed) ** 2 * u_sup / (e_bed ** 3 * d ** 2)
                  + 1.75 * RHO * (1 - e_bed) * u_sup ** 2 / (e_bed ** 3 * d))
    assert dp == pytest.approx(ergun_grad * l_bed, rel=0.05)
    # inside the bed: interstitial velocity and returned gradient [Pa/m] match Ergun
    mid = [i for i, z in enumerate(levels) if 0.015 < z < 0.04]
    assert uz[mid] == pytest.approx(u_sup / e_bed, rel=1e-3)
    gz = mean(fl["gradp"][:, 2])[mid]
    assert gz == pytest.approx(-ergun_grad - RHO * 9.81, rel=0.005)


# Porosity jumps: void fraction per 6 mm layer of the ergun template (20 layers, 1 above)
JUMP_PROFILES = {
    "sharp": {i: 0.4 for i in range(10)},                                    # bed top on a cell face
    "graded": {0: 0.55, **{i: 0.4 for i in range(1, 8)}, 8: 0.6, 9: 0.85},   # loose floor, rough top
}


@pytest.mark.parametrize("profile", sorted(JUMP_PROFILES))
@pytest.mark.parametrize("regime", ["drag", "inertia", "drag, model B"])
def test_b_porosity_jumps(tmp_path, solver, profile, regime):
    """A bed of 2 mm beads held still, Ksl from Ergun per layer, whose void fraction jumps at
    its top and its floor: the gas solver adds no loss at the jumps (dragFaces.H). The exact
    answer of the volume-averaged equations for this layered column is the series integral of
    Ksl u_s/eps^2 over the layers, with u_s the superficial inlet velocity everywhere.

    regime "drag": u_s 0.05 m/s, CFD step 1 ms (the drag's relaxation K dt = 0.57); "inertia":
    u_s 0.5 m/s, 0.1 ms (K dt = 0.12, Re_p 67), where the momentum of the bed's interstitial
    jets, rho u_s^2 (1/eps - 1) = 0.45 Pa = 0.2 % of the drop, enters and leaves at the bed's
    ends: the tolerances there; "drag, model B": the first with Zhou et al.'s model B (epsP = 1,
    the DEM's Ksl carrying 1/eps). Before the face treatment: -4.7 / -5.2 % and -3.6 / -3.3 % of
    the drop lost, the top bed cell's gas at 0.54 / 0.62 of u_s/eps."""
    u_sup, dt, n_steps, tol_dp, tol_u = {"drag": (0.05, 1e-3, 100, 0.002, 0.015),
                                         "inertia": (0.5, 1e-4, 300, 0.005, 0.05),
                                         "drag, model B": (0.05, 1e-3, 100, 0.002, 0.015)}[regime]
    model_b = regime.endswith("model B")
    case, C, V = make_case(tmp_path, "ergun", n_steps=n_steps, dt=dt)
    if model_b:   # epsP = 1; the DEM's Ksl carries the 1/eps of model B: the same bed
        cp = case / "constant" / "couplingProperties"
        import re
        text = cp.read_text()
        assert re.search(r"modelType\s+A;", text)
        cp.write_text(re.sub(r"modelType\s+A;", "modelType B;", text))
    n = len(V)
    levels, lay = layers(C)
    d = 2e-3
    e_l = np.array([JUMP_PROFILES[profile].get(i, 1.0) for i in range(len(levels))])
    k_l = np.where(e_l < 1, ergun_ksl(e_l, d, u_sup), 0.0)
    if model_b:
        k_l = k_l / e_l
    eps, ksl = np.ones(n), np.zeros(n)
    for i, idx in enumerate(lay):
        eps[idx], ksl[idx] = e_l[i], k_l[i]
    fc.write_eps(case, eps)
    uf = case / "0" / "U"
    uf.write_text(uf.read_text().replace("uniform (0 0 0.5)", f"uniform (0 0 {u_sup!r})"))

    def inputs(s, fl):
        x = zero_inputs(n)
        x["eps"], x["Ksl"] = eps, ksl
        return x

    fl = run_coupled(case, solver, n_steps, inputs)[-1]
    mean = lambda a: np.array([a[idx].mean() for idx in lay])  # noqa: E731
    p, uz, gz = mean(fl["p"]), mean(fl["U"][:, 2]), mean(fl["gradp"][:, 2])
    dz = levels[1] - levels[0]
    G = k_l * u_sup / e_l ** (1 if model_b else 2)  # the drag's pressure gradient per layer (Pa/m)
    w = np.full(len(lay), dz)
    w[0] = w[-1] = 0.5 * dz                         # cell centre of the bottom layer .. of the top one
    exact = (G * w).sum()
    dp = p[0] - p[-1] - RHO * 9.81 * (levels[-1] - levels[0])
    assert dp == pytest.approx(exact, rel=tol_dp)
    # the gas velocity of every cell of the bed, the top one and the floor included, is the
    # superficial velocity over its void fraction; in the dense cells (eps <= 0.6) the pressure
    # gradient sent to the particles is the drag's
    bed = e_l < 1
    dense = e_l <= 0.6
    ratio = uz * e_l / u_sup
    assert np.abs(ratio[dense] - 1).max() < tol_u, ratio[bed]
    assert np.abs(ratio[bed] - 1).max() < 0.16, ratio[bed]   # incl. the eps 0.85 cell under the jets
    grad_ratio = (-gz - RHO * 9.81)[dense] / G[dense]
    assert np.abs(grad_ratio - 1).max() < 2 * tol_u, grad_ratio


# --------------------------------------------------------------------------- (f) wall heat

def _patch_values(path: Path, patch: str) -> np.ndarray:
    """The boundary values of ``patch`` in an ASCII volScalarField file."""
    import re
    text = path.read_text()
    block = text[text.index(patch, text.index("boundaryField")):]
    block = block[:block.index("}")]
    m = re.search(r"value\s+nonuniform\s+List<scalar>\s*(\d+)\s*\(([^)]*)\)", block)
    if m:
        return np.array(m.group(2).split(), float)
    m = re.search(r"value\s+uniform\s+([-+0-9.eE]+)", block)
    return np.array([float(m.group(1))])


def test_f_wall_heat_flux_field(tmp_path, solver):
    """Gas at rest (void fraction 0.5) between two walls at 400 K and 300 K 60 mm apart: steady
    conduction. The wallHeatFlux field written with the time folder is eps k dT/L on every face
    of both walls, into the gas at the hot one and out of it at the cold one (issue 14: the gas
    path of a wall's heat), and zero on the other patches."""
    n_steps, dt = 60, 5.0      # 300 s: 18 times the slowest decay time L^2/(pi^2 alpha) = 16.8 s
    case, C, V = make_case(tmp_path, "fluidized_bed_heating", n_steps=n_steps, dt=dt, name="walls",
                           g=(0, 0, 0))
    n = len(V)
    uf = case / "0" / "U"
    uf.write_text(uf.read_text().replace("uniform (0 0 2.0)", "uniform (0 0 0)"))
    tf = case / "0" / "T"
    hot_cold = " ".join(["400"] * 60 + ["300"] * 60)   # xWalls: the x = 0 faces (2 x 30), then x = L
    text = tf.read_text().replace(
        "xWalls\n    {\n        type zeroGradient;\n    }",
        f"xWalls\n    {{\n        type fixedValue;\n        value nonuniform List<scalar> 120({hot_cold});\n    }}")
    # no heat through the inlet either: a 1-D conduction problem across x
    text = text.replace("inlet\n    {\n        type fixedValue;\n        value uniform 373.15;\n    }",
                        "inlet\n    {\n        type zeroGradient;\n    }")
    assert "120(" in text and "373.15;\n    }\n    outlet" not in text
    tf.write_text(text)
    eps = np.full(n, 0.5)
    fc.write_eps(case, eps)

    def inputs(s, fl):
        x = zero_inputs(n)
        x["eps"] = eps
        return x

    fl = run_coupled(case, solver, n_steps, inputs)[-1]
    k, L = 0.0262, 0.06
    q = _patch_values(case / f"{n_steps * dt:g}" / "wallHeatFlux", "xWalls")
    assert q.shape == (120,)
    assert q[:60] == pytest.approx(np.full(60, 0.5 * k * 100.0 / L), rel=1e-4)
    assert q[60:] == pytest.approx(np.full(60, -0.5 * k * 100.0 / L), rel=1e-4)
    for patch in ("inlet", "outlet", "yWalls"):
        assert np.all(_patch_values(case / f"{n_steps * dt:g}" / "wallHeatFlux", patch) == 0.0)
    # the gas's temperature is the linear profile between the walls
    x = C[:, 0]
    assert fl["T"] == pytest.approx(400.0 - 100.0 * x / L, rel=1e-5)
    log = (case / "log.thermoDemFoam").read_text()
    assert "Wall heat into the gas, patch xWalls" in log


# --------------------------------------------------------------------------- (c) transports

def _bed_inputs(C, n):
    rng = np.random.default_rng(7)
    in_bed = C[:, 2] < 0.06
    eps = np.where(in_bed, 0.4 + 0.05 * rng.random(n), 1.0)
    ksl = np.where(in_bed, 1500.0 * (1 + 0.1 * rng.random(n)), 0.0)
    us = np.where(in_bed[:, None], 0.01 * rng.standard_normal((n, 3)), 0.0)
    simp = np.where(in_bed, 2e4, 0.0)

    def inputs(s, fl):
        return dict(eps=eps, Ksl=ksl, Us=us, Simp=simp, Sexp=simp * (350.0 + s))
    return eps, inputs


def test_c_file_and_socket_bit_identical(tmp_path, solver):
    n_steps, dt = 20, 1e-4
    results = {}
    for transport in ("file", "socket"):
        case, C, V = make_case(tmp_path, "ergun", n_steps=n_steps, dt=dt, name=transport)
        eps, inputs = _bed_inputs(C, len(V))
        fc.write_eps(case, eps)
        results[transport] = run_coupled(case, solver, n_steps, inputs, transport=transport)
    for a, b in zip(results["file"], results["socket"]):
        for k in a:
            assert np.array_equal(a[k].view(np.uint64), b[k].view(np.uint64)), k
    assert results["file"][-1]["T"].max() > 300.0


def test_parallel_matches_serial(tmp_path, solver):
    """mpirun -np 2 (simple decomposition, file transport) agrees with the serial run."""
    n_steps, dt = 20, 1e-4
    res = {}
    for nprocs in (1, 2):
        case, C, V = make_case(tmp_path, "ergun", n_steps=n_steps, dt=dt, name=f"np{nprocs}")
        eps, inputs = _bed_inputs(C, len(V))
        fc.write_eps(case, eps)
        res[nprocs] = run_coupled(case, solver, n_steps, inputs, nprocs=nprocs)[-1]
    # linear solvers (DIC/DILU preconditioning) differ in parallel; the bounded T
    # convection scheme's limiter amplifies that locally where T is nearly uniform
    for k in ("U", "gradp", "p"):
        scale = np.abs(res[1][k]).max()
        assert np.abs(res[1][k] - res[2][k]).max() <= 1e-5 * scale, k
    heating = np.abs(res[1]["T"] - 300.0).max()
    assert heating > 1.0
    assert np.abs(res[1]["T"] - res[2]["T"]).max() <= 2e-3 * heating


# --------------------------------------------------------------------------- (d) peer death

FAKE_DEM = textwrap.dedent("""
    import sys, time, numpy as np
    sys.path.insert(0, {root!r})
    from coupling.exchange import FileExchange, SocketExchange
    transport, where, n = sys.argv[1], sys.argv[2], int(sys.argv[3])
    ex = FileExchange(where, timeout=30) if transport == "file" else SocketExchange(port=int(where), timeout=30)
    ex.receive(0)
    for s in (1, 2, 3):
        ex.send(s, dict(eps=np.ones(n), Ksl=np.zeros(n), Us=np.zeros((n, 3)),
                        Simp=np.zeros(n), Sexp=np.zeros(n)))
        ex.receive(s)
    print("ready", flush=True)
    time.sleep(600)
""")


@pytest.mark.parametrize("transport", ["file", "socket"])
def test_d_dem_peer_killed(tmp_path, solver, transport):
    timeout = 5.0
    case, C, V = make_case(tmp_path, "ergun", n_steps=50, dt=1e-4)
    n = len(V)
    script = tmp_path / "fake_dem.py"
    script.write_text(FAKE_DEM.format(root=str(ROOT)))
    if transport == "file":
        fc.write_coupling_dict(case, "file", timeout=timeout)
        where = str(case / "coupling")
    else:
        import socket
        s = socket.socket()
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
        s.close()
        fc.write_coupling_dict(case, "socket", port=port, timeout=timeout)
        where = str(port)
    dem = subprocess.Popen([sys.executable, str(script), transport, where, str(n)],
                           stdout=subprocess.PIPE, text=True)
    time.sleep(0.3 if transport == "socket" else 0.0)
    cfd = fc.start_solver(case, solver=solver)
    try:
        assert dem.stdout.readline().strip() == "ready"
        dem.send_signal(signal.SIGKILL)
        dem.wait()
        t0 = time.monotonic()
        rc = cfd.wait(timeout=timeout + 10)
        elapsed = time.monotonic() - t0
    finally:
        for p in (dem, cfd):
            if p.poll() is None:
                p.kill()
                p.wait()
    log = (case / "log.thermoDemFoam").read_text()
    assert rc != 0
    assert elapsed < timeout + 2
    assert "peer: DEM, coupling step 4" in log, log[-2000:]


def test_d_solver_killed_dem_gets_error(tmp_path, solver):
    case, C, V = make_case(tmp_path, "ergun", n_steps=50, dt=1e-4)
    fc.write_coupling_dict(case, "file", timeout=20)
    ex = FileExchange(case / "coupling", timeout=20)
    proc = fc.start_solver(case, solver=solver)
    ex.peer_process = proc
    ex.receive(0)
    proc.kill()
    proc.wait()
    ex.send(1, zero_inputs(len(V)))
    t0 = time.monotonic()
    with pytest.raises(CouplingError, match=r"CFD solver.*peer: CFD solver, coupling step 1"):
        ex.receive(1)
    assert time.monotonic() - t0 < 2


# --------------------------------------------------------------------------- (e) energy

def test_e_energy_balance(tmp_path, solver):
    """Gas heated by a bed of particles held at Tp: steady enthalpy rise = exchanged heat."""
    n_steps, dt = 800, 1e-3
    case, C, V = make_case(tmp_path, "ergun", n_steps=n_steps, dt=dt, name="energy")
    n = len(V)
    u_sup, d, e_bed, Tp, T_in, h = 0.5, 2e-3, 0.4, 400.0, 300.0, 10.0
    in_bed = (C[:, 2] > 0.03) & (C[:, 2] < 0.09)
    eps = np.where(in_bed, e_bed, 1.0)
    ksl = np.where(in_bed, ergun_ksl(e_bed, d, u_sup), 0.0)
    simp = np.where(in_bed, h * 6 * (1 - e_bed) / d, 0.0)  # h a  [W/(m^3 K)]
    sexp = simp * Tp
    fc.write_eps(case, eps)

    def inputs(s, fl):
        return dict(eps=eps, Ksl=ksl, Us=np.zeros((n, 3)), Simp=simp, Sexp=sexp)

    out = run_coupled(case, solver, n_steps, inputs, send_velocity="flux")
    fl = out[-1]
    levels, lay = layers(C)
    dz = levels[1] - levels[0]
    area = V / dz
    T = fl["T"]
    # enthalpy flow out (top layer, eps = 1, outflow face T = cell T) minus in
    q_out = RHO * CP * (fl["U"][lay[-1], 2] * area[lay[-1]] * T[lay[-1]]).sum()
    q_in = RHO * CP * u_sup * area[lay[0]].sum() * T_in
    q_exch = ((sexp - simp * T) * V).sum()
    assert q_exch > 0
    assert q_out - q_in == pytest.approx(q_exch, rel=0.01)
    # the gas heats towards Tp along the bed; plug-flow estimate of the outlet temperature
    t_lay = np.array([T[idx].mean() for idx in lay])
    assert np.all(np.diff(t_lay) >= -1e-6)
    assert T_in < t_lay[-1] < Tp
    ntu = h * 6 * (1 - e_bed) / d * (in_bed.sum() / len(lay[0]) * dz) / (RHO * CP * u_sup)
    assert t_lay[-1] == pytest.approx(Tp - (Tp - T_in) * np.exp(-ntu), rel=0.02)
    # steady: the last steps no longer change T
    assert np.abs(out[-1]["T"] - out[-50]["T"]).max() < 1e-3


# --------------------------------------------------------------------------- (g) m2m transport

def _recv_exact(sock, n: int) -> bytes:
    buf = bytearray()
    while len(buf) < n:
        chunk = sock.recv(n - len(buf))
        if not chunk:
            raise ConnectionError("the gas processor closed the connection")
        buf += chunk
    return bytes(buf)


class FakeDemRanks:
    """DEM ranks of the m2m transport (docs/coupling_protocol.md), faked in this process: one
    listening TCP socket per rank, each served by its own thread (the ranks run concurrently,
    like separate processes). ``owner``: the DEM rank of each global cell; ``addr``: each gas
    processor's cellProcAddressing (one identity for a serial run). The pairs' cells go in a
    shuffled order (``pairs[(g, r)]``, local cell ids; a test may edit them before
    :meth:`write_plan`). ``kill``: {rank: step}: that rank closes its connections, as a dying
    process does, instead of sending the frame of that step. ``pause``: {rank: (step, event)}:
    that rank sets ``self.paused`` and waits for the event before it sends the frame of that
    step. A rank stops after the solver's FINAL frame (which all its pairs must agree on)."""

    def __init__(self, plan_dir: Path, owner: np.ndarray, addr: list[np.ndarray], *,
                 timeout: float = 20.0, kill: dict | None = None, pause: dict | None = None):
        import socket
        import threading
        self.plan_dir = Path(plan_dir)
        self.addr = addr
        self.timeout = timeout
        self.kill = kill or {}
        self.pause = pause or {}
        self.paused = threading.Event()
        self.n_ranks = int(owner.max()) + 1
        rng = np.random.default_rng(11)
        self.pairs: dict[tuple[int, int], np.ndarray] = {}
        for g, a in enumerate(addr):
            for r in range(self.n_ranks):
                ids = np.flatnonzero(owner[a] == r)
                if ids.size:
                    self.pairs[(g, r)] = rng.permutation(ids)
        self.listeners = [socket.create_server(("127.0.0.1", 0)) for _ in range(self.n_ranks)]
        self.received: dict[tuple[int, int], list] = {}     # (g, r) -> [(header, fields)] per step
        self.errors: dict[int, BaseException] = {}
        self.threads = []

    def write_plan(self) -> None:
        for (g, r), ids in self.pairs.items():
            d = self.plan_dir / f"gas{g}"
            d.mkdir(parents=True, exist_ok=True)
            port = self.listeners[r].getsockname()[1]
            (d / f"dem{r}").write_text(f"127.0.0.1 {port} {ids.size}\n")
        (self.plan_dir / "ready").write_text(f"{self.n_ranks}\n")

    def start(self, n_steps: int, inputs) -> None:
        import threading
        for r in range(self.n_ranks):
            t = threading.Thread(target=self._run, args=(r, n_steps, inputs), daemon=True)
            t.start()
            self.threads.append(t)

    def join(self) -> None:
        for t in self.threads:
            t.join(timeout=self.timeout + 30)
            assert not t.is_alive()
        for lst in self.listeners:
            lst.close()

    def _run(self, r, n_steps, inputs):
        conns = {}
        try:
            self._serve(r, n_steps, inputs, conns)
        except BaseException as e:  # noqa: BLE001 - reported by the test
            self.errors[r] = e
        finally:
            for c in conns.values():
                c.close()

    def _serve(self, r, n_steps, inputs, conns):
        import socket
        mine = sorted(g for (g, rr) in self.pairs if rr == r)
        lst = self.listeners[r]
        lst.settimeout(self.timeout)
        while len(conns) < len(mine):                       # set-up: hello, reply
            c, _ = lst.accept()
            c.settimeout(self.timeout)
            c.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            magic, g, n_cells = struct.unpack("<8sqq", _recv_exact(c, 24))
            assert magic == b"TDEMHELO" and g in mine and n_cells == len(self.addr[g]), (magic, g)
            ids = self.pairs[(g, r)]
            body = struct.pack("<qq", r, ids.size) + ids.astype("<i8").tobytes()
            c.sendall(struct.pack("<Q", len(body)) + body)
            conns[g] = c
            self.received[(g, r)] = []

        def receive(step):
            for g in mine:
                (n,) = struct.unpack("<Q", _recv_exact(conns[g], 8))
                h, f = decode_frame(_recv_exact(conns[g], n))
                assert (h["kind"], h["step"], h["n_cells"]) == (2, step, self.pairs[(g, r)].size), h
                self.received[(g, r)].append((h, f))

        def solver_final(step):
            flags = {self.received[(g, r)][-1][0]["flags"] for g in mine}
            assert len(flags) == 1, (step, flags)   # every gas processor sends the same flags
            return bool(flags.pop() & 1)

        receive(0)
        for s in range(1, n_steps + 1):
            if self.kill.get(r) == s:
                return
            if r in self.pause and self.pause[r][0] == s:
                self.paused.set()
                self._hold(self.pause[r][1], conns)
            glob = inputs(s, None)
            for g in mine:
                cells = self.addr[g][self.pairs[(g, r)]]
                sub = {k: np.asarray(v)[cells] for k, v in glob.items()}
                buf = encode_frame(1, s, sub, time_value=0.0, flags=int(s == n_steps))
                conns[g].sendall(struct.pack("<Q", len(buf)) + buf)
            receive(s)
            if solver_final(s):
                return

    def _hold(self, event, conns):
        """Wait for ``event``, or until a gas processor closes its connection (it died)."""
        import select
        import socket
        t0 = time.monotonic()
        while not event.wait(0.02):
            ready, _, _ = select.select(list(conns.values()), [], [], 0)
            for c in ready:
                if not c.recv(1, socket.MSG_PEEK):
                    raise ConnectionError("a gas processor closed the connection")
            assert time.monotonic() - t0 < self.timeout + 20, "held too long"

    def assemble(self, n_global: int) -> list[dict]:
        """The frames the ranks received, per step, in global cell order (as one frame of the
        file or socket transport would carry them)."""
        n_steps = len(next(iter(self.received.values())))
        out = []
        for s in range(n_steps):
            fl: dict = {}
            for (g, r), frames in self.received.items():
                h, f = frames[s]
                cells = self.addr[g][self.pairs[(g, r)]]
                for k, v in f.items():
                    if k == "scalars":
                        if "scalars" in fl:      # the global ledger, the same in every pair
                            assert np.array_equal(fl[k].view(np.uint64), v.view(np.uint64))
                        fl[k] = v
                        continue
                    if k not in fl:
                        fl[k] = np.full((n_global,) + v.shape[1:], np.nan)
                    fl[k][cells] = v
                fl.setdefault("flags", set()).add(h["flags"])
            out.append(fl)
        return out


def run_m2m(case: Path, solver: Path, n_steps: int, inputs, owner, *, nprocs=1, timeout=20.0,
            plan_dir: str = "m2m", edit_pairs=None, kill=None, pause=None, during=None,
            expect_rc0=True):
    """Fake DEM of several ranks (FakeDemRanks) around thermoDemFoam with the m2m transport.
    ``plan_dir``: relative to the case (as written into the couplingDict) or absolute;
    ``during(proc, fake)``: called once the ranks run."""
    fc.write_coupling_dict(case, "m2m", timeout=timeout, m2m_directory=plan_dir)
    if nprocs > 1:
        fc.decompose(case, nprocs, method="simple")
        addr = fc.cell_proc_addressing(case)
    else:
        addr = [np.arange(len(owner))]
    fc.check_case(case)
    pd = Path(plan_dir) if os.path.isabs(plan_dir) else case / plan_dir
    fake = FakeDemRanks(pd, owner, addr, timeout=timeout, kill=kill, pause=pause)
    if edit_pairs:
        edit_pairs(fake.pairs)
    fake.write_plan()
    proc = fc.start_solver(case, nprocs=nprocs, solver=solver)
    t0 = time.monotonic()
    try:
        fake.start(n_steps, inputs)
        if during:
            during(proc, fake)
        if kill:
            fake.threads[min(kill)].join(timeout=timeout + 30)   # the killed rank is gone
            t0 = time.monotonic()
        rc = proc.wait(timeout=timeout + 60)
        fake.t_end = time.monotonic()
        elapsed = fake.t_end - t0
        fake.join()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        for lst in fake.listeners:
            lst.close()
    log = (case / "log.thermoDemFoam").read_text()
    if expect_rc0:
        assert rc == 0, log[-3000:]
        assert not fake.errors, fake.errors
    return fake, addr, rc, elapsed, log


def _assert_frames_identical(ref: list[dict], got: list[dict]):
    assert len(ref) == len(got)
    for s, (a, b) in enumerate(zip(ref, got)):
        for k in ("U", "T", "gradp", "p", "scalars"):
            assert a[k].shape == b[k].shape, (s, k)
            assert np.array_equal(a[k].view(np.uint64), b[k].view(np.uint64)), (s, k)
    assert got[-1]["flags"] == {1} and all(fl["flags"] == {0} for fl in got[:-1])


def test_m2m_parallel_bit_identical_to_file(tmp_path, solver):
    """2 gas processors (simple decomposition in z), 2 fake DEM ranks owning the x halves:
    every processor exchanges with both ranks; the frames the ranks receive, put together in
    global cell order, are bitwise those of the file transport on the same decomposition."""
    n_steps, dt = 8, 1e-4
    res = {}
    for transport in ("file", "m2m"):
        case, C, V = make_case(tmp_path, "ergun", n_steps=n_steps, dt=dt, name=transport)
        eps, inputs = _bed_inputs(C, len(V))
        fc.write_eps(case, eps)
        if transport == "file":
            res[transport] = run_coupled(case, solver, n_steps, inputs, nprocs=2, timeout=20)
            continue
        owner = (C[:, 0] > 0.5 * (C[:, 0].min() + C[:, 0].max())).astype(int)
        fake, addr, rc, _, log = run_m2m(case, solver, n_steps, inputs, owner, nprocs=2,
                                         plan_dir=str(tmp_path / "plan"))
        assert {(g, r) for g, r in fake.pairs} == {(0, 0), (0, 1), (1, 0), (1, 1)}
        assert "m2m exchange of gas processor 1" in log
        res[transport] = fake.assemble(len(V))
    _assert_frames_identical(res["file"], res["m2m"])
    assert res["file"][-1]["T"].max() > 300.0


def test_m2m_serial_bit_identical_to_socket(tmp_path, solver):
    """Serial gas (processor 0), 2 fake DEM ranks owning the cells below / above mid-height;
    plan folder relative to the case: bitwise the socket transport's frames."""
    n_steps, dt = 8, 1e-4
    res = {}
    for transport in ("socket", "m2m"):
        case, C, V = make_case(tmp_path, "ergun", n_steps=n_steps, dt=dt, name=transport)
        eps, inputs = _bed_inputs(C, len(V))
        fc.write_eps(case, eps)
        if transport == "socket":
            res[transport] = run_coupled(case, solver, n_steps, inputs, transport="socket",
                                         timeout=20)
            continue
        owner = (C[:, 2] > 0.5 * (C[:, 2].min() + C[:, 2].max())).astype(int)
        fake, addr, rc, _, log = run_m2m(case, solver, n_steps, inputs, owner, plan_dir="m2m")
        assert set(fake.pairs) == {(0, 0), (0, 1)}
        res[transport] = fake.assemble(len(V))
    _assert_frames_identical(res["socket"], res["m2m"])


@pytest.mark.parametrize("fault", ["uncovered", "twice"])
def test_m2m_plan_must_cover_each_cell_once(tmp_path, solver, fault):
    """A plan whose pairs leave a local cell of gas processor 1 uncovered, or cover one twice:
    the solver refuses it at the set-up (non-zero exit) naming the local and global cell."""
    case, C, V = make_case(tmp_path, "ergun", n_steps=5, dt=1e-4)
    owner = (C[:, 0] > 0.5 * (C[:, 0].min() + C[:, 0].max())).astype(int)
    picked = {}

    def edit(pairs):
        ids0 = pairs[(1, 0)]
        picked["cell"] = int(ids0[3])
        if fault == "uncovered":
            pairs[(1, 0)] = np.delete(ids0, 3)
        else:
            pairs[(1, 1)] = np.append(pairs[(1, 1)], ids0[3])

    fake, addr, rc, _, log = run_m2m(case, solver, 5, _bed_inputs(C, len(V))[1], owner, nprocs=2,
                                     timeout=10, edit_pairs=edit, expect_rc0=False)
    assert rc != 0
    c = picked["cell"]
    what = (f"local cell {c} (global cell {addr[1][c]}) of gas processor 1 is "
            + ("covered by none of its DEM ranks (0 1)" if fault == "uncovered"
               else "covered 2 times, by DEM ranks 0 and 1"))
    assert what in log, log[-3000:]


@pytest.mark.parametrize("fault", ["killed", "hung"])
def test_m2m_dem_rank_killed(tmp_path, solver, fault):
    """DEM rank 1, partner of gas processor 1 only, dies at step 4 (or hangs there, sending
    nothing): processor 1 stops with a fatal error naming it, and the MPI job (processor 0 too)
    ends non-zero at once (within the timeout when the rank hangs)."""
    import threading
    timeout = 3.0
    case, C, V = make_case(tmp_path, "ergun", n_steps=50, dt=1e-4)
    eps, inputs = _bed_inputs(C, len(V))
    fc.write_eps(case, eps)
    zmax, xmid = C[:, 2].max(), 0.5 * (C[:, 0].min() + C[:, 0].max())
    owner = ((C[:, 2] > 0.75 * zmax) & (C[:, 0] > xmid)).astype(int)
    t_fault = []

    def during(proc, fake):
        assert fake.paused.wait(30)
        t_fault.append(time.monotonic())

    fault_args = (dict(kill={1: 4}) if fault == "killed"
                  else dict(pause={1: (4, threading.Event())}, during=during))
    fake, addr, rc, elapsed, log = run_m2m(case, solver, 50, inputs, owner, nprocs=2,
                                           timeout=timeout, expect_rc0=False, **fault_args)
    assert set(fake.pairs) == {(0, 0), (1, 0), (1, 1)}
    assert rc != 0
    assert "[peer: DEM rank 1, coupling step 4]" in log, log[-3000:]
    if fault == "killed":
        assert elapsed < 2
        assert "DEM rank 1 closed the connection" in log, log[-3000:]
    else:
        waited = fake.t_end - t_fault[0]
        assert timeout - 0.5 < waited < timeout + 2
        assert "timeout (3 s) waiting for the frame of DEM rank 1" in log, log[-3000:]


def _mpi_rank_pid(mpirun_pid: int, rank: int) -> int:
    """The pid of MPI rank ``rank`` among mpirun's children."""
    for _ in range(100):
        kids = Path(f"/proc/{mpirun_pid}/task/{mpirun_pid}/children").read_text().split()
        for k in kids:
            try:
                env = Path(f"/proc/{k}/environ").read_bytes().split(b"\0")
            except OSError:
                continue
            if f"OMPI_COMM_WORLD_RANK={rank}".encode() in env:
                return int(k)
        time.sleep(0.1)
    raise AssertionError(f"no MPI rank {rank} under mpirun {mpirun_pid}")


def test_m2m_stop_signal(tmp_path, solver):
    """SIGTERM to gas processor 1 alone while it waits for step 3's frames: every processor
    finishes step 3, writes it and sends each of its DEM ranks FINAL with the signal in flag
    bits 8-15; the solver exits 0."""
    import threading
    dt = 1e-4
    case, C, V = make_case(tmp_path, "ergun", n_steps=50, dt=dt)
    eps, inputs = _bed_inputs(C, len(V))
    fc.write_eps(case, eps)
    owner = (C[:, 0] > 0.5 * (C[:, 0].min() + C[:, 0].max())).astype(int)
    go = threading.Event()

    def during(proc, fake):
        assert fake.paused.wait(30)             # rank 0 holds back step 3's frames
        os.kill(_mpi_rank_pid(proc.pid, 1), signal.SIGTERM)
        time.sleep(0.3)
        go.set()

    fake, addr, rc, _, log = run_m2m(case, solver, 50, inputs, owner, nprocs=2, timeout=10,
                                     pause={0: (3, go)}, during=during)
    assert "Stopped by signal 15 after step 3" in log
    for (g, r), frames in fake.received.items():
        h = frames[-1][0]
        assert (len(frames), h["step"], h["flags"]) == (4, 3, 1 | (15 << 8)), (g, r, h)
    for g in (0, 1):
        assert (case / f"processor{g}" / f"{3 * dt:g}" / "U").is_file()


@pytest.mark.parametrize("missing", ["ready", "dem"])
def test_m2m_plan_missing(tmp_path, solver, missing):
    """No <directory>/ready within connectTimeout, or no dem<r> file in gas0/: a fatal error
    naming the file or folder."""
    case, C, V = make_case(tmp_path, "ergun", n_steps=5, dt=1e-4)
    plan = tmp_path / "plan"
    (plan / "gas0").mkdir(parents=True)
    if missing == "dem":
        (plan / "ready").write_text("1\n")
        (plan / "gas1").mkdir()
        (plan / "gas1" / "dem0").write_text("127.0.0.1 9 320\n")
    fc.write_coupling_dict(case, "m2m", timeout=1, m2m_directory=str(plan))
    proc = fc.start_solver(case, solver=solver)
    try:
        rc = proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    log = (case / "log.thermoDemFoam").read_text()
    assert rc != 0
    what = (f"{plan}/ready did not appear within 1 s" if missing == "ready"
            else f"no plan file dem<r> in the m2m plan folder {plan}/gas0")
    assert what in log, log[-3000:]
