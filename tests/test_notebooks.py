"""Every notebook runs top to bottom (short mode), in a fresh interpreter."""

import json
import os
import subprocess
import sys
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
    env = dict(os.environ, CAPSULE_NOTEBOOK_SHORT="1", MPLBACKEND="Agg")
    proc = subprocess.run([sys.executable, str(script)], cwd=path.parent, env=env,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
