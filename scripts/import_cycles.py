"""Import circles among pemviz's modules, found by reading the source (``ast``), not by importing it.

Every ``import pemviz.x`` / ``from pemviz.x import y`` / relative import in ``pemviz/**/*.py`` is an edge from the
importing module to the imported one (to ``pemviz.x.y`` when ``y`` is a module, else to ``pemviz.x``). Three kinds
are counted apart: imports run when the module is loaded (at module level, in class bodies, under ``try`` / ``if``),
imports inside functions (run when the function is called), and imports under ``if TYPE_CHECKING:`` (never run; a
circle through them is one of design, not of loading). A circle is a strongly connected component of the graph
(Tarjan 1972) with more than one module; each is printed with one closed path through it.

The folders are checked too (:func:`folder_rules`): a top-level folder of the package (``core``, ``sinks``, ...; a
module at its top, ``config``, ``settings``, counts as a folder of its own; ``methods`` is one folder, whatever
sub-folders it has, so that no circle among the top-level folders hides behind a method's folder) imports folders only
in this layer order, lowest first, lazy and ``TYPE_CHECKING`` imports included, and no folders import one another in a
circle:

1. the registry: ``plugins`` and ``methods`` (the method registry, the built-in methods' light settings and words
   modules), which import nothing else of the package: the registry names a method's estimator and hooks by text only
   (``"pemviz.estimators.<module>:Class"``, a :data:`pemviz.plugins.Ref` resolved when used);
2. the framework: ``settings``, ``config``, ``core``, ``pem``, ``stl``, ``stack``, ``estimators``, ``engine``; of
   these the core, the PEMs, formulas, stack, estimators and engine (:data:`FRAMEWORK`) import nothing of layer 3;
3. the rest: ``scenarios``, ``io``, ``sinks``, ``app``, ``commands``, ``studies`` (:data:`UPPER`) and the other
   modules at the top (the command line, the presets, the gymnasium environment).

    python scripts/import_cycles.py             # exit 1 if there is a circle among module-level imports
    python scripts/import_cycles.py --strict    # exit 1 also for circles through function-level or TYPE_CHECKING ones,
                                                # folder circles and imports against the layer order
    python scripts/import_cycles.py --root path/to/pkg

Exit status: 0 (no circle), 1 (circles or imports against the layer order found), 2 (bad arguments or a file that
does not parse).
"""

from __future__ import annotations

import argparse
import ast
import sys
from dataclasses import dataclass, field
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


@dataclass
class ImportGraph:
    """Edges importer -> imported among one package's modules, split by when the import runs."""

    modules: set[str] = field(default_factory=set)
    lines: dict[tuple[str, str], list[str]] = field(default_factory=dict)
    """(importer, imported) -> ``file:line`` of each import statement of the edge (``file`` from the package folder)."""
    module_level: dict[str, set[str]] = field(default_factory=dict)
    function_level: dict[str, set[str]] = field(default_factory=dict)
    type_checking: dict[str, set[str]] = field(default_factory=dict)

    def edges(self, *kinds: str) -> dict[str, set[str]]:
        """The adjacency of module-level edges plus those of ``kinds`` (``function_level``, ``type_checking``)."""
        out = {m: set(self.module_level.get(m, ())) for m in self.modules}
        for kind in kinds:
            for m, targets in getattr(self, kind).items():
                out[m] |= targets
        return out


def module_name(path: Path, root: Path) -> str:
    """``root/a/b.py`` -> ``pkg.a.b`` and ``root/a/__init__.py`` -> ``pkg.a``, with ``pkg`` the folder name of root."""
    parts = [root.name, *path.relative_to(root).with_suffix("").parts]
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _imports(tree: ast.Module) -> list[tuple[ast.Import | ast.ImportFrom, str]]:
    """Every import statement of a module with its kind: ``module_level``, ``function_level`` or ``type_checking``."""
    found: list[tuple[ast.Import | ast.ImportFrom, str]] = []

    def visit(node: ast.AST, kind: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.If) and _is_type_checking(child.test):
                for inner in child.body:
                    visit_one(inner, "type_checking")
                for other in child.orelse:  # the else branch does run
                    visit_one(other, kind)
                continue
            visit_one(child, kind)

    def visit_one(node: ast.AST, kind: str) -> None:
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            found.append((node, kind))
        elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)) and kind == "module_level":
            visit(node, "function_level")
        else:
            visit(node, kind)

    visit(tree, "module_level")
    return found


