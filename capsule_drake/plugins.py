"""Users' functions named "package.module:function" (lumen detectors, navigators)."""

import importlib


def load_function(what: str, name: str, choices: str):
    """The function `name` names; ValueError in one line, naming `what` (e.g. "navigator")
    and the built-in `choices`, when it is malformed or cannot be found."""
    module_name, _, attribute = name.partition(":")
    if not module_name or not attribute:
        raise ValueError(f"{what} {name!r} is not {choices} or 'package.module:function'")
    try:
        module = importlib.import_module(module_name)
    except ImportError as e:
        raise ValueError(f"{what} {name!r}: cannot import {module_name!r} ({e})") from None
    function = getattr(module, attribute, None)
    if not callable(function):
        raise ValueError(f"{what} {name!r}: {module_name!r} has no function {attribute!r}")
    return function
