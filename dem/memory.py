"""Memory a scene will need, estimated before anything is allocated, and the check against
the memory the machine has available (``/proc/meminfo`` MemAvailable).

``dem check`` and ``dem run`` (and ``coupling check|run``) call :func:`check_scene` right
after the scene is read and before the Simulation allocates its arrays, so that a scene
too large for the machine is refused with the figures instead of ending in a
``MemoryError`` (or the kernel's out-of-memory killer). ``simulation.force = true`` runs it
anyway. :func:`check_insertion` does the same for the candidate arrays of a
``count = ...`` insertion, while the scene is parsed.

The neighbour-grid term (:func:`neighbor_grid_cells`) mirrors what
``dem.neighbors.cell_grid`` allocates: cells of size ``cut = 2 r_max + reach + skin``, but
only over the box of occupied cells, and at most ``8 n + 4097`` of them (beyond that it
switches to sorted cell keys), so the grid grows with the particles, not with the domain.
"""
import math
import os

import numpy as np

GRID_BYTES_PER_CELL = 16          # head (ncell + 1) and fill (ncell), int64
STATE_BYTES = 192                 # State: 6 vectors, 4 scalars, id, material, group
THERMAL_STATE_BYTES = 24 + 120    # temperature, heat rate, 1/C + the thermal model's arrays
SLOTS = 16                        # neighbour slots per particle of a dense packing (max count + 2)
INSERTION_ATTEMPTS = 200          # dem.insertion.insert: random candidates per sphere


