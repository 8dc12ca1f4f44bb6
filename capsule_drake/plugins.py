"""Users' functions named "package.module:function" (lumen detectors, navigators).

A plug-in runs code: it is loaded only from where a user names one (the scenario keys
`epm.driver: !Plugin {factory: ...}` and `capsule.lumen_tracker.detector`, the benchmark's
`--navigators`), and the module and the file it comes from are printed on stderr before
it is imported, so that what runs is never a surprise.
"""

import importlib
import importlib.util
import sys

# Modules already announced (a scenario is checked at load and built later: one line).
_announced: set[str] = set()


def load_function(what: str, name: str, choices: str, announce: bool = True):
    """The function `name` names; ValueError in one line, naming `what` (e.g. "navigator")
    and the built-in `choices`, when it is malformed or cannot be found. With `announce`,
    prints "plug-in <what> <name>: <file>" on stderr before importing a module the first
    time."""
    module_name, _, attribute = name.partition(":")
    if not module_name or not attribute:
        raise ValueError(f"{what} {name!r} is not {choices} or 'package.module:function'")
    try:
        spec = importlib.util.find_spec(module_name)
    except (ImportError, ValueError) as e:
        raise ValueError(f"{what} {name!r}: cannot import {module_name!r} ({e})") from None
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
    except Exception as e:  # the module's own code failed as it was imported
        text = str(e).strip().splitlines()[0] if str(e).strip() else ""
        raise ValueError(f"{what} {name!r}: importing {module_name!r} failed "
                         f"({type(e).__name__}: {text})") from None
    function = getattr(module, attribute, None)
    if not callable(function):
        raise ValueError(f"{what} {name!r}: {module_name!r} has no function {attribute!r}")
    return function
