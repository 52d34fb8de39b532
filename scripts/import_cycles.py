"""Import circles among the modules of dem/ and coupling/ (ast-based: module-level and
function-level imports both count; ``from pkg import name`` counts as an import of
``pkg.name`` when that is a module, else of ``pkg``).

    python scripts/import_cycles.py            # every circle; exit 1 if one lies in coupling/
    python scripts/import_cycles.py dem        # exit 1 if one lies in the packages named

Prints each strongly connected group of modules (a circle) and one shortest circle in it.
"""
import ast
import os
import sys
from collections import deque

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PACKAGES = ("dem", "coupling")


def modules():
    """{module name: path} of every .py file under the packages."""
    found = {}
    for pkg in PACKAGES:
        for d, _, files in os.walk(os.path.join(ROOT, pkg)):
            for f in files:
                if f.endswith(".py"):
                    rel = os.path.relpath(os.path.join(d, f), ROOT)[:-3].split(os.sep)
                    if rel[-1] == "__init__":
                        rel = rel[:-1]
                    found[".".join(rel)] = os.path.join(d, f)
    return found


def _base(name, path, node):
    """The absolute module a ``from ... import`` names."""
    if not node.level:
        return node.module
    parts = name.split(".")
    if not path.endswith("__init__.py"):
        parts = parts[:-1]
    parts = parts[:len(parts) - node.level + 1]
    return ".".join(parts + ([node.module] if node.module else []))


def imports(name, path, known):
    """The known modules that module ``name`` imports, anywhere in its file."""
    with open(path) as fh:
        tree = ast.parse(fh.read(), path)
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = _base(name, path, node)
            for a in node.names:
                sub = f"{base}.{a.name}"
                out.add(sub if sub in known else base)
    return {m for m in out if m in known and m != name}


def strongly_connected(graph):
    """Tarjan's groups of mutually reachable modules (iterative)."""
    index, low, stack, on, groups, counter = {}, {}, [], set(), [], [0]
    for start in graph:
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = counter[0]
        counter[0] += 1
        stack.append(start)
        on.add(start)
        while work:
            v, it = work[-1]
            w = next(it, None)
            if w is None:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
                if low[v] == index[v]:
                    g = []
                    while True:
                        x = stack.pop()
                        on.discard(x)
                        g.append(x)
                        if x == v:
                            break
                    if len(g) > 1:
                        groups.append(sorted(g))
            elif w not in index:
                index[w] = low[w] = counter[0]
                counter[0] += 1
                stack.append(w)
                on.add(w)
                work.append((w, iter(sorted(graph[w]))))
            elif w in on:
                low[v] = min(low[v], index[w])
    return groups


def shortest_circle(graph, group):
    """One shortest circle through the first module of the group."""
    s = group[0]
    prev, todo = {s: None}, deque([s])
    while todo:
        v = todo.popleft()
        for w in sorted(graph[v]):
            if w == s:
                path = [v]
                while prev[path[-1]] is not None:
                    path.append(prev[path[-1]])
                return [s] + path[::-1][1:] + [s] if len(path) > 1 else [s, v, s] if v != s else [s, s]
            if w in group and w not in prev:
                prev[w] = v
                todo.append(w)
    return group


def main(argv):
    strict = tuple(argv) or ("coupling",)
    known = modules()
    graph = {m: imports(m, p, known) for m, p in known.items()}
    groups = strongly_connected(graph)
    bad = 0
    for g in groups:
        hit = any(m.split(".")[0] in strict for m in g)
        bad += hit
        print(f"{'CIRCLE' if hit else 'circle'} ({len(g)} modules): {' -> '.join(shortest_circle(graph, g))}")
    print(f"{len(known)} modules, {sum(map(len, graph.values()))} imports; "
          f"{len(groups)} circle group(s), {bad} in {'/'.join(strict)}")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
