"""The import graph of hybridhdr follows ``docs/architecture.md``: no forbidden arrow, no cycle.

The graph is read from the source with ``ast`` (nothing is imported): every ``import`` and
``from ... import``, at module level or inside functions and classes, absolute or relative.
"""

from __future__ import annotations

import ast
import shutil
import textwrap
from collections import defaultdict
from pathlib import Path

import pytest

PACKAGE_DIR = Path(__file__).resolve().parents[1] / "hybridhdr"

#: The parts, lowest first. A module may import from its own part and from parts of a lower rank;
#: the four verbs of rank 3 import each other only along PEER_ARROWS.
RANK = {"core": 0, "camera": 1, "formats": 2, "capture": 3, "calibrate": 3, "simulate": 3, "reconstruct": 3,
        "evaluate": 4, "app": 5}
PEER_ARROWS = {("reconstruct", "calibrate")}
#: Arrows named in docs/architecture.md as ones that must never exist (all also follow from RANK).
FORBIDDEN = {("capture", "reconstruct"), ("reconstruct", "simulate"), ("calibrate", "reconstruct"),
             ("reconstruct", "evaluate"), ("simulate", "evaluate"), ("calibrate", "evaluate"),
             *(("formats", verb) for verb in ("capture", "calibrate", "simulate", "reconstruct", "evaluate")),
             *(("camera", verb) for verb in ("capture", "calibrate", "simulate", "reconstruct", "evaluate")),
             *(("core", p) for p in RANK if p != "core")}

_CORE_MODULES = {"events", "model", "errors", "_version", "_util"}


def part_of(module: str) -> str:
    """The part of a dotted module name inside the package (``hybridhdr.formats.text`` -> formats)."""
    names = module.split(".")
    if len(names) == 1:
        return "app"  # the package root re-exports the public names: it sits on top
    head = names[1]
    if head in _CORE_MODULES:
        return "core"
    if head in RANK:
        return head
    return "app"  # cli, __main__, view, interop, the README's hybridhdr.container, CLI helpers


def _modules(root: Path, package: str) -> dict[str, tuple[Path, bool]]:
    out = {}
    for path in sorted((root / package).rglob("*.py")):
        rel = path.relative_to(root).with_suffix("").parts
        is_pkg = rel[-1] == "__init__"
        out[".".join(rel[:-1] if is_pkg else rel)] = (path, is_pkg)
    return out


