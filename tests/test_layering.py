"""The package's layering, read from its source with ast: no import circles, no imports of the
package's own modules inside functions, the station built only by the runners, station.py
short."""

import ast
from pathlib import Path

PACKAGE_DIR = Path(__file__).resolve().parents[1] / "capsule_drake"

# The application layer (capsule_drake/app/): the only modules that may import the station
# (they run whole stations; everything else is a block the station adds, or works without
# a station).
STATION_MAX_LINES = 300


def module_name(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE_DIR.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {module_name(path): path for path in sorted(PACKAGE_DIR.rglob("*.py"))}
APP = {module for module in MODULES if module.startswith("capsule_drake.app")}


def imported_modules(node, module: str, is_package: bool) -> list[str]:
    """The capsule_drake modules an Import/ImportFrom node imports: `from a.b import c` is
    module a.b.c if that is a module, else a.b (a name from a.b, e.g. its __init__)."""
    if isinstance(node, ast.Import):
        names = [alias.name for alias in node.names]
    else:
        base = node.module or ""
        if node.level:  # relative: from the module's package, `level - 1` packages up
            package = module.split(".") if is_package else module.split(".")[:-1]
            package = package[:len(package) - (node.level - 1)]
            base = ".".join(package + ([base] if base else []))
        names = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in MODULES else base
                 for alias in node.names]
    return sorted({name for name in names if name.split(".")[0] == "capsule_drake"})


def imports_of(path: Path):
    """(lineno, imported module, at_top_level) of every capsule_drake import in a module;
    at_top_level is False inside a def or class body (it runs when that is called or
    defined, not when the module is imported at its top)."""
    module = module_name(path)
    is_package = path.name == "__init__.py"
    found = []

    def visit(node, top):
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.Import, ast.ImportFrom)):
                for target in imported_modules(child, module, is_package):
                    found.append((child.lineno, target, top))
            inner = top and not isinstance(
                child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef, ast.Lambda))
            visit(child, inner)

    visit(ast.parse(path.read_text(), str(path)), True)
    return found


def import_graph(top_level_only: bool) -> dict[str, set[str]]:
    """module -> the capsule_drake modules it imports. Importing a.b.c also runs the
    __init__ of package a.b (unless the importer is inside a.b, which is then already
    being imported): that is an edge too."""
    graph = {}
    for module, path in MODULES.items():
        edges = set()
        for _, target, top in imports_of(path):
            if top_level_only and not top:
                continue
            edges.add(target)
            parts = target.split(".")
            for i in range(2, len(parts)):
                package = ".".join(parts[:i])
                if not (module == package or module.startswith(package + ".")):
                    edges.add(package)
        graph[module] = edges - {module}
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import circle (a list of modules, the first repeated at the end), or None."""
    state, stack = {}, []

    def visit(node):
        state[node] = "open"
        stack.append(node)
        for target in sorted(graph.get(node, ())):
            if state.get(target) == "open":
                return stack[stack.index(target):] + [target]
            if target not in state:
                cycle = visit(target)
                if cycle:
                    return cycle
        stack.pop()
        state[node] = "done"
        return None

    for node in sorted(graph):
        if node not in state:
            cycle = visit(node)
            if cycle:
                return cycle
    return None


def test_the_import_graph_is_read():
    # The checks below are not vacuous: the modules are found and their imports resolved.
    graph = import_graph(top_level_only=True)
    assert {"capsule_drake.station", "capsule_drake.scenario", "capsule_drake.app.cli",
            "capsule_drake.app.run", "capsule_drake.anatomy"} <= set(graph)
    assert "capsule_drake.station" in graph["capsule_drake.app.run"]
    assert "capsule_drake.anatomy.source" in graph["capsule_drake.anatomy"]  # the __init__
    assert all(target in MODULES for edges in graph.values() for target in edges)
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set()}) is None


def test_no_import_circles():
    cycle = find_cycle(import_graph(top_level_only=True))
    assert cycle is None, "import circle: " + " -> ".join(cycle)


def test_no_imports_of_the_package_inside_functions():
    # Lazy imports of other packages' heavy optional dependencies are fine; the package's
    # own modules are imported at the top, where the import graph shows them.
    lazy = [f"{path.relative_to(PACKAGE_DIR.parent)}:{line} imports {target}"
            for module, path in MODULES.items()
            for line, target, top in imports_of(path) if not top]
    assert not lazy, "capsule_drake imported inside a function or class:\n" + "\n".join(lazy)


def test_only_the_app_imports_the_station_and_only_the_entry_imports_the_cli():
    graph = import_graph(top_level_only=False)  # an import anywhere in a module counts
    station = sorted(m for m, edges in graph.items() if "capsule_drake.station" in edges)
    assert set(station) <= APP, (
        f"capsule_drake.station imported by {station}; only the application layer "
        f"(capsule_drake/app/) may build whole stations")
    # The command's entry point (it takes the signals first, then imports the CLI).
    cli = sorted(m for m, edges in graph.items() if "capsule_drake.app.cli" in edges)
    assert cli == ["capsule_drake.app.entry"], f"capsule_drake.app.cli imported by {cli}"


def test_station_is_short():
    lines = len((PACKAGE_DIR / "station.py").read_text().splitlines())
    assert lines < STATION_MAX_LINES, f"station.py has {lines} lines"


# The layers from the top: each module may import only modules of its own layer or below.
# A block (everything not listed) is below the scenario, which collects the blocks' configs;
# the station is above the scenario; the application layer above the station.
LAYERS = [
    APP,   # the run loop, record, benchmark, Gymnasium environment, writers, the CLI
    {"capsule_drake.station"},
    {"capsule_drake.scenario"},
]


def test_no_block_imports_a_layer_above_it():
    graph = import_graph(top_level_only=False)
    upward = []
    for level, layer in enumerate(LAYERS):
        assert layer <= set(MODULES), layer - set(MODULES)
        below = set(MODULES) - set().union(*LAYERS[:level + 1])
        upward += [f"{module} imports {target}" for module in sorted(below)
                   for target in sorted(graph[module] & layer)]
    assert not upward, "imports from a lower layer to a higher one:\n" + "\n".join(upward)


SIMULATOR_MAKER = "capsule_drake.app.start"
"""The one module that constructs a Simulator (`simulator_for`): every run, the settling of a
start and the teleoperation bench step their diagram through it."""


def simulator_constructions(path: Path) -> list[int]:
    """Lines of a module where a pydrake Simulator is constructed (`Simulator(...)`, also
    as `analysis.Simulator(...)` or `Simulator_[T](...)`)."""
    lines = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if not isinstance(node, ast.Call):
            continue
        func = node.func.value if isinstance(node.func, ast.Subscript) else node.func
        name = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", "")
        if name in ("Simulator", "Simulator_"):
            lines.append(node.lineno)
    return lines


def test_a_simulator_is_constructed_in_one_module(tmp_path):
    sample = tmp_path / "sample.py"
    sample.write_text("a = Simulator(d)\nb = analysis.Simulator_[float](d)\nc = Simulatorx(d)\n")
    assert simulator_constructions(sample) == [1, 2]   # the check is not vacuous
    found = {module: lines for module, path in MODULES.items()
             if (lines := simulator_constructions(path))}
    assert set(found) == {SIMULATOR_MAKER}, (
        "Simulator constructed outside " + SIMULATOR_MAKER + ": "
        + ", ".join(f"{m}:{lines}" for m, lines in found.items() if m != SIMULATOR_MAKER))
    assert len(found[SIMULATOR_MAKER]) == 1