def available_bytes():
    """MemAvailable of /proc/meminfo in bytes, or None when the machine does not say."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


def fmt(nbytes):
    """Bytes in the largest binary unit that keeps the number >= 1."""
    x = float(nbytes)
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if x < 1024 or unit == "PiB":
            return f"{x:.3g} {unit}"
        x /= 1024


def _reach(scene, rmax):
    """Extra pair reach of the thermal models (dem.thermal.kernel.ThermalModel.reach)."""
    th = scene.thermal
    if th is None:
        return 0.0
    gas = th["gas"]
    reach = 0.0
    if th["indirect_id"] >= 0:
        reach = max(reach, float(gas.get("cutoff", 1.0)) * rmax)
    if th["radiation_id"] >= 0:
        reach = max(reach, (float(gas.get("radiation_range", 3.0)) - 2.0) * rmax)
    uses_por = th["indirect_id"] >= 0 or th["convection_id"] >= 0 or th["radiation"] == "zhou_2009"
    if uses_por and th["porosity"] in ("local", "voronoi"):
        reach = max(reach, rmax)
    return reach


def neighbor_grid_cells(lo, hi, periodic, cut):
    """Cells of the domain's neighbour grid, as a Python int (the grid actually stored is
    bounded by :func:`stored_grid_cells`)."""
    total = 1
    for k in range(3):
        nc = max(1, int(math.floor((hi[k] - lo[k]) / cut)))
        if periodic[k] and nc < 3:
            nc = 1
        total *= nc
    return total


def stored_grid_cells(n, domain_cells):
    """Cells the neighbour search stores for ``n`` particles: the occupied box of the domain's
    grid, at most 8 n + 4097 cells (dem.neighbors.cell_grid: a dense table up to that size,
    sorted cell keys beyond it)."""
    return min(int(domain_cells), 8 * int(n) + 4097)


def scene_bytes(scene):
    """Estimated peak bytes of a serial run of ``scene``: {'total', 'particles', 'grid',
    'cells'}. Per particle: the state, two copies of the neighbour list with its history
    (old and new during a rebuild), the wall lists, the thermal arrays."""
    if getattr(scene, "distributed", False):   # set up per rank (MPI): one rank's even share
        n, rmax = int(scene.n_rank), float(scene.rmax)
    else:
        n, rmax = int(scene.radius.size), float(scene.radius.max(initial=0.0))
    nw = max(sum(int(w.get("slots", 1)) for w in scene.walls), 1)   # wall rows (a mesh wall has several)
    rolling = scene.contact["rolling"] != "none"
    thermal = scene.thermal is not None
    slot = 4 + 24 + (24 if rolling else 0)
    if thermal:
        slot += 8 + 8 + 1 + (16 if scene.thermal["direct"] == "zhou_2008_collisional" else 0)
    per = STATE_BYTES + 2 * SLOTS * slot + 8 + nw * (4 + 24 + (24 if rolling else 0)) + 4 + 16
    if thermal:
        per += THERMAL_STATE_BYTES + nw * 16
    cut = 2.0 * rmax + _reach(scene, rmax) + float(scene.simulation["neighbor_skin"])
    cells = stored_grid_cells(n, neighbor_grid_cells(scene.domain["min"], scene.domain["max"],
                                                     scene.domain["periodic"], cut))
    grid = GRID_BYTES_PER_CELL * (cells + 1) + 48 * n   # + per-particle cell keys and order
    return dict(total=per * n + grid, particles=per * n, grid=grid, cells=cells, per_particle=per)


def insertion_bytes(region, count, rmax):
    """Peak bytes of dem.insertion.insert for ``count`` spheres: the random candidates (and
    two temporaries of their size) and the placement grid of cells 2 r_max over the region."""
    cand = 3 * count * INSERTION_ATTEMPTS * 3 * 8
    if region["type"] == "box":
        ext = np.asarray(region["max"], float) - np.asarray(region["min"], float)
    else:
        ax = np.asarray(region["axis"], float)
        ax = ax / np.linalg.norm(ax)
        ext = 2 * (np.abs(ax) * float(region["length"]) / 2
                   + np.sqrt(np.maximum(0.0, 1 - ax ** 2)) * float(region["radius"]))
    cells = 1
    for e in ext:
        cells *= max(1, int(e / (2 * rmax)))
    return cand + 8 * cells


def _refuse(subject, need, detail, force):
    """None when ``need`` fits in the available memory (or force), else the reason."""
    avail = available_bytes()
    if force or avail is None or need <= avail:
        return None
    return (f"{subject} needs about {fmt(need)} of memory ({detail}), more than the {fmt(avail)} "
            f"available on this machine (/proc/meminfo MemAvailable)")


def check_insertion(v, key, region, count, rmax, force):
    """SceneError at ``key`` (particles[k].count) when the insertion cannot fit in memory."""
    need = insertion_bytes(region, count, rmax)
    why = _refuse(f"inserting {count} particles", need,
                  f"{INSERTION_ATTEMPTS} random candidates per particle", force)
    if why:
        v.err(key, why + "; lower the count (or set simulation.force = true to try anyway)")


def check_block_insertion(v, key, count, block_region, block, rmax, ranks, force):
    """SceneError at ``key`` when an insertion by blocks (dem.scene._insert_blocks) cannot fit:
    one block's candidates and grid, and the particles' state (about STATE_BYTES + two neighbour
    lists of SLOTS slots each) of one rank's share of the ``count``, checked before any is drawn."""
    share = -(-int(count) // max(int(ranks), 1))
    per = STATE_BYTES + 2 * SLOTS * 28
    need = insertion_bytes(block_region, block, rmax) + per * share
    why = _refuse(f"inserting {count} particles", need,
                  f"{share} per rank at {per} B each, and one block of {block} with {INSERTION_ATTEMPTS} random "
                  f"candidates per particle", force)
    if why:
        v.err(key, why + "; lower the count, run on more ranks (or set simulation.force = true to try anyway)")


def check_scene(scene):
    """Raise SceneError when the estimated memory of ``scene`` exceeds the available memory
    (unless simulation.force = true). Returns the estimate (scene_bytes)."""
    from .errors import SceneError
    est = scene_bytes(scene)
    if est["grid"] > est["particles"]:
        what = (f"neighbour grid {fmt(est['grid'])}: {est['cells']:.3g} cells of the "
                f"largest particle size; particles {fmt(est['particles'])}")
        key, advice = "domain", "shrink [domain] to where the particles go"
    else:
        share = (f"{scene.n_rank} particles per rank of {scene.n_total}" if getattr(scene, "distributed", False)
                 else f"{scene.radius.size} particles")
        what = (f"{share} at {est['per_particle']} B each {fmt(est['particles'])}; "
                f"neighbour grid {fmt(est['grid'])}")
        key, advice = "particles", "use fewer particles, or run with mpirun on several machines"
    why = _refuse("the scene", est["total"], what, scene.simulation["force"])
    if why:
        raise SceneError(scene.file, key, f"{why}; {advice}, or set simulation.force = true to try anyway")
    return est
