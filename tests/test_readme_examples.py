"""The examples of the README and the docs (docs/), run as written.

Every code block is fenced and says its language: `python` and `bash` blocks are examples,
`text` blocks are diagrams and synopses. Each Python block runs, as it stands, in a Python
of its own (in an empty folder); a shell block runs there too (its `./capsule-sim` is this
checkout's command) when its marker says what it exits with. A block that cannot run in a
test (it opens a browser, runs for minutes, needs the user's own file) carries a marker
saying so and why, and is still checked: Python compiles, the shell parses (`bash -n`),
and each `./capsule-sim` command's flags are the command's own.

The marker is an HTML comment on the line before the block's fence:
    <!-- example: exits 1 -->               run; the exit status it must end with
    <!-- example: not run: REASON -->       not run, for REASON (a few words at least)

And a call written inline, a capsule_drake class with literal arguments only
(`MagneticForce(field_model="finite")`), is made as written: it must not raise.
"""

import ast
import dataclasses
import importlib
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCUMENTS = [ROOT / "README.md"] + sorted((ROOT / "docs").rglob("*.md"))
LANGUAGES = ("python", "bash", "text")
FENCE = re.compile(r"^(\s*)```(\S*)\s*$")
MARKER = re.compile(r"^\s*<!--\s*example:\s*(.*?)\s*-->\s*$")
# A run example's own time (the Default scenario's station is built in each).
TIMEOUT = 600


@dataclasses.dataclass
class Block:
    document: str
    line: int           # of the opening fence, from 1
    language: str
    code: str
    marker: str | None  # the text of its `example:` marker, if any

    @property
    def name(self) -> str:
        return f"{self.document}:{self.line}:{self.language}"

    @property
    def not_run(self) -> str | None:
        """The reason it is not run, or None."""
        if self.marker and self.marker.startswith("not run"):
            return self.marker.removeprefix("not run").lstrip(":").strip()
        return None

    @property
    def exits(self) -> int | None:
        match = re.fullmatch(r"exits (\d+)", self.marker or "")
        return int(match.group(1)) if match else None


def blocks(text: str, document: str) -> list[Block]:
    """The fenced code blocks of a Markdown text, with the marker before each."""
    lines = text.splitlines()
    out, k = [], 0
    while k < len(lines):
        match = FENCE.match(lines[k])
        if not match:
            k += 1
            continue
        indent, language = len(match.group(1)), match.group(2)
        end = next((j for j in range(k + 1, len(lines))
                    if lines[j].strip() == "```"), len(lines))
        code = "\n".join(line[indent:] for line in lines[k + 1:end]) + "\n"
        before = next((lines[j] for j in range(k - 1, -1, -1) if lines[j].strip()), "")
        marker = MARKER.match(before)
        out.append(Block(document, k + 1, language, code, marker.group(1) if marker else None))
        k = end + 1
    return out


def indented_code(text: str) -> list[int]:
    """Lines (from 1) that open an indented code block outside fences and lists: after a
    blank line, indented four spaces more than the list item around them (none: 0)."""
    found, fenced, list_indent, blank = [], False, 0, True
    for number, line in enumerate(text.splitlines(), 1):
        if FENCE.match(line):
            fenced = not fenced
            continue
        if fenced:
            continue
        if not line.strip():
            blank = True
            continue
        indent = len(line) - len(line.lstrip())
        item = re.match(r"^(\s*)([-*+]|\d+[.)])\s+", line)
        if blank and indent >= list_indent + 4 and not item:
            found.append(number)
        if item:
            list_indent = len(item.group(0))
        elif indent < list_indent:
            list_indent = 0 if indent == 0 else indent
        blank = False
    return found


def all_blocks() -> list[Block]:
    return [b for path in DOCUMENTS
            for b in blocks(path.read_text(), str(path.relative_to(ROOT)))]


EXAMPLES = [b for b in all_blocks() if b.language in ("python", "bash")]


def _marks(block: Block):
    runs = block.not_run is None and (block.language == "python" or block.exits is not None)
    return [pytest.mark.slow] if runs else []


def test_every_code_block_is_fenced_with_its_language():
    problems = []
    for path in DOCUMENTS:
        text = path.read_text()
        name = str(path.relative_to(ROOT))
        problems += [f"{b.name}: fenced without one of {LANGUAGES}"
                     for b in blocks(text, name) if b.language not in LANGUAGES]
        problems += [f"{name}:{line}: an indented code block (fence it, with its language)"
                     for line in indented_code(text)]
        problems += [f"{name}: an `example:` marker that is neither 'exits N' nor "
                     f"'not run: REASON': {b.marker!r}"
                     for b in blocks(text, name) if b.marker is not None
                     and b.exits is None and b.not_run is None]
    assert not problems, "\n".join(problems)


