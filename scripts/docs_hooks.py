"""The documentation site's hooks (mkdocs.yml): what the site shows that is made from the
code and the result files at build time, so that it cannot drift from them.

- The reference pages (reference/*.md): every scenario field, named scenario, block and
  port, command-line flag and benchmark column (capsule_drake/app/reference.py).
- The diagram's picture (diagram.svg): the station of WithSensors as built
  (capsule_drake/app/diagram_picture.py).
- The navigation tables of the results pages, where a page names the result files they
  come from (capsule_drake/app/benchmark/result_tables.py).
"""

import tempfile
from pathlib import Path

from mkdocs.structure.files import File

from capsule_drake.app.benchmark.result_tables import expand
from capsule_drake.app.diagram_picture import draw_scenario
from capsule_drake.app.reference import reference_pages

ROOT = Path(__file__).resolve().parents[1]
_made: dict[str, str | bytes] = {}   # made once per process (`mkdocs serve` rebuilds often)


def _generated() -> dict[str, str | bytes]:
    if not _made:
        _made.update(reference_pages())
        with tempfile.TemporaryDirectory() as folder:
            picture = Path(folder) / "diagram.svg"
            draw_scenario(picture)
            _made["diagram.svg"] = picture.read_bytes()
    return _made


def on_files(files, config):
    for path, content in _generated().items():
        files.append(File.generated(config, path, content=content))
    return files


def on_page_markdown(markdown, page, config, files):
    return expand(markdown, ROOT)
