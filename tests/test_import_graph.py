"""The package's import graph, read from the source with ``ast``: no cycles, no upward imports.

Every ``import`` / ``from ... import`` of an omnipipe module counts, at module level and
inside functions alike (a function-local import only postpones a cycle); only those
under ``if TYPE_CHECKING:`` are left out (annotations, never executed).

An edge A -> B is the module B imported by A (``from omnipipe.x import y`` is the
submodule ``omnipipe.x.y`` when there is one, else ``omnipipe.x``), plus B's parent
packages that are not also A's (importing ``omnipipe.camera.factory`` from outside
runs ``omnipipe/camera/__init__.py`` first; a module importing a sibling does not).

"Upward" is either of:

- a module importing a unit of a higher layer (:data:`LAYERS`; a unit is a top-level
  module or subpackage of omnipipe; the CLI layer is ``omnipipe.cli``, its argument
  checks ``omnipipe.cli_values`` and the modules that register sub-commands,
  ``omnipipe.cli.COMMAND_MODULES``);
- a module of a subpackage importing names its own package's ``__init__`` defines or
  re-exports (the ``__init__`` is the package's face to the layers above; its
  modules import each other directly). The package's CLI modules are exempt: they
  sit above it.
"""

from __future__ import annotations

import ast
from pathlib import Path

import omnipipe
from omnipipe.cli import COMMAND_MODULES

PACKAGE_DIR = Path(omnipipe.__file__).parent

# Lower layers never import higher ones; one layer's units may import each other (but
# never in a cycle). The CLI layer is above all of these.
LAYERS: tuple[tuple[str, ...], ...] = (
    # 0 foundation: errors, YAML, small numeric and image helpers, output folders
    ("omnipipe", "errors", "safe_yaml", "geometry", "native", "memory", "image", "config",
     "survey", "output", "progress", "scratch", "spill", "handoff"),
    # 1 the contract's data classes: the calibration, report.json's records
    ("rig", "contract"),
    # 2 the camera models (one interface, CameraModel)
    ("camera",),
    # 3 files in: rig.yaml, recorded inputs, datasets
    ("rig_yaml", "inputs", "dataset"),
    # 4 parallel work
    ("executor",),
    # 5 the stages
    ("laser", "sfm", "model", "analysis", "report", "baseline", "calibrate"),
    # 6 tools around the stages: the simulator and the evaluation against ground truth
    ("sim", "evaluation"),
    # 7 the reconstruction pipeline that runs the stages
    ("pipeline",),
)
CLI_LAYER = len(LAYERS)
# Units of the CLI layer besides the modules that register sub-commands.
CLI_UNITS = ("cli", "cli_values")


def _modules() -> dict[str, tuple[Path, bool]]:
    """Dotted name -> (file, is a package ``__init__``) of every module of omnipipe."""
    out = {}
    for path in sorted(PACKAGE_DIR.rglob("*.py")):
        parts = list(path.relative_to(PACKAGE_DIR.parent).with_suffix("").parts)
        is_pkg = parts[-1] == "__init__"
        out[".".join(parts[:-1] if is_pkg else parts)] = (path, is_pkg)
    return out


def _type_checking_nodes(tree: ast.AST) -> set[int]:
    skip: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            for child in node.body:
                skip.update(id(n) for n in ast.walk(child))
    return skip


def _imports(modules: dict[str, tuple[Path, bool]]) -> dict[str, dict[str, tuple[int, bool]]]:
    """module -> {imported module: (line, names taken from a package's __init__)}."""
    graph: dict[str, dict[str, tuple[int, bool]]] = {}
    for name, (path, is_pkg) in modules.items():
        tree = ast.parse(path.read_text(encoding="utf-8"))
        skip = _type_checking_nodes(tree)
        package = name if is_pkg else name.rpartition(".")[0]
        out = graph.setdefault(name, {})
        for node in ast.walk(tree):
            if id(node) in skip:
                continue
            if isinstance(node, ast.Import):
                for alias in node.names:
                    if alias.name.split(".")[0] == "omnipipe":
                        out.setdefault(alias.name, (node.lineno, False))
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = package.split(".")[: len(package.split(".")) - node.level + 1]
                    target = ".".join(base + ([node.module] if node.module else []))
                else:
                    target = node.module or ""
                if target.split(".")[0] != "omnipipe":
                    continue
                for alias in node.names:
                    sub = f"{target}.{alias.name}"
                    if sub in modules:
                        out.setdefault(sub, (node.lineno, False))
                    else:
                        out.setdefault(target, (node.lineno, modules.get(target, (None, False))[1]))
    return graph