def test_the_extraction_finds_blocks_markers_and_indented_code():
    text = ("Intro.\n\n    ./capsule-sim run\n\n- a list item\n  continued\n\n"
            "<!-- example: not run: it opens a browser -->\n```bash\n./capsule-sim notebooks\n"
            "```\n\n  ```python\n  print(1)\n  ```\n")
    found = blocks(text, "x.md")
    assert [(b.language, b.code, b.not_run) for b in found] == [
        ("bash", "./capsule-sim notebooks\n", "it opens a browser"), ("python", "print(1)\n", None)]
    assert indented_code(text) == [3]
    assert len(EXAMPLES) >= 3  # the README's and the docs' own: not an empty parametrisation


@pytest.mark.parametrize("block", [pytest.param(b, marks=_marks(b), id=b.name)
                                   for b in EXAMPLES])
def test_each_example_runs_as_written_or_says_why_not(block, tmp_path):
    if block.not_run is not None:
        assert len(block.not_run.split()) >= 3, f"{block.name}: say why it is not run"
        _check_without_running(block)
        return
    if block.language == "python":
        done = subprocess.run([sys.executable, "-c", block.code], cwd=tmp_path,
                              capture_output=True, text=True, timeout=TIMEOUT)
        assert done.returncode == 0, f"{block.name}:\n{block.code}\n{done.stderr[-3000:]}"
        return
    assert block.exits is not None, (
        f"{block.name}: a shell block needs a marker: 'exits N' to run it, or "
        "'not run: REASON'")
    _check_without_running(block)
    shim = tmp_path / "capsule-sim"
    shim.write_text(f'#!/bin/sh\nexec "{sys.executable}" -m capsule_drake.app.entry "$@"\n')
    shim.chmod(0o755)
    done = subprocess.run(["bash", "-c", block.code], cwd=tmp_path, capture_output=True,
                          text=True, timeout=TIMEOUT)
    assert done.returncode == block.exits, (
        f"{block.name}: exit {done.returncode}, not {block.exits}\n{done.stderr[-3000:]}")


def _check_without_running(block: Block) -> None:
    """Python compiles; the shell parses, and each `./capsule-sim` command's flags are
    the command's own (argparse, nothing run)."""
    if block.language == "python":
        compile(block.code, block.name, "exec")
        return
    done = subprocess.run(["bash", "-n"], input=block.code, capture_output=True, text=True)
    assert done.returncode == 0, f"{block.name}: {done.stderr}"
    from capsule_drake.app.cli_parser import _parser

    for command in _commands(block.code):
        words = shlex.split(command, comments=True)
        if words and words[0] == "./capsule-sim":
            try:
                _parser().parse_args(words[1:])
            except SystemExit as e:
                pytest.fail(f"{block.name}: {command!r} is refused by the command line "
                            f"(exit {e.code})")


def _commands(code: str) -> list[str]:
    """The block's commands, continuation lines joined."""
    return [c for c in code.replace("\\\n", " ").splitlines() if c.strip()]


# --- Calls written inline ------------------------------------------------------------------

INLINE_CALL = re.compile(r"`([A-Z]\w*\((?:[^`()]|\([^`()]*\))*\))`")


def _defined(name: str):
    """The capsule_drake class or function `name` is (by its definition in the package's
    source), or None."""
    pattern = re.compile(rf"^(?:class {name}\b|{name} = )", re.M)
    for path in sorted((ROOT / "capsule_drake").rglob("*.py")):
        if pattern.search(path.read_text()):
            module = ".".join(path.relative_to(ROOT).with_suffix("").parts)
            return getattr(importlib.import_module(module), name, None)
    return None


def inline_call_failures(text: str, document: str) -> list[str]:
    """Each inline call of a capsule_drake class with literal arguments, made: what it
    raised."""
    failures = []
    for match in INLINE_CALL.finditer(text):
        call = ast.parse(match.group(1), mode="eval").body
        if not isinstance(call, ast.Call) or not isinstance(call.func, ast.Name):
            continue
        try:
            args = [ast.literal_eval(a) for a in call.args]
            kwargs = {k.arg: ast.literal_eval(k.value) for k in call.keywords}
        except ValueError:
            continue  # not literal: a call's shape in prose, not something to run
        target = _defined(call.func.id)
        if target is None:
            continue
        line = text.count("\n", 0, match.start()) + 1
        try:
            target(*args, **kwargs)
        except Exception as e:
            failures.append(f"{document}:{line}: {match.group(1)} raises "
                            f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}")
    return failures


def test_inline_calls_with_literal_arguments_run_as_written():
    failures = []
    for path in DOCUMENTS:
        failures += inline_call_failures(path.read_text(), str(path.relative_to(ROOT)))
    assert not failures, "\n".join(failures)


def test_an_inline_call_that_raises_is_found():
    # The finite-size magnets' text (then the README's, now docs/models/magnets.md) once
    # read `MagneticForce(field_model="finite")`, which lacks the plant and the magnets.
    failures = inline_call_failures('as `MagneticForce(field_model="finite")` or '
                                    '`MagnetGeometry(shape="sphere", dimensions=[0.01])`',
                                    "x.md")
    assert len(failures) == 1 and "MagneticForce" in failures[0] and "TypeError" in failures[0]