def _targets(node: ast.Import | ast.ImportFrom, importer: str, is_package: bool, modules: set[str]) -> set[str]:
    """The package modules an import statement loads (the deepest existing module of each dotted name)."""

    def deepest(name: str) -> str | None:
        while name and name not in modules:
            name = name.rpartition(".")[0]
        return name or None

    if isinstance(node, ast.Import):
        return {t for a in node.names if (t := deepest(a.name))}
    if node.level:  # relative: from the importer's package, one level up per extra dot
        base = importer if is_package else importer.rpartition(".")[0]
        for _ in range(node.level - 1):
            base = base.rpartition(".")[0]
        source = f"{base}.{node.module}" if node.module else base
    else:
        source = node.module or ""
    out = set()
    for a in node.names:
        sub = f"{source}.{a.name}"
        t = sub if sub in modules else deepest(source)
        if t:
            out.add(t)
    return out


def build_graph(root: Path) -> ImportGraph:
    """The import graph of the package folder ``root`` (its ``.py`` files, recursively).

    Raises:
        SyntaxError: a file that does not parse (the message names it).
    """
    files = {module_name(p, root): p for p in sorted(root.rglob("*.py"))}
    graph = ImportGraph(modules=set(files))
    for name, path in files.items():
        try:
            tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        except SyntaxError as exc:
            raise SyntaxError(f"{path}:{exc.lineno}: {exc.msg}") from None
        for node, kind in _imports(tree):
            targets = _targets(node, name, path.name == "__init__.py", graph.modules) - {name}
            getattr(graph, kind).setdefault(name, set()).update(targets)
            for target in targets:
                graph.lines.setdefault((name, target), []).append(f"{path.relative_to(root).as_posix()}:{node.lineno}")
    for name in graph.modules:  # an edge that also exists at module level is a module-level one
        for kind in (graph.function_level, graph.type_checking):
            kind.get(name, set()).difference_update(graph.module_level.get(name, set()))
    return graph


def strongly_connected(edges: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan 1972), each sorted, sorted by first member."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []

    def connect(v: str) -> None:  # iterative: a deep package must not hit Python's recursion limit
        work = [(v, iter(sorted(edges.get(v, ()))))]
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(edges.get(child, ())))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    w = stack.pop()
                    on_stack.discard(w)
                    component.append(w)
                    if w == node:
                        break
                if len(component) > 1:
                    out.append(sorted(component))

    for v in sorted(edges):
        if v not in index:
            connect(v)
    return sorted(out)


def cycle_in(component: list[str], edges: dict[str, set[str]]) -> list[str]:
    """One closed path through a component, from its first module back to it (breadth first: a shortest one)."""
    start, members = component[0], set(component)
    previous: dict[str, str] = {}
    frontier = [start]
    while frontier:
        following = []
        for v in frontier:
            for w in sorted(edges.get(v, set()) & members):
                if w == start:
                    path = [v]
                    while path[-1] != start:
                        path.append(previous[path[-1]])
                    return [start, *reversed(path[:-1]), start] if len(path) > 1 else [start, v, start]
                if w not in previous:
                    previous[w] = v
                    following.append(w)
        frontier = following
    return [start, start]


KINDS = (
    ("module-level imports", ()),
    ("module- and function-level imports", ("function_level",)),
    ("all imports, TYPE_CHECKING ones included", ("function_level", "type_checking")),
)


def report(graph: ImportGraph) -> list[list[list[str]]]:
    """The circles of each of :data:`KINDS` (module-level; + function-level; + ``TYPE_CHECKING``), printed."""
    found = []
    for label, kinds in KINDS:
        edges = graph.edges(*kinds)
        circles = strongly_connected(edges)
        print(
            f"{len(circles)} circle{'s' if len(circles) != 1 else ''} among {label} "
            f"({len(graph.modules)} modules, {sum(map(len, edges.values()))} edges)"
        )
        for component in circles:
            print(
                "  "
                + " -> ".join(cycle_in(component, edges))
                + (f"   (with {', '.join(component)})" if len(component) > 2 else "")
            )
        found.append(circles)
    return found


