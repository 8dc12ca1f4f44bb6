"""Users' functions named "package.module:function" (lumen detectors, navigators).

A plug-in runs code: it is loaded only from where a user names one (the scenario keys
`epm.driver: !Plugin {factory: ...}` and `capsule.lumen_tracker.detector`, the benchmark's
`--navigators`), and the module and the file it comes from are printed on stderr before
it is imported, so that what runs is never a surprise.

A plug-in that breaks is named in the one line that reports it: one that cannot be imported
(it raised, or exited, as it was imported) is a ValueError here; one whose code raises or
exits as its run is built or simulated is found in the error's traceback (`culprit`), among
the plug-ins the run loaded (`noting_loads`).
"""

import contextlib
import importlib
import importlib.util
import os
import sys
import threading
import traceback

# Modules already announced (a scenario is checked at load and built later: one line).
_announced: set[str] = set()
# What a user's code may raise that is its failure, not the user's Ctrl-C: SystemExit too
# (sys.exit() in a plug-in), which `except Exception` lets through.
FAILURES = (Exception, SystemExit)
# The lists `noting_loads` blocks fill, per thread.
_noting = threading.local()


class PluginError(Exception):
    """A plug-in broke its interface as it ran (e.g. a detector's result that is not one);
    the message is one line naming it and what it did."""


def first_line(error: BaseException) -> str:
    """"ZeroDivisionError: <its message's first line>", or the type's name alone."""
    text = str(error).strip().splitlines()[0] if str(error).strip() else ""
    return f"{type(error).__name__}: {text}" if text else type(error).__name__


def what_it_did(error: BaseException) -> str:
    """"raised ZeroDivisionError: ...", or "exited (SystemExit: 0)" for a sys.exit()."""
    if isinstance(error, SystemExit):
        return f"exited ({first_line(error)})"
    return f"raised {first_line(error)}"


def read_only(array):
    """A read-only view of `array`, for a plug-in given what others see too (a frame, a
    mask): a write into it raises ValueError instead of changing it for them."""
    view = array.view()
    view.flags.writeable = False
    return view


@contextlib.contextmanager
def noting_loads():
    """Within the block, each plug-in `load_function` loads (in this thread) is noted in the
    list it yields, as (its module's file, "navigator 'package.module:function'", the
    function): a run notes those it builds with, to name the one whose code broke it."""
    if not hasattr(_noting, "stack"):
        _noting.stack = []
    loads: list[tuple[str, str, object]] = []
    _noting.stack.append(loads)
    try:
        yield loads
    finally:
        _noting.stack.remove(loads)


def failure_text(error: BaseException, loads=()) -> str:
    """One line on an error: a PluginError's message; "<the plug-in> raised X: ..." (or
    "exited ...") when the code of one of `loads` raised it (`culprit`); else "X: ..."."""
    if isinstance(error, PluginError):
        return str(error)
    plugin = culprit(error, loads)
    return f"{plugin} {what_it_did(error)}" if plugin else first_line(error)


def culprit(error: BaseException, loads=()) -> str | None:
    """The plug-in of `loads` (`noting_loads`) whose code is innermost in the error's
    traceback ("navigator 'package.module:function'"), or None. Plug-ins from the same
    module are told apart by their functions in the traceback, or all named."""
    frames = [frame for frame, _ in traceback.walk_tb(error.__traceback__)][::-1]
    for frame in frames:
        mine = [load for load in loads
                if load[0] == os.path.realpath(frame.f_code.co_filename)]
        if mine:
            codes = {f.f_code for f in frames}
            called = [load for load in mine if getattr(load[2], "__code__", None) in codes]
            return " or ".join(dict.fromkeys(name for _, name, _ in (called or mine)))
    return None


def load_function(what: str, name: str, choices: str, announce: bool = True):
    """The function `name` names; ValueError in one line, naming `what` (e.g. "navigator")
    and the built-in `choices`, when it is malformed or cannot be found. With `announce`,
    prints "plug-in <what> <name>: <file>" on stderr before importing a module the first
    time."""
    module_name, _, attribute = name.partition(":")
    if not module_name or not attribute:
        raise ValueError(f"{what} {name!r} is not {choices} or 'package.module:function'")
    try:
        spec = importlib.util.find_spec(module_name)  # imports the packages it is in
    except (ImportError, ValueError) as e:
        raise ValueError(f"{what} {name!r}: cannot import {module_name!r} ({e})") from None
    except FAILURES as e:  # a package's own code failed (or exited) as it was imported
        raise ValueError(f"{what} {name!r}: importing {module_name!r} failed "
                         f"({first_line(e)})") from None
    if spec is None:
        raise ValueError(f"{what} {name!r}: no module {module_name!r} on the Python path")
    if announce and name not in _announced:
        _announced.add(name)
        print(f"plug-in {what} {name}: loading {module_name} from "
              f"{spec.origin or 'a namespace package'}", file=sys.stderr)
    try:
        module = importlib.import_module(module_name)
    except ImportError as e:
        raise ValueError(f"{what} {name!r}: cannot import {module_name!r} ({e})") from None
    except FAILURES as e:  # the module's own code failed (or exited) as it was imported
        raise ValueError(f"{what} {name!r}: importing {module_name!r} failed "
                         f"({first_line(e)})") from None
    function = getattr(module, attribute, None)
    if not callable(function):
        raise ValueError(f"{what} {name!r}: {module_name!r} has no function {attribute!r}")
    if getattr(module, "__file__", None):
        for loads in getattr(_noting, "stack", ()):
            loads.append((os.path.realpath(module.__file__), f"{what} {name!r}", function))
    return function
