"""The code's shape (issue 25), read from the sources with ast: no import circle in dem/ or
coupling/, no function outside the scalar model laws with more than 12 parameters, no
``range(...)`` index-constant tuples, and a Simulation that wires its parts (no attribute
forwarding, under 300 lines)."""
import ast
import pathlib

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
PACKAGES = ("dem", "coupling")
MAX_PARAMETERS = 12
# the scalar model laws: one contact's physics, named after its authors, whose inputs are the
# scalars of the paper's equation (docs/models.md); a record would only hide them
SCALAR_LAWS = {
    ("dem/step.py", "_pair_law"),   # the run's contact law with the laws' scalars (its docstring: why)
    ("dem/contact/hertz_mindlin.py", "hertz_mindlin"),
    ("dem/contact/linear.py", "linear_spring_dashpot"),
    ("dem/contact/rolling.py", "epsd"),
    ("dem/thermal/direct.py", "beaulieu_2020_network"),
    ("dem/thermal/indirect.py", "_cheng_a_pp"),
    ("dem/thermal/indirect.py", "_cheng_b_pp"),
    ("dem/thermal/indirect.py", "_gan_a_pp"),
    ("dem/thermal/indirect.py", "_chen_b_pp"),
    ("dem/thermal/indirect.py", "_rong_horio_pp"),
    ("dem/thermal/indirect.py", "_musser_pp"),
    ("dem/thermal/indirect.py", "_vargas_pp"),
    # geometry of a mesh contact as numbers: called for each particle and contact, where an array
    # argument would cost its reference counts (dem.contact.mesh.mesh_contacts)
    ("dem/contact/mesh.py", "_snap"),
    ("dem/contact/mesh.py", "frame_point"),
}


def _sources():
    for pkg in PACKAGES:
        for p in sorted((ROOT / pkg).rglob("*.py")):
            yield p, ast.parse(p.read_text(), filename=str(p))


def _module_name(p):
    parts = list(p.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def import_graph():
    """module -> the modules of dem/coupling it imports (at module level or inside functions);
    ``from pkg import mod`` counts as importing ``pkg.mod``."""
    trees = {_module_name(p): (p, t) for p, t in _sources()}
    graph = {m: set() for m in trees}
    for m, (p, tree) in trees.items():
        pkg = m.split(".") if p.name == "__init__.py" else m.split(".")[:-1]
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom):
                base = pkg[:len(pkg) - node.level + 1] if node.level else []
                target = ".".join(base + (node.module.split(".") if node.module else []))
                names = [f"{target}.{a.name}" if f"{target}.{a.name}" in trees else target for a in node.names]
            elif isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            else:
                continue
            graph[m].update(n for n in names if n in trees and n != m)
    return graph


def cycles(graph):
    """The strongly connected groups of more than one module (Tarjan)."""
    index, low, stack, on, found = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while True:
                w = stack.pop()
                on.discard(w)
                group.append(w)
                if w == v:
                    break
            if len(group) > 1:
                found.append(sorted(group))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_no_import_circles():
    graph = import_graph()
    assert "dem.simulation" in graph and "coupling.run" in graph  # the walk found the packages
    assert cycles(graph) == []


def test_cycle_finder_finds_a_cycle():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def _parameters(fn):
    a = fn.args
    n = len(a.posonlyargs) + len(a.args) + len(a.kwonlyargs) + (a.vararg is not None) + (a.kwarg is not None)
    if a.args and a.args[0].arg in ("self", "cls"):
        n -= 1
    return n


def test_no_long_parameter_lists():
    long = []
    for p, tree in _sources():
        rel = p.relative_to(ROOT).as_posix()
        for node in ast.walk(tree):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and (rel, node.name) not in SCALAR_LAWS:
                if _parameters(node) > MAX_PARAMETERS:
                    long.append(f"{rel}:{node.lineno} {node.name} ({_parameters(node)})")
    assert long == []


def test_no_range_index_tuples():
    """``A, B, C = range(3)``: slots known by position only; declare them by name instead."""
    found = []
    for p, tree in _sources():
        for node in ast.walk(tree):
            if (isinstance(node, ast.Assign) and isinstance(node.targets[0], ast.Tuple)
                    and isinstance(node.value, ast.Call) and getattr(node.value.func, "id", "") == "range"):
                found.append(f"{p.relative_to(ROOT).as_posix()}:{node.lineno}")
    assert found == []


def test_simulation_wires_parts():
    src = (ROOT / "dem" / "simulation.py").read_text()
    tree = ast.parse(src)
    cls = next(n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == "Simulation")
    methods = {n.name for n in cls.body if isinstance(n, ast.FunctionDef)}
    assert not methods & {"__getattr__", "__setattr__", "__getattribute__"}
    assert len(src.splitlines()) < 300