REGISTRY = ("plugins", "methods")
"""Layer 1: the registries' plugin loading and the method registry with its light modules; they import nothing else."""
FRAMEWORK = ("core", "pem", "stl", "stack", "estimators", "engine")
"""The folders of layer 2 that know no scenario, file, sink, panel or command (:data:`UPPER`)."""
UPPER = ("scenarios", "io", "sinks", "app", "commands", "studies")
"""Layer 3's folders: none of :data:`FRAMEWORK` imports them."""


def folder_of(module: str) -> str | None:
    """The top-level folder node of ``module``: ``pkg.core.x`` -> ``core``, ``pkg.config`` -> ``config`` (a module at
    the top is a folder of its own), ``pkg.methods.rows`` and ``pkg.methods.state.glm`` -> ``methods``; None for the
    package itself."""
    parts = module.split(".")[1:]
    return parts[0] if parts else None


def against_layers(importer: str, imported: str) -> str | None:
    """Why the folder ``importer`` may not import the folder ``imported`` (the layer order of the module docstring),
    or None where it may."""
    if importer in REGISTRY and imported not in REGISTRY:
        return "the registry imports nothing of the package above it: name that code by text (a Ref)"
    if importer in FRAMEWORK and imported in UPPER:
        return "no scenario, file, sink, panel or command below them"
    return None


def folder_imports(graph: ImportGraph) -> dict[tuple[str, str], list[str]]:
    """(folder, folder it imports) -> the ``file:line`` of each import statement, of every kind (module-level,
    function-level, ``TYPE_CHECKING``), each top-level folder one node (:func:`folder_of`)."""
    found: dict[tuple[str, str], list[str]] = {}
    for (importer, imported), where in sorted(graph.lines.items()):
        a, b = folder_of(importer), folder_of(imported)
        if a and b and a != b:
            found.setdefault((a, b), []).extend(where)
    return found


def folder_rules(graph: ImportGraph) -> tuple[list[list[str]], dict[tuple[str, str], list[str]]]:
    """The folders that import one another in a circle (strongly connected components), and the folder imports
    against the layer order (:func:`against_layers`) with where each is made."""
    found = folder_imports(graph)
    edges: dict[str, set[str]] = {}
    for a, b in found:
        edges.setdefault(a, set()).add(b)
        edges.setdefault(b, set())
    return strongly_connected(edges), {k: v for k, v in found.items() if against_layers(*k)}


def report_folders(graph: ImportGraph) -> tuple[list[list[str]], dict[tuple[str, str], list[str]]]:
    """:func:`folder_rules`, printed."""
    circles, against = folder_rules(graph)
    found = folder_imports(graph)
    folders = {f for edge in found for f in edge}
    print(
        f"{len(circles)} folder circle{'s' if len(circles) != 1 else ''} ({len(folders)} folders, {len(found)} edges)"
    )
    for component in circles:
        print("  " + " -> ".join(cycle_in(component, {a: {b for x, b in found if x == a} for a in folders})))
    print(f"{len(against)} folder import{'s' if len(against) != 1 else ''} against the layer order")
    for (a, b), where in against.items():
        print(f"  {a} -> {b} ({against_layers(a, b)}): {', '.join(where)}")
    return circles, against


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", type=Path, default=REPO / "pemviz", help="the package folder (default: pemviz/)")
    parser.add_argument(
        "--strict",
        action="store_true",
        help="fail on circles through function-level or TYPE_CHECKING imports, folder circles and imports against the "
        "layer order too",
    )
    args = parser.parse_args(argv)
    if not (args.root / "__init__.py").is_file():
        print(f"import_cycles: --root {args.root} is not a package folder (no __init__.py)", file=sys.stderr)
        return 2
    try:
        graph = build_graph(args.root)
    except SyntaxError as exc:
        print(f"import_cycles: {exc}", file=sys.stderr)
        return 2
    module_circles, _, all_circles = report(graph)
    folder_circles, against = report_folders(graph)
    return 1 if module_circles or (args.strict and (all_circles or folder_circles or against)) else 0


if __name__ == "__main__":
    sys.exit(main())
