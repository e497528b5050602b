"""The import layering of `bimfactor`: stage packages import downward only.

Every module under bimfactor/ is parsed with `ast` (nothing is imported), and each `import` statement it holds, at
module level or inside a function, a class or an `if`, is mapped to the top-level unit it names: a package (`bim`,
`sim`, `io`, ...) or a module (`pipeline`, `demo`, `cli`, `config`, `types`, `errors`, ...; `bimfactor` is the
package's own `__init__`). The allowed order, lowest first (`LAYERS`); a unit may import its own layer and the layers
below it:

    foundation   bimfactor (__version__), errors, types, odometry, textfile, progress, resources, config, and any
                 top-level module not named below
    io           atomic output folders, the sequence format and its readers (TUM, rosbag): below bim, whose prior
                 is written with `io.atomic.output_dir`
    embed        text embedders
    bim          IFC → prior (offline)
    sim          the simulator
    perception
    localization
    backend
    registration
    active       where to look next: the belief's modes (localization) against the BIM's predicted views
    pipeline     pipeline.py, the localizer that runs perception → localization → backend → registration: above
                 every stage it runs, below evaluation, whose reports and benchmarks read its runs
    refine       refine.py, the offline refinement of a localized run: above pipeline, whose runs it refines,
                 below evaluation, whose reports and benchmarks read its refined runs
    evaluation   metrics, reports, plots, benchmarks
    workflows    workflows.py, the commands' workflows as library functions (convert_recording): above evaluation,
                 whose checks and reports they write, below the demo and the CLI that call them
    demo         demo.py, the end-to-end demo: above evaluation, whose report, metrics and plots it writes, below
                 the CLI that runs it
    cli          cli.py (the one CLI) and __main__

The checks, each naming the offending import and its file:line:

(a) no import cycle between units. Imports under `if TYPE_CHECKING:` are left out of this check only: they never
    run, and they are how a module annotates with a type of a module that imports it (`bim.visibility`);
(b) bim, sim, io, perception, localization, backend, registration, active and embed never import
    `bimfactor.evaluation` or `bimfactor.cli`, not even for a type: plotting, benchmarks and the CLI sit above the
    algorithms;
(c) every import, type-only ones included, goes down `LAYERS` (or stays in its layer).
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

PACKAGE_DIR = Path(__file__).resolve().parents[1] / "bimfactor"
PACKAGE = PACKAGE_DIR.name
FOUNDATION = 0  # the layer of `bimfactor`, errors, types, config, ... and of any unit LAYERS does not name
LAYERS: tuple[tuple[str, ...], ...] = (
    ("bimfactor", "errors", "types", "odometry", "textfile", "progress", "resources", "config"),
    ("io",),
    ("embed",),
    ("bim",),
    ("sim",),
    ("perception",),
    ("localization",),
    ("backend",),
    ("registration",),
    ("active",),
    ("pipeline",),
    ("refine",),
    ("evaluation",),
    ("workflows",),
    ("demo",),
    ("cli", "__main__"),
)
ALGORITHM_STAGES = ("bim", "sim", "io", "perception", "localization", "backend", "registration", "active", "embed")
NEVER_FROM_STAGES = ("evaluation", "cli")


@dataclass(frozen=True)
class Import:
    """One import of a bimfactor unit by a module of another unit."""

    source: str  # the importing unit
    target: str  # the imported unit
    where: str  # bimfactor/bim/prior.py:332
    statement: str  # the statement as written (its first line)
    type_only: bool  # under `if TYPE_CHECKING:`

    def __str__(self) -> str:
        return f"{self.where}: {self.statement}" + ("  (type-only)" if self.type_only else "")


def layer_of(unit: str) -> int:
    return next((i for i, layer in enumerate(LAYERS) if unit in layer), FOUNDATION)


def unit_of(dotted: str) -> str:
    """The top-level unit of a dotted name inside the package: `bimfactor.bim.prior` → `bim`."""
    parts = dotted.split(".")
    assert parts[0] == PACKAGE, dotted
    return parts[1] if len(parts) > 1 else PACKAGE


def is_unit(name: str) -> bool:
    """Whether `bimfactor.<name>` is a subpackage or a module (not a name defined in the package's __init__)."""
    return (PACKAGE_DIR / name).is_dir() or (PACKAGE_DIR / f"{name}.py").is_file()


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE_DIR.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _import_nodes(tree: ast.AST) -> Iterator[tuple[ast.Import | ast.ImportFrom, bool]]:
    """Every import statement anywhere in the tree, with whether it sits under `if TYPE_CHECKING:`."""

    def walk(node: ast.AST, type_only: bool) -> Iterator[tuple[ast.Import | ast.ImportFrom, bool]]:
        if isinstance(node, ast.Import | ast.ImportFrom):
            yield node, type_only
        if isinstance(node, ast.If) and _is_type_checking(node.test):
            for child in node.body:
                yield from walk(child, True)
            for child in node.orelse:
                yield from walk(child, type_only)
            return
        for child in ast.iter_child_nodes(node):
            yield from walk(child, type_only)

    yield from walk(tree, False)


def imports_of(source: str, module: str, where: str, is_package: bool = False) -> list[Import]:
    """The imports of bimfactor units other than `module`'s own that `source` (module `module`) makes."""
    own = unit_of(module)
    found = []
    lines = source.splitlines()
    for node, type_only in _import_nodes(ast.parse(source)):
        targets: list[str] = []
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        else:
            base = node.module or ""
            if node.level:  # relative: resolved against the importing module's package
                package = module.split(".")
                package = package if is_package else package[:-1]
                package = package[: len(package) - (node.level - 1)]
                base = ".".join([*package, base] if base else package)
            if base == PACKAGE:  # `from bimfactor import errors` names a unit; `... import __version__` does not
                targets = [f"{PACKAGE}.{a.name}" if is_unit(a.name) else PACKAGE for a in node.names]
            else:
                targets = [base]
        for target in targets:
            if target != PACKAGE and not target.startswith(f"{PACKAGE}."):
                continue
            unit = unit_of(target)
            if unit != own:
                statement = lines[node.lineno - 1].strip()
                found.append(Import(own, unit, f"{where}:{node.lineno}", statement, type_only))
    return found


def package_imports() -> list[Import]:
    found = []
    for path in sorted(PACKAGE_DIR.rglob("*.py")):
        where = path.relative_to(PACKAGE_DIR.parent).as_posix()
        source = path.read_text(encoding="utf-8")
        found += imports_of(source, module_name(path), where, is_package=path.name == "__init__.py")
    return found


def cycles(edges: list[Import]) -> list[list[str]]:
    """The strongly connected components of more than one unit (Tarjan), each sorted."""
    graph: dict[str, set[str]] = {}
    for e in edges:
        graph.setdefault(e.source, set()).add(e.target)
        graph.setdefault(e.target, set())
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                components.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return components


def shortest_cycles(edges: list[Import], component: set[str]) -> list[list[str]]:
    """The distinct cycles of a strongly connected component: for each of its edges u → v, v's shortest path
    back to u (breadth first), as the list of units from the cycle's first unit in sorted order."""
    graph: dict[str, list[str]] = {}
    for e in edges:
        if e.source in component and e.target in component and e.target not in graph.setdefault(e.source, []):
            graph[e.source].append(e.target)
    found: list[list[str]] = []
    for u in sorted(graph):
        for v in sorted(graph[u]):
            parent: dict[str, str | None] = {v: None}
            queue = [v]
            while queue and u not in parent:
                nxt = []
                for w in queue:
                    for x in sorted(graph.get(w, [])):
                        if x not in parent:
                            parent[x] = w
                            nxt.append(x)
                queue = nxt
            path: list[str] = []
            node: str | None = u
            while node is not None:
                path.append(node)
                node = parent[node]
            loop = path[::-1]  # v ... u, and u → v closes it
            start = loop.index(min(loop))
            loop = loop[start:] + loop[:start]
            if loop not in found:
                found.append(loop)
    return sorted(found, key=lambda loop: (len(loop), loop))


# ------------------------------------------------------------------------------------------ the scanner itself


def test_the_scanner_finds_imports_at_every_level() -> None:
    source = (
        "from __future__ import annotations\n"
        "import numpy as np\n"
        "from typing import TYPE_CHECKING\n"
        "import bimfactor.sim.world\n"
        "from bimfactor import __version__, errors\n"
        "from bimfactor.bim.prior import BimPrior\n"
        "from . import likelihood\n"
        "from ..registration.scan import frame_scan\n"
        "if TYPE_CHECKING:\n"
        "    from bimfactor.pipeline import Track\n"
        "def f():\n"
        "    from bimfactor.evaluation.plots import save_figure\n"
        "class C:\n"
        "    def g(self):\n"
        "        if True:\n"
        "            import bimfactor.cli\n"
    )
    found = imports_of(source, "bimfactor.localization.smcl", "bimfactor/localization/smcl.py")
    assert [(i.target, i.where.rsplit(":", 1)[1], i.type_only) for i in found] == [
        ("sim", "4", False),
        ("bimfactor", "5", False),
        ("errors", "5", False),
        ("bim", "6", False),
        ("registration", "8", False),
        ("pipeline", "10", True),
        ("evaluation", "12", False),
        ("cli", "16", False),
    ]
    assert str(found[-2]) == "bimfactor/localization/smcl.py:12: from bimfactor.evaluation.plots import save_figure"


def test_the_scan_covers_the_package() -> None:
    found = package_imports()
    units = {i.source for i in found} | {i.target for i in found}
    assert {*ALGORITHM_STAGES, "evaluation", "pipeline", "demo", "cli", "config", "types"} <= units
    assert any(i.source == "cli" and i.target == "pipeline" for i in found)
    assert all(layer_of(unit) == FOUNDATION for unit in units - {u for layer in LAYERS for u in layer})


# ------------------------------------------------------------------------------------------ the rules


def test_no_import_cycle_between_units() -> None:
    edges = [i for i in package_imports() if not i.type_only]
    problems = []
    for component in cycles(edges):
        problems.append(f"cycle between {', '.join(component)}:")
        for loop in shortest_cycles(edges, set(component)):
            problems.append("  " + " → ".join([*loop, loop[0]]))
            for a, b in zip(loop, [*loop[1:], loop[0]], strict=True):
                hops = [e for e in edges if e.source == a and e.target == b]
                more = f"  (and {len(hops) - 1} more)" if len(hops) > 1 else ""
                problems.append(f"    {a} → {b}  {hops[0]}{more}")
    assert not problems, "\n".join(problems)


def test_stages_never_import_evaluation_or_cli() -> None:
    bad = [i for i in package_imports() if i.source in ALGORITHM_STAGES and i.target in NEVER_FROM_STAGES]
    assert not bad, "a stage package imports evaluation or the CLI:\n" + "\n".join(
        f"  {i.source} → {i.target}  {i}" for i in bad
    )


def test_imports_go_down_the_layers() -> None:
    bad = [i for i in package_imports() if layer_of(i.target) > layer_of(i.source)]
    assert not bad, "an import goes up the layers (see LAYERS in tests/test_layers.py):\n" + "\n".join(
        f"  {i.source} (layer {layer_of(i.source)}) → {i.target} (layer {layer_of(i.target)})  {i}" for i in bad
    )