PARTS = ("simulation", "world", "stepper", "writers", "checkpointer", "reports", "fluid")
NAMEDTUPLE_API = {"_fields", "_replace", "_asdict", "_make"}


def test_parts_use_each_other_through_public_members():
    """No part reads or sets another object's private member (``other._x``)."""
    reached = []
    for name in PARTS:
        p = ROOT / "dem" / f"{name}.py"
        for node in ast.walk(ast.parse(p.read_text())):
            if (isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__")
                    and node.attr not in NAMEDTUPLE_API
                    and not (isinstance(node.value, ast.Name) and node.value.id == "self")):
                reached.append(f"dem/{name}.py:{node.lineno} .{node.attr}")
    assert reached == []


def test_contact_law_is_inlined_into_the_contact_loops():
    """``_pair_law`` is compiled into its two call sites (issue 28): as a called function each
    contact spilled the pair loop's live doubles around the call and returned 8 values through
    memory, 5-8 % of the shared beds' pair loop (docs/notebook.md, "Where a step goes")."""
    tree = ast.parse((ROOT / "dem/step.py").read_text())
    fn = next(n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name == "_pair_law")
    (dec,) = fn.decorator_list
    options = {k.arg: k.value.value for k in dec.keywords if isinstance(k.value, ast.Constant)}
    assert options.get("inline") == "always", options
    calls = [n for n in ast.walk(tree) if isinstance(n, ast.Call) and getattr(n.func, "id", "") == "_pair_law"]
    callers = {f.name for f in tree.body if isinstance(f, ast.FunctionDef)
               for n in ast.walk(f) if n in calls}
    assert callers == {"interact_rows"} and len(calls) == 2, (callers, len(calls))


@pytest.mark.parametrize("path, name, expected, loops", [
    ("dem/step.py", "interact_rows", {"i": 2, "j": 1, "wl": 1, "mi": 2, "mj": 1}, 2),
    ("dem/thermal/implicit.py", "_apply_rows", {"i": 1, "j": 1}, 1),
])
def test_pair_loops_index_rows_unsigned(path, name, expected, loops):
    """The pair and wall loops of ``interact_rows`` and the implicit solvers' product with the
    matrix (``_apply_rows``) take their row indices (i, j, wall) as uint32 (issue 28), and the
    pair loops their material indices into the pair tables (mi, mj) too. A signed
    index makes Numba wrap a negative value around the array's length at every access: a test,
    a conditional move and a reload of the length per array, and the pair loop is bound by the
    instructions it issues (about 1,100 per particle-step on the shared 10k bed), not by its
    arithmetic's latency. Unsigned, the interact phase of the shared 10k bed takes 8 % less
    time, the frozen 50k bed's TR-BDF2 step 3-5 % less (docs/notebook.md, "Row indices
    without the wrap-around")."""
    tree = ast.parse((ROOT / path).read_text())
    fn = next(n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name == name)
    casts = {}
    for n in ast.walk(fn):
        if (isinstance(n, ast.Assign) and len(n.targets) == 1 and isinstance(n.targets[0], ast.Name)
                and isinstance(n.value, ast.Call) and isinstance(n.value.func, ast.Attribute)
                and n.value.func.attr == "uint32"):
            casts[n.targets[0].id] = casts.get(n.targets[0].id, 0) + 1
    assert casts == expected, casts
    # every loop over the pairs' rows goes through the cast
    fors = [n for n in ast.walk(fn) if isinstance(n, ast.For) and isinstance(n.target, ast.Name)]
    assert sum(1 for n in fors if n.target.id == "iu") == loops


def test_lean_form_leaves_out_only_what_full_form_checks():
    """The lean form of the interact phase (``xon`` None) replaces the switches it leaves out by
    constants in one block, ``if xon is not None:`` of ``interact_rows``; each switch read there
    is one that ``full_form`` (which picks the form for a scene) checks, so that no scene using
    it runs in the lean form (tests/test_lean_form.py runs both forms)."""
    tree = ast.parse((ROOT / "dem/step.py").read_text())
    fns = {n.name: n for n in tree.body if isinstance(n, ast.FunctionDef)}
    block = next(n for n in fns["interact_rows"].body if isinstance(n, ast.If)
                 and ast.unparse(n.test) == "xon is not None")
    read = {ast.unparse(s) for a in block.body for s in ast.walk(a.value) if isinstance(s, ast.Subscript)}
    lean = {a.targets[0].id for a in block.body}
    assert lean == {"imodel", "radon", "fric", "use_age", "rolling", "px", "py", "pz"}, lean
    checked = {ast.unparse(s) for s in ast.walk(fns["full_form"]) if isinstance(s, ast.Subscript)}
    assert read and read <= checked, read - checked
