"""Every file path the README, the docs and the code's docstrings and comments name exists
(a path under one of the repository's folders, or a module path under capsule_drake/, as
`anatomy/lesions.py`), so that a renamed or removed file leaves no reference behind.
Paths given as where to write (after `--out`) are not references."""

import ast
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
