"""The import graph of hybridhdr follows ``docs/architecture.md``: no forbidden arrow, no cycle, no
private name imported across parts, no dependency injected at import time.

The graph is read from the source with ``ast`` (nothing is imported): every ``import`` and
``from ... import``, at module level or inside functions and classes, absolute or relative. The
package is parsed once; the checker's own rules are tested on small graph literals.
"""

from __future__ import annotations

import ast
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
    """The part of a dotted module name inside the package (``hybridhdr.formats.text`` -> formats).

    Each part's command line (``<part>/cli.py`` and ``<part>/_cli_*.py``) is the app layer: it
    wires the parts together (``reconstruct``'s command line calls calibrate's estimators), so it
    may import every part, and no module of a part may import it."""
    names = module.split(".")
    if len(names) == 1:
        return "app"  # the package root re-exports the public names: it sits on top
    head = names[1]
    if head in _CORE_MODULES:
        return "core"
    if head in RANK:
        if len(names) >= 3 and (names[2] == "cli" or names[2].startswith("_cli_")):
            return "app"
        return head
    return "app"  # cli, __main__, view, interop, the README's hybridhdr.container, CLI helpers


def _modules(root: Path, package: str) -> dict[str, tuple[Path, bool]]:
    out = {}
    for path in sorted((root / package).rglob("*.py")):
        rel = path.relative_to(root).with_suffix("").parts
        is_pkg = rel[-1] == "__init__"
        out[".".join(rel[:-1] if is_pkg else rel)] = (path, is_pkg)
    return out


def parse_package(root: Path, package: str = "hybridhdr") -> tuple[dict[str, ast.Module], dict]:
    """(module -> its syntax tree, module -> (path, is a package)) of every module of the package."""
    mods = _modules(root, package)
    return {name: ast.parse(path.read_text(encoding="utf-8"), str(path)) for name, (path, _) in mods.items()}, mods


def _imports(trees: dict[str, ast.Module], mods: dict, package: str = "hybridhdr"):
    """``(module, target module, imported name or None)`` for every import of the package's own
    modules (the target: the longest module of the package that the dotted name starts with)."""
    def target_of(dotted: str) -> str | None:
        parts = dotted.split(".")
        while parts and ".".join(parts) not in mods:
            parts.pop()
        return ".".join(parts) if parts and parts[0] == package else None

    for name, tree in trees.items():
        is_pkg = mods[name][1]
        here = name.split(".") if is_pkg else name.split(".")[:-1]
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                for a in node.names:
                    t = target_of(a.name)
                    if t is not None and t != name:
                        yield name, t, None
            elif isinstance(node, ast.ImportFrom):
                base = here[:len(here) - node.level + 1] if node.level else []
                mod = ".".join(base + ([node.module] if node.module else []))
                for a in node.names:
                    sub = target_of(f"{mod}.{a.name}")
                    if sub is not None and sub == f"{mod}.{a.name}":  # a module imported from its package
                        if sub != name:
                            yield name, sub, None
                    else:
                        t = target_of(mod)
                        if t is not None and t != name:
                            yield name, t, a.name


def graph_of(edges) -> dict[str, set[str]]:
    graph: dict[str, set[str]] = defaultdict(set)
    for a, b, _ in edges:
        graph[a].add(b)
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


def private_crossings(edges) -> list[str]:
    """Private names (``_name``) and private modules (``_module``, but core's ``_util`` and
    ``_version``, which every part shares) imported from another part."""
    bad = []
    for a, b, name in edges:
        pa, pb = part_of(a), part_of(b)
        if pa == pb:
            continue
        mods = b.split(".")[1:]
        private_module = any(m.startswith("_") and not m.startswith("__") and m not in ("_util", "_version")
                             for m in mods)
        private_name = name is not None and name.startswith("_") and not name.startswith("__")
        if private_module or private_name:
            bad.append(f"{a} -> {b}{'' if name is None else '.' + name} ({pa} -> {pb})")
    return sorted(set(bad))


def injected_dependencies(trees: dict[str, ast.Module]) -> list[str]:
    """Functions that install a dependency into a module global (``global X`` then ``X = ...``
    inside a ``set_*`` function): the part's graph would not show the arrow."""
    bad = []
    for name, tree in trees.items():
        for node in tree.body:
            if isinstance(node, ast.FunctionDef) and node.name.startswith("set_"):
                if any(isinstance(n, ast.Global) for n in ast.walk(node)):
                    bad.append(f"{name}.{node.name}")
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


def check_graph(edges) -> list[str]:
    """All violations of an import graph given as ``(module, target, name or None)`` edges."""
    edges = list(edges)
    graph = graph_of(edges)
    problems = forbidden_arrows(graph)
    problems += [f"private import across parts: {p}" for p in private_crossings(edges)]
    problems += [f"cycle between parts: {' <-> '.join(c)}" for c in _cycles(part_graph(graph))]
    problems += [f"cycle between modules: {' <-> '.join(c)}" for c in _cycles(_without_package_roots(graph))]
    return problems


@pytest.fixture(scope="module")
def package():
    trees, mods = parse_package(PACKAGE_DIR.parent)
    return trees, list(_imports(trees, mods))


# -- the package --------------------------------------------------------------------------------------

def test_package_follows_the_architecture(package):
    problems = check_graph(package[1])
    assert not problems, "\n".join(problems)


def test_no_dependency_is_injected(package):
    assert injected_dependencies(package[0]) == []


def test_graph_sees_relative_and_function_level_imports(package):
    graph = graph_of(package[1])
    assert "hybridhdr.formats.base" in graph["hybridhdr.formats.container"]  # relative, module level
    assert "hybridhdr.formats.prophesee" in graph["hybridhdr.formats.registry"]  # inside a function
    assert {"core", "camera", "formats"} <= part_graph(graph)["reconstruct"] | {"core"}
    names = {(a, b, n) for a, b, n in package[1]}
    assert ("hybridhdr.reconstruct.api", "hybridhdr.reconstruct.request", "ReconstructRequest") in names


