"""`capsule-sim notebooks`: JupyterLab on the repository's notebooks."""

from __future__ import annotations

import importlib.util
import os
import sys
from pathlib import Path

from capsule_drake.scenario import ScenarioError
from capsule_drake.app.cli_parser import LOOPBACK


NOTEBOOKS_DIR = Path(__file__).resolve().parents[3] / "notebooks"


def _notebooks(args) -> int:
    """Replaces this process with JupyterLab on notebooks/ (it returns only on an error)."""
    if importlib.util.find_spec("jupyterlab") is None:
        raise ScenarioError("JupyterLab is not installed: ./capsule-sim notebooks installs it "
                            "into .venv; elsewhere run pip install -e '.[notebooks]' in the "
                            "repository")
    if not NOTEBOOKS_DIR.is_dir():
        raise ScenarioError(f"no notebooks folder at {NOTEBOOKS_DIR} (the notebooks come with "
                            "the repository: install it with pip install -e)")
    command = [sys.executable, "-m", "jupyterlab", f"--ServerApp.root_dir={NOTEBOOKS_DIR}",
               f"--ServerApp.ip={args.host or LOOPBACK}", f"--ServerApp.port={args.port}"]
    if args.no_browser:
        command.append("--no-browser")
    if hasattr(os, "geteuid") and os.geteuid() == 0:
        command.append("--allow-root")  # a container's user (JupyterLab refuses root else)
    sys.stdout.flush()
    os.execv(sys.executable, command)
    return 0
