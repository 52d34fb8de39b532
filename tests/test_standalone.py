"""The repository stands alone: every scene it ships (examples/, benchmarks/, openfoam_cases/,
tests/scenes/) reads its particle files from inside the clone, and they are there; the shared
benchmark beds committed as NPZ are the shared scene's beds (their size, box and packing), and
only the LIGGGHTS side of the side by side reads anything beside the clone."""
import glob
import os
import re
import tomllib

import numpy as np
import pytest

from dem import Simulation

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCENES = sorted(f for pattern in ("examples/*.toml", "benchmarks/*.toml", "openfoam_cases/*/dem.toml",
                                  "tests/scenes/*.toml")
                for f in glob.glob(os.path.join(ROOT, pattern)))


def _files(node):
    if isinstance(node, dict):
        for k, v in node.items():
            if k == "file" and isinstance(v, str):
                yield v
            else:
                yield from _files(v)
    elif isinstance(node, list):
        for v in node:
            yield from _files(v)


def test_every_shipped_scene_reads_its_files_from_the_clone():
    assert len(SCENES) >= 15
    seen = 0
    for scene in SCENES:
        with open(scene, "rb") as fh:
            data = tomllib.load(fh)
        for rel in _files(data):
            path = os.path.realpath(os.path.join(os.path.dirname(scene), rel))
            assert os.path.commonpath([path, os.path.realpath(ROOT)]) == os.path.realpath(ROOT), (scene, rel)
            assert os.path.isfile(path), (scene, rel)
            seen += 1
    assert seen >= 6        # the packed beds of examples, openfoam_cases and the four shared beds


@pytest.mark.parametrize("size,n,box,phi", [("10k", 10000, 0.04, 0.57), ("50k", 50000, 0.07, 0.59)])
def test_shared_beds_in_the_repository_are_the_shared_scene(size, n, box, phi):
    """The bed of ../shared/bench/README.md: N spheres of 1 mm resting in an L x L box, packing
    fraction about 0.57 (10k) and 0.59 (50k), ids 1..N; loaded by the scene that names it."""
    sim = Simulation.from_file(os.path.join(ROOT, "benchmarks", f"shared_bed_{size}.toml"))
    st = sim.state
    assert st.n == n and sorted(st.id.tolist()) == list(range(1, n + 1))
    assert np.all(st.radius == 0.001)
    x = st.position
    # inside the walls, pressed into them by at most 5 % of a radius (E = 5 MPa, the bed's weight)
    assert x[:, :2].min() >= 0.95e-3 and x[:, :2].max() <= box - 0.95e-3
    assert x[:, 2].min() >= 0.95e-3
    # packing fraction of the bulk: the spheres whose centres lie in the middle 60 % of the height
    z = x[:, 2]
    lo, hi = np.quantile(z, 0.2), np.quantile(z, 0.8)
    inside = (z > lo) & (z < hi)
    frac = inside.sum() * 4 / 3 * np.pi * 0.001 ** 3 / (box * box * (hi - lo))
    assert frac == pytest.approx(phi, abs=0.03)
    # settled (LIGGGHTS's settling, the state at its end): the r.m.s. speed is under 1 % of
    # sqrt(g d) = 0.14 m/s, the speed of a bead dropped by its own diameter, and no bead moves at 10 %
    v = np.linalg.norm(st.velocity, axis=1)
    ref = np.sqrt(9.81 * 0.002)
    assert np.sqrt(np.mean(v ** 2)) < 0.01 * ref and v.max() < 0.1 * ref


def test_only_the_liggghts_side_reads_beside_the_clone():
    """No test, benchmark or package module names a path outside the repository, except the
    shared scene's LIGGGHTS inputs (benchmarks/shared_scene.py, optional, said when missing)."""
    pattern = re.compile(r"""\.\./\.\./shared|["']shared["']\s*,\s*["']bench["']|\.\./shared/bench/packings""")
    hits = []
    for base in ("dem", "coupling", "benchmarks", "tests", "scripts"):
        for f in glob.glob(os.path.join(ROOT, base, "**", "*"), recursive=True):
            if not f.endswith((".py", ".toml", ".sh")) or os.path.samefile(f, __file__):
                continue
            with open(f, encoding="utf-8") as fh:
                if pattern.search(fh.read()):
                    hits.append(os.path.relpath(f, ROOT))
    assert hits == ["benchmarks/shared_scene.py"]
