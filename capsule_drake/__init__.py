"""capsule_drake: magnetically actuated endoscopic capsules in the colon, as a Drake diagram."""

__version__ = "0.1.0"

# The Gymnasium environment (app/gym_env.py), registered by name: nothing of it (or
# of Drake) is imported until `gymnasium.make("capsule_drake/ColonNavigation-v0")`.
try:
    import gymnasium as _gymnasium
except ImportError:  # the simulator runs without it
    _gymnasium = None
if _gymnasium is not None and "capsule_drake/ColonNavigation-v0" not in _gymnasium.registry:
    _gymnasium.register(id="capsule_drake/ColonNavigation-v0",
                        entry_point="capsule_drake.app.gym_env:ColonNavigationEnv")