def import_graph(root: Path, package: str = "hybridhdr") -> dict[str, set[str]]:
    """module -> the package's modules it imports (anywhere in its source)."""
    mods = _modules(root, package)
    graph: dict[str, set[str]] = {}
    for name, (path, is_pkg) in mods.items():
        here = name.split(".") if is_pkg else name.split(".")[:-1]
        targets = set()
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
            if isinstance(node, ast.Import):
                cands = [[a.name] for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = here[:len(here) - node.level + 1] if node.level else []
                mod = ".".join(base + ([node.module] if node.module else []))
                cands = [[mod, f"{mod}.{a.name}"] for a in node.names]
            else:
                continue
            for cand in cands:
                for target in cand:
                    # the longest module of the package that the dotted name starts with
                    parts = target.split(".")
                    while parts and ".".join(parts) not in mods:
                        parts.pop()
                    if parts and parts[0] == package:
                        targets.add(".".join(parts))
        targets.discard(name)
        graph[name] = targets
    return graph


def forbidden_arrows(graph: dict[str, set[str]]) -> list[str]:
    """Every import between parts that the layering does not allow, as ``a -> b (part -> part)``."""
    bad = []
    for a, targets in sorted(graph.items()):
        pa = part_of(a)
        for b in sorted(targets):
            pb = part_of(b)
            if pa == pb:
                continue
            allowed = RANK[pb] < RANK[pa] or (pa, pb) in PEER_ARROWS
            if not allowed or (pa, pb) in FORBIDDEN:
                bad.append(f"{a} -> {b} ({pa} -> {pb})")
    return bad


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one node (Tarjan, iterative)."""
    index, low, on, stack, out, counter = {}, {}, set(), [], [], [0]
    for start in sorted(graph):
        if start in index:
            continue
        work = [(start, iter(sorted(graph.get(start, ()))))]
        index[start] = low[start] = counter[0]
        counter[0] += 1
        stack.append(start)
        on.add(start)
        while work:
            v, it = work[-1]
            for w in it:
                if w not in index:
                    index[w] = low[w] = counter[0]
                    counter[0] += 1
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(sorted(graph.get(w, ())))))
                    break
                if w in on:
                    low[v] = min(low[v], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
                if low[v] == index[v]:
                    comp = []
                    while True:
                        w = stack.pop()
                        on.discard(w)
                        comp.append(w)
                        if w == v:
                            break
                    if len(comp) > 1:
                        out.append(sorted(comp))
    return out


def part_graph(graph: dict[str, set[str]]) -> dict[str, set[str]]:
    parts = defaultdict(set)
    for a, targets in graph.items():
        for b in targets:
            if part_of(a) != part_of(b):
                parts[part_of(a)].add(part_of(b))
    return parts


def _without_package_roots(graph: dict[str, set[str]]) -> dict[str, set[str]]:
    """The graph without arrows into a package's ``__init__`` from inside that package (a module
    reaching its package's re-exports is how Python imports it anyway) -- they are not cycles."""
    return {a: {b for b in t if not (a.startswith(b + ".") and b != "hybridhdr")} for a, t in graph.items()}


def check(root: Path, package: str = "hybridhdr") -> list[str]:
    """All violations in the tree at ``root``: forbidden arrows, cycles between parts and modules."""
    graph = import_graph(root, package)
    problems = forbidden_arrows(graph)
    problems += [f"cycle between parts: {' <-> '.join(c)}" for c in _cycles(part_graph(graph))]
    problems += [f"cycle between modules: {' <-> '.join(c)}" for c in _cycles(_without_package_roots(graph))]
    return problems


# -- the tests ----------------------------------------------------------------------------------------

def test_package_follows_the_architecture():
    problems = check(PACKAGE_DIR.parent)
    assert not problems, "\n".join(problems)


def test_graph_sees_relative_and_function_level_imports():
    graph = import_graph(PACKAGE_DIR.parent)
    assert "hybridhdr.formats.base" in graph["hybridhdr.formats.container"]  # relative, module level
    assert "hybridhdr.formats.prophesee" in graph["hybridhdr.formats.registry"]  # inside a function
    assert {"core", "camera", "formats"} <= part_graph(graph)["reconstruct"] | {"core"}


@pytest.fixture
def package_copy(tmp_path):
    shutil.copytree(PACKAGE_DIR, tmp_path / "hybridhdr", ignore=shutil.ignore_patterns("__pycache__"))
    assert check(tmp_path) == []
    return tmp_path


def test_a_forbidden_import_inside_a_function_fails(package_copy):
    (package_copy / "hybridhdr" / "capture" / "_shortcut.py").write_text(textwrap.dedent("""\
        def preview(rec):
            from ..reconstruct import reconstruct
            return reconstruct(rec)
        """))
    assert check(package_copy) == [
        "hybridhdr.capture._shortcut -> hybridhdr.reconstruct (capture -> reconstruct)"]


def test_a_format_importing_a_verb_fails(package_copy):
    (package_copy / "hybridhdr" / "formats" / "_sneaky.py").write_text("import hybridhdr.simulate.scene\n")
    assert check(package_copy) == ["hybridhdr.formats._sneaky -> hybridhdr.simulate.scene (formats -> simulate)",
                                   "cycle between parts: formats <-> simulate"]


def test_a_cycle_between_modules_fails(package_copy):
    d = package_copy / "hybridhdr" / "reconstruct"
    (d / "_ping.py").write_text("from . import _pong\n")
    (d / "_pong.py").write_text("def f():\n    from ._ping import g\n")
    assert check(package_copy) == [
        "cycle between modules: hybridhdr.reconstruct._ping <-> hybridhdr.reconstruct._pong"]


def test_a_cycle_between_peer_parts_fails(package_copy):
    (package_copy / "hybridhdr" / "calibrate" / "_recon.py").write_text("from ..reconstruct import smoother\n")
    problems = check(package_copy)
    assert "hybridhdr.calibrate._recon -> hybridhdr.reconstruct.smoother (calibrate -> reconstruct)" in problems
    assert "cycle between parts: calibrate <-> reconstruct" in problems
