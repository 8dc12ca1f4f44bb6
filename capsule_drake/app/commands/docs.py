"""`capsule-sim docs`: the documentation site, served on this machine or built to a folder."""

from __future__ import annotations

import importlib.util
import os
import sys
from pathlib import Path

from capsule_drake.scenario import ScenarioError
from capsule_drake.app.cli_parser import LOOPBACK


ROOT = Path(__file__).resolve().parents[3]
CONFIG = ROOT / "mkdocs.yml"


def mkdocs_command(args) -> list[str]:
    """The MkDocs command line for `args` (strict either way: a broken link, anchor or
    reference is an error)."""
    command = [sys.executable, "-m", "mkdocs"]
    if args.build:
        return command + ["build", "--strict", "--config-file", str(CONFIG),
                          "--site-dir", str(Path(args.out or ROOT / "site").resolve())]
    return command + ["serve", "--strict", "--config-file", str(CONFIG),
                      "--dev-addr", f"{args.host or LOOPBACK}:{args.port}"]


def _docs(args) -> int:
    """Replaces this process with MkDocs (it returns only on an error)."""
    if importlib.util.find_spec("mkdocs") is None or importlib.util.find_spec("material") is None:
        raise ScenarioError("MkDocs is not installed: ./capsule-sim docs installs it into "
                            ".venv; elsewhere run pip install -e '.[docs]' in the repository")
    if not CONFIG.is_file():
        raise ScenarioError(f"no mkdocs.yml at {CONFIG} (the site comes with the repository: "
                            "install it with pip install -e)")
    if args.out and not args.build:
        raise ScenarioError("--out names where --build writes the site; without --build the "
                            "site is served")
    command = mkdocs_command(args)
    sys.stdout.flush()
    os.chdir(ROOT)
    # The theme's banner about its successor, printed at every build, is not the user's news.
    os.environ.setdefault("NO_MKDOCS_2_WARNING", "1")
    os.execv(sys.executable, command)
    return 0
