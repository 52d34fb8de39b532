"""Integer-switch dispatchers generated from the model records.

The njit kernels select a model by an integer id. Rather than hand-written if/elif chains that
every new model must edit, the dispatchers ``direct_pp``, ``direct_pw``, ``indirect_pp`` and
``indirect_pw`` are generated from the records' ``laws`` (dem.thermal.records): one branch per
record, ``if model == <id>: return <law>(<slot arguments>[, <column indices of the record's new
inputs>])``, after the slot's common prelude (copied verbatim from the former hand-written
dispatchers, so the arithmetic is unchanged).

Numba's ``cache=True`` needs a real source file whose content does not change between runs: the
source is written once to ``<numba cache dir>/thermodem_dispatch/dispatch_<hash of source>.py``
(content-addressed, written atomically, never rewritten) and imported from there. A second
process finds the same file and loads the compiled dispatchers from Numba's cache; adding a
model changes the source, hence the file name, hence a fresh compile - never stale code.
"""
import hashlib
import importlib.util
import os
import sys
import tempfile

import numba

from . import registry

# slot -> (mechanism, record law key, dispatcher name, signature, prelude, law arguments,
#          prelude imports, docstring)
SLOTS = {
    "direct_pp": dict(
        mechanism="direct", law="pp",
        args="model, Ri, Rj, d, rc, mi, mj, tmat, gas, t_contact, vn_impact",
        prelude=("if rc <= 0.0:\n"
                 "    return 0.0\n"),
        call="Ri, Rj, d, rc, mi, mj, tmat, gas, t_contact, vn_impact",
        imports=(),
        doc="Particle-particle direct conduction conductance [W/K].\n\n"
            "model: direct-conduction id (registry); Ri, Rj [m]; d centre distance [m]; rc contact\n"
            "radius [m] (0 if not touching -> H = 0); mi, mj material rows of tmat; t_contact: time\n"
            "since the contact started [s]; vn_impact: normal relative velocity at impact [m/s].\n"
            "Unknown model -> -1. Generated from the records by dem.thermal.dispatch."),
    "direct_pw": dict(
        mechanism="direct", law="pw",
        args="model, R, d, rc, mp, mw, tmat, gas, t_contact, vn_impact",
        prelude=("if rc <= 0.0:\n"
                 "    return 0.0\n"),
        call="R, d, rc, mp, mw, tmat, gas, t_contact, vn_impact",
        imports=(),
        doc="Particle-wall direct conduction conductance [W/K].\n\n"
            "R particle radius, d centre-to-wall distance [m], rc contact radius [m], mp/mw particle\n"
            "and wall material rows (wall K_COND may be inf: perfect conductor, ref 001).\n"
            "Unknown model -> -1. Generated from the records by dem.thermal.dispatch."),
    "indirect_pp": dict(
        mechanism="indirect", law="pp",
        args="model, Ri, Rj, d, rc, mi, mj, por_i, por_j, tmat, gas",
        prelude=("Rmin = min(Ri, Rj)\n"
                 "if d - Ri - Rj >= gas[CUTOFF] * Rmin:\n"
                 "    return 0.0\n"
                 "kf = gas[KF]\n"
                 "ki = tmat[mi, K_COND]\n"
                 "kj = tmat[mj, K_COND]\n"
                 "r_low = max(rc, geometric_pp(Ri, Rj, d))\n"
                 "por = 0.5 * (por_i + por_j)\n"
                 "por = min(max(por, 0.0), 0.999)\n"),
        call="Ri, Rj, d, rc, r_low, por, Rmin, kf, ki, kj, mi, mj, tmat, gas",
        imports=("from dem.thermal.registry import CUTOFF, K_COND, KF",
                 "from dem.thermal.contact_radius import geometric_pp"),
        doc="Particle-particle indirect conduction conductance [W/K].\n\n"
            "model: indirect-conduction id; Ri, Rj [m]; d centre distance [m]; rc contact radius [m]\n"
            "(0 if apart); mi, mj material rows; por_i, por_j local porosities. Cut-off: 0 when the\n"
            "surface gap >= gas[CUTOFF] min(Ri, Rj). Unknown model -> -1. Generated from the\n"
            "records by dem.thermal.dispatch."),
    "indirect_pw": dict(
        mechanism="indirect", law="pw",
        args="model, R, d, rc, mp, mw, por, tmat, gas",
        prelude=("if d - R >= gas[CUTOFF] * R:\n"
                 "    return 0.0\n"
                 "kf = gas[KF]\n"
                 "kp = tmat[mp, K_COND]\n"
                 "r_low = max(rc, geometric_pw(R, d))\n"
                 "por = min(max(por, 0.0), 0.999)\n"),
        call="R, d, rc, r_low, por, kf, kp, mp, mw, tmat, gas",
        imports=("from dem.thermal.registry import CUTOFF, K_COND, KF",
                 "from dem.thermal.contact_radius import geometric_pw"),
        doc="Particle-wall indirect conduction conductance [W/K].\n\n"
            "R particle radius, d centre-to-wall distance [m], rc contact radius [m], mp/mw\n"
            "particle/wall material rows, por local porosity. Cut-off: 0 when d - R >= gas[CUTOFF] R.\n"
            "Unknown model -> -1. Generated from the records by dem.thermal.dispatch."),
}


