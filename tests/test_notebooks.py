"""Every notebook runs top to bottom (short mode), in a fresh interpreter, leaving no\ntemporary files; `capsule-sim notebooks` opens them in JupyterLab."""

import json
import os
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

NOTEBOOKS = sorted((Path(__file__).resolve().parents[1] / "notebooks").glob("*.ipynb"))


def notebook_source(path: Path) -> str:
    """The notebook's code cells as one script (the cells share one namespace, as in Jupyter)."""
    cells = json.loads(path.read_text())["cells"]
    return "\n\n".join("".join(c["source"]) for c in cells if c["cell_type"] == "code")


@pytest.mark.slow
@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.name)
def test_notebook_runs(path, tmp_path):
    for cell in json.loads(path.read_text())["cells"]:
        if cell["cell_type"] == "code":
            assert not cell["outputs"], f"{path.name}: commit notebooks with outputs cleared"
    script = tmp_path / (path.stem + ".py")
    script.write_text(notebook_source(path))
    # A temporary folder of its own: what a notebook leaves there, it leaves on a user's disk.
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    env = dict(os.environ, CAPSULE_NOTEBOOK_SHORT="1", MPLBACKEND="Agg", TMPDIR=str(scratch))
    proc = subprocess.run([sys.executable, str(script)], cwd=path.parent, env=env,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    left = sorted(p.name for p in scratch.iterdir())
    assert not left, f"{path.name} left {left} in the temporary folder"


def test_the_notebooks_verb_opens_jupyterlab_on_the_notebooks(monkeypatch):
    from capsule_drake.app import cli
    from capsule_drake.app.commands import notebooks
    started = []
    monkeypatch.setattr(notebooks.importlib.util, "find_spec", lambda name: object())
    monkeypatch.setattr(notebooks.os, "execv", lambda path, argv: started.append(argv))
    assert cli.main(["notebooks", "--no-browser", "--port", "8890"]) == 0
    argv, = started
    assert argv[:3] == [sys.executable, "-m", "jupyterlab"]
    assert f"--ServerApp.root_dir={NOTEBOOKS[0].parent}" in argv
    assert {"--ServerApp.ip=127.0.0.1", "--ServerApp.port=8890", "--no-browser"} <= set(argv)


def test_without_jupyterlab_the_notebooks_verb_says_how_to_install_it(monkeypatch, capsys):
    from capsule_drake.app import cli
    from capsule_drake.app.commands import notebooks
    monkeypatch.setattr(notebooks.importlib.util, "find_spec", lambda name: None)
    monkeypatch.setattr(notebooks.os, "execv", lambda *a: pytest.fail("nothing to start"))
    assert cli.main(["notebooks"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "pip install -e '.[notebooks]'" in err, err
    # ... which the project declares: JupyterLab and a kernel.
    with open(NOTEBOOKS[0].parents[1] / "pyproject.toml", "rb") as f:
        extra = tomllib.load(f)["project"]["optional-dependencies"]["notebooks"]
    assert {re.split(r"[<>=\[ ]", r)[0] for r in extra} >= {"jupyterlab", "ipykernel"}