# -- the checker, on small graph literals ----------------------------------------------------------------

def test_parts_and_the_app_layer():
    assert part_of("hybridhdr") == "app" and part_of("hybridhdr.cli") == "app"
    assert part_of("hybridhdr._util.atomic") == "core" and part_of("hybridhdr.model") == "core"
    assert part_of("hybridhdr.reconstruct.api") == "reconstruct"
    assert part_of("hybridhdr.reconstruct.cli") == "app" and part_of("hybridhdr.calibrate._cli_rig") == "app"
    assert part_of("hybridhdr.calibrate.client") == "calibrate"  # only cli / _cli_* are the app layer


def test_a_forbidden_import_fails():
    edges = [("hybridhdr.capture.session", "hybridhdr.reconstruct.api", "reconstruct")]
    assert check_graph(edges) == [
        "hybridhdr.capture.session -> hybridhdr.reconstruct.api (capture -> reconstruct)"]


def test_an_upward_import_fails_and_a_downward_one_passes():
    assert check_graph([("hybridhdr.formats.text", "hybridhdr.camera.profile", "load_profile")]) == []
    assert check_graph([("hybridhdr.formats.text", "hybridhdr.simulate.scene", None)]) == [
        "hybridhdr.formats.text -> hybridhdr.simulate.scene (formats -> simulate)"]
    assert check_graph([("hybridhdr.evaluate.bench", "hybridhdr.reconstruct.cli", None)]) == [
        "hybridhdr.evaluate.bench -> hybridhdr.reconstruct.cli (evaluate -> app)"]


def test_the_peer_arrow_goes_one_way():
    assert check_graph([("hybridhdr.reconstruct.api", "hybridhdr.calibrate.resolve", "resolve_thresholds")]) == []
    problems = check_graph([("hybridhdr.calibrate.selfcal", "hybridhdr.reconstruct.params", "AKFParams"),
                            ("hybridhdr.reconstruct.api", "hybridhdr.calibrate.resolve", None)])
    assert "hybridhdr.calibrate.selfcal -> hybridhdr.reconstruct.params (calibrate -> reconstruct)" in problems
    assert "cycle between parts: calibrate <-> reconstruct" in problems


def test_the_app_layer_may_import_every_part():
    edges = [("hybridhdr.reconstruct.cli", "hybridhdr.calibrate.selfcal", "self_calibration"),
             ("hybridhdr.calibrate._cli_rig", "hybridhdr.reconstruct.api", "reconstruct")]
    assert check_graph(edges) == []


def test_a_private_name_across_parts_fails():
    edges = [("hybridhdr.reconstruct.output", "hybridhdr.formats.images", "_write_png"),
             ("hybridhdr.reconstruct.api", "hybridhdr.reconstruct.colour", "_metadata"),  # same part: fine
             ("hybridhdr.evaluate.bench", "hybridhdr.reconstruct._kernels", None),
             ("hybridhdr.formats.base", "hybridhdr._util.atomic", "atomic_path")]  # core's _util: shared
    assert check_graph(edges) == [
        "private import across parts: hybridhdr.evaluate.bench -> hybridhdr.reconstruct._kernels "
        "(evaluate -> reconstruct)",
        "private import across parts: hybridhdr.reconstruct.output -> hybridhdr.formats.images._write_png "
        "(reconstruct -> formats)"]


def test_cycles_between_modules_fail():
    edges = [("hybridhdr.reconstruct._ping", "hybridhdr.reconstruct._pong", None),
             ("hybridhdr.reconstruct._pong", "hybridhdr.reconstruct._ping", "g"),
             ("hybridhdr.reconstruct.api", "hybridhdr.reconstruct", None),  # into its package root: not a cycle
             ("hybridhdr.reconstruct", "hybridhdr.reconstruct.api", None)]
    assert check_graph(edges) == ["cycle between modules: hybridhdr.reconstruct._ping <-> hybridhdr.reconstruct._pong"]


def test_an_injected_dependency_is_found():
    tree = ast.parse("_HOOK = None\n\ndef set_hook(fn):\n    global _HOOK\n    _HOOK = fn\n\n"
                     "def setup():\n    global _X\n")
    assert injected_dependencies({"hybridhdr.reconstruct.cli": tree}) == ["hybridhdr.reconstruct.cli.set_hook"]


def test_imports_are_read_from_source():
    """Relative, absolute, function-level and module-from-package imports become edges."""
    mods = {"hybridhdr": (None, True), "hybridhdr.formats": (None, True), "hybridhdr.formats.images": (None, False),
            "hybridhdr.reconstruct": (None, True), "hybridhdr.reconstruct.output": (None, False),
            "hybridhdr.reconstruct.api": (None, False)}
    src = ("from ..formats.images import _write_png, write_exr\nimport hybridhdr.formats.images\n"
           "def f():\n    from . import api\n    from .api import reconstruct\n")
    got = set(_imports({"hybridhdr.reconstruct.output": ast.parse(src)}, mods))
    assert got == {("hybridhdr.reconstruct.output", "hybridhdr.formats.images", "_write_png"),
                   ("hybridhdr.reconstruct.output", "hybridhdr.formats.images", "write_exr"),
                   ("hybridhdr.reconstruct.output", "hybridhdr.formats.images", None),
                   ("hybridhdr.reconstruct.output", "hybridhdr.reconstruct.api", None),
                   ("hybridhdr.reconstruct.output", "hybridhdr.reconstruct.api", "reconstruct")}