def _parents(name: str) -> set[str]:
    parts = name.split(".")
    return {".".join(parts[:i]) for i in range(1, len(parts))}


def _edges(graph: dict[str, dict[str, tuple[int, bool]]]) -> dict[str, set[str]]:
    """The run-time edges: each imported module and its packages not shared with the importer."""
    edges: dict[str, set[str]] = {}
    for name, targets in graph.items():
        out = edges.setdefault(name, set())
        for target in targets:
            if target != name:
                out.add(target)
            out.update(p for p in _parents(target) - _parents(name) - {name} if p != "omnipipe")
    return edges


def _cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    counter = 0
    for root in sorted(edges):
        if root in index:
            continue
        work = [(root, iter(sorted(edges.get(root, ()))))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is None:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[node])
                if low[node] == index[node]:
                    comp = []
                    while True:
                        top = stack.pop()
                        on_stack.discard(top)
                        comp.append(top)
                        if top == node:
                            break
                    if len(comp) > 1:
                        found.append(sorted(comp))
                continue
            if child not in edges:
                continue
            if child not in index:
                index[child] = low[child] = counter
                counter += 1
                stack.append(child)
                on_stack.add(child)
                work.append((child, iter(sorted(edges.get(child, ())))))
            elif child in on_stack:
                low[node] = min(low[node], index[child])
    return found


def _unit(name: str) -> str:
    parts = name.split(".")
    return parts[1] if len(parts) > 1 else parts[0]


def _layer(name: str) -> int:
    unit = _unit(name)
    if (unit in CLI_UNITS and name.count(".") == 1) or name in COMMAND_MODULES:
        return CLI_LAYER
    for layer, units in enumerate(LAYERS):
        if unit in units:
            return layer
    raise AssertionError(f"{name}: its unit {unit!r} has no layer in LAYERS (add it there)")


def test_import_graph_has_no_cycles() -> None:
    edges = _edges(_imports(_modules()))
    assert len(edges) > 50  # the package was really read
    cycles = _cycles(edges)
    assert not cycles, f"import cycles: {cycles}"


def test_no_import_runs_upward() -> None:
    modules = _modules()
    graph = _imports(modules)
    upward = []
    for name, targets in graph.items():
        own_package = name if modules[name][1] else name.rpartition(".")[0]
        is_cli = _layer(name) == CLI_LAYER
        for target, (line, from_init) in targets.items():
            if _layer(target) > _layer(name):
                upward.append(f"{name}:{line} imports {target} (a higher layer)")
            elif (
                from_init
                and not is_cli
                and target != name
                and target != "omnipipe"
                and (target == own_package or target in _parents(name))
            ):
                upward.append(f"{name}:{line} imports names of its package's __init__ {target}")
    assert not upward, "upward imports:\n" + "\n".join(upward)


def test_the_checks_see_a_cycle_and_an_upward_import() -> None:
    """The graph code itself: a cycle and the layers are found on a made-up graph."""
    edges = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert _cycles(edges) == [["a", "b", "c"]]
    assert _edges({"omnipipe.sfm.bundle": {"omnipipe.camera.factory": (1, False)}}) == {
        "omnipipe.sfm.bundle": {"omnipipe.camera.factory", "omnipipe.camera"}
    }
    assert _layer("omnipipe.rig") < _layer("omnipipe.camera.base") < _layer("omnipipe.laser.stage")
    assert _layer("omnipipe.pipeline.batch") == CLI_LAYER
