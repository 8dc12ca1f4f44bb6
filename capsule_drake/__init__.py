"""capsule_drake: magnetically actuated endoscopic capsules in the colon, as a Drake diagram."""

import importlib.abc
import importlib.util
import sys

__version__ = "0.1.0"

GYM_ENV_ID = "capsule_drake/ColonNavigation-v0"
"""The Gymnasium environment (app/gym_env.py), registered by name: nothing of it (or of
Drake) is imported until `gymnasium.make(GYM_ENV_ID)`."""


def _register(gymnasium) -> None:
    if GYM_ENV_ID not in gymnasium.registry:
        gymnasium.register(id=GYM_ENV_ID, entry_point="capsule_drake.app.gym_env:ColonNavigationEnv")


class _RegisterWhenImported(importlib.abc.MetaPathFinder):
    """Registers the environment as soon as gymnasium is imported, by whoever imports it
    (before or after this package). Importing gymnasium here would cost every use of the
    package a third of a second, and the command line would start that much later to
    take its signals (app/entry.py)."""

    def find_spec(self, name, path=None, target=None):
        if name != "gymnasium":
            return None
        sys.meta_path.remove(self)   # once; the real finders find it
        spec = importlib.util.find_spec(name)
        if spec is not None and spec.loader is not None and hasattr(spec.loader, "exec_module"):
            load = spec.loader.exec_module

            def exec_module(module):
                load(module)
                _register(module)
            spec.loader.exec_module = exec_module
        return spec


if "gymnasium" in sys.modules:
    _register(sys.modules["gymnasium"])
elif not any(isinstance(finder, _RegisterWhenImported) for finder in sys.meta_path):
    sys.meta_path.insert(0, _RegisterWhenImported())