def _indent(text, n):
    pad = " " * n
    return "".join(pad + line + "\n" if line else "\n" for line in text.splitlines())


def _law_ref(fn):
    py = getattr(fn, "py_func", fn)
    return py.__module__, py.__name__


def source(derived=None):
    """Python source of the dispatcher module for the records in ``derived`` (default: the
    registry's); deterministic, so equal records give byte-identical source."""
    d = derived or registry.derived()
    lines = ['"""Dispatchers generated by dem.thermal.dispatch from the model records: do not edit."""',
             "import numba", ""]
    imports, bodies = [], []
    for slot, spec in SLOTS.items():
        for imp in spec["imports"]:
            if imp not in imports:
                imports.append(imp)
        recs = sorted(d["by_mech"][spec["mechanism"]].values(), key=lambda r: r.id)
        branches = []
        for rec in recs:
            fn = rec.laws.get(spec["law"])
            if fn is None:
                raise ValueError(f"{spec['mechanism']} model '{rec.name}' has no '{spec['law']}' law "
                                 f"(needed by {slot})")
            mod, name = _law_ref(fn)
            alias = f"_{slot}_{rec.id}"
            imports.append(f"from {mod} import {name} as {alias}")
            table = {"material": d["material_keys"], "gas": d["gas_keys"]}
            extra = "".join(f", {table[i.table][i.key]}" for i in rec.new_inputs)
            branches.append((rec.id, f"return {alias}({spec['call']}{extra})"))
        body = spec["prelude"]
        for k, (mid, ret) in enumerate(branches):
            body += f"{'if' if k == 0 else 'elif'} model == {mid}:\n    {ret}\n"
        body += "return -1.0\n"
        doc = '"""' + spec["doc"] + '"""\n'
        bodies.append('@numba.njit(cache=True, error_model="numpy")\n'
                      f"def {slot}({spec['args']}):\n" + _indent(doc + body, 4))
    return "\n".join(lines + imports + ["", ""] + ["\n\n".join(bodies)])


def _folder():
    base = numba.config.CACHE_DIR or os.path.join(
        os.environ.get("XDG_CACHE_HOME", os.path.expanduser("~/.cache")), "thermodem", "numba")
    return os.path.join(base, "thermodem_dispatch")


def write(src, folder=None):
    """Write ``src`` to its content-addressed file (once) and return the path."""
    h = hashlib.sha256(src.encode()).hexdigest()[:16]
    for base in (folder or _folder(), os.path.join(tempfile.gettempdir(), "thermodem_dispatch")):
        path = os.path.join(base, f"dispatch_{h}.py")
        try:
            if not os.path.exists(path):
                os.makedirs(base, exist_ok=True)
                fd, tmp = tempfile.mkstemp(dir=base, suffix=".tmp")
                with os.fdopen(fd, "w") as fh:
                    fh.write(src)
                os.replace(tmp, path)  # atomic: concurrent processes write identical content
            return path
        except OSError:
            continue
    raise OSError("cannot write the generated thermal dispatchers (numba cache dir and temp dir)")


def load(path):
    """Import the generated module at ``path`` (cached in sys.modules by file name)."""
    name = "dem.thermal._generated_" + os.path.splitext(os.path.basename(path))[0]
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod


_MODULE = None


def module():
    """The generated dispatcher module of the registry's records (built on first use)."""
    global _MODULE
    if _MODULE is None:
        _MODULE = load(write(source()))
    return _MODULE
