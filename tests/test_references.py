"""Every file path the README, the docs and the code's docstrings and comments name exists
(a path under one of the repository's folders, or a module path under capsule_drake/, as
`anatomy/lesions.py`), and every function named with its module, so that a renamed or
removed file or function leaves no reference behind.
Paths given as where to write (after `--out`) are not references."""

import ast
import importlib
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "capsule_drake"
FOLDERS = ["capsule_drake", "benchmarks", "tests", "docs", "models", "diagrams", "notebooks",
           "scripts", "examples"] + sorted(
    p.name for p in PACKAGE.iterdir() if p.is_dir() and not p.name.startswith("_"))
PATH = re.compile(r"(?<![\w/.~-])(?<!--out )(?<!--out=)((?:%s)/[\w./-]*\.(?:py|md|png|jpg|"
                  r"yaml|sdf|ipynb|obj|npz|json|csv))" % "|".join(FOLDERS))


def texts():
    """(file, text) of the README, the docs, and every Python file's docstrings and
    comments."""
    yield "README.md", (ROOT / "README.md").read_text()
    for path in sorted((ROOT / "docs").rglob("*.md")):
        yield str(path.relative_to(ROOT)), path.read_text()
    for folder in ("capsule_drake", "benchmarks", "tests", "scripts", "examples"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            source = path.read_text()
            tree = ast.parse(source)
            docs = [ast.get_docstring(node) for node in ast.walk(tree)
                    if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef,
                                         ast.AsyncFunctionDef))]
            comments = [line for line in source.splitlines() if line.strip().startswith("#")]
            yield str(path.relative_to(ROOT)), "\n".join([d for d in docs if d] + comments)


def test_every_named_file_exists():
    missing = []
    for where, text in texts():
        for match in PATH.finditer(text):
            name = match.group(1).rstrip(".")
            if not ((ROOT / name).exists() or (PACKAGE / name).exists()):
                missing.append(f"{where}: {name}")
    assert not missing, "\n".join(missing)


def test_the_check_finds_a_missing_file():
    found = [m.group(1) for m in PATH.finditer(
        "see anatomy/no_such_module.py and benchmarks/gone.py; --out docs/new.png")]
    assert found == ["anatomy/no_such_module.py", "benchmarks/gone.py"]
    assert not any((PACKAGE / f).exists() or (ROOT / f).exists() for f in found)


# A function or class named with its module unambiguously: the package's dotted path
# (`capsule_drake.physics.magnetics.dipole_field`), or a file path then the name
# (app/dataset.py's `state_time`, anatomy/start_check.py `pick_start`). A short dotted name
# (`station.add_camera_walls`) cannot be told from a port or a scenario key
# (`capsule.camera.label_image`) and is not checked.
DOTTED = re.compile(r"(?<![\w.])(capsule_drake(?:\.[A-Za-z_]\w*)+)")
FILE_THEN_NAME = re.compile(r"(?<![\w/.])((?:[a-z_]+/)*[a-z_]+\.py)(?:'s)? `([A-Za-z_][\w.]*)`")


def _module_for(path: str):
    """The capsule_drake module a file path names (`anatomy/lesions.py` or
    `capsule_drake/anatomy/lesions.py`), or None (a benchmark, a test)."""
    name = path.removeprefix("capsule_drake/")
    if not (PACKAGE / name).is_file():
        return None
    return "capsule_drake." + name.removesuffix(".py").replace("/", ".")


def _resolves(dotted: str) -> bool:
    """Whether `dotted` is a module, or a module then attributes that exist."""
    parts = dotted.split(".")
    for i in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:i]))
        except ImportError:
            continue
        for name in parts[i:]:
            if not hasattr(obj, name):
                return False
            obj = getattr(obj, name)
        return True
    return False


def test_every_named_function_exists():
    missing, checked = [], 0
    for where, text in texts():
        refs = [m.group(1).rstrip(".") for m in DOTTED.finditer(text)]
        for m in FILE_THEN_NAME.finditer(text):
            module = _module_for(m.group(1))
            if module is not None:
                refs.append(f"{module}.{m.group(2).rstrip('.')}")
        for ref in refs:
            checked += 1
            if not _resolves(ref):
                missing.append(f"{where}: {ref}")
    assert checked > 20
    assert not missing, "\n".join(missing)


def test_the_check_finds_a_missing_function():
    assert _resolves("capsule_drake.physics.magnetics.dipole_field")
    assert not _resolves("capsule_drake.physics.magnetics.no_such_function")
    assert not _resolves("capsule_drake.no_such_module.f")
    found = [m.groups() for m in FILE_THEN_NAME.finditer(
        "app/dataset.py's `state_time` and anatomy/start_check.py `pick_start`")]
    assert found == [("app/dataset.py", "state_time"), ("anatomy/start_check.py", "pick_start")]
