"""The navigation benchmark: seeded random colons x navigators, one table.

A run puts the capsule in the rectum of one seeded random colon (`colon.seed`) and lets one
navigator drive the EPM for up to `duration` simulated seconds, stopping early when the
capsule reaches the cecum (its centreline station within `CECUM_MARGIN` of the end). The
suite runs in parallel processes on this machine (`engine="local"`) or on a Dask cluster
(`engine="dask"`: a local cluster of `workers` processes, or an existing scheduler's
address), with a progress line, and gives the same table for the same seeds either way.
A run whose process crashes, that outlives its wall-time limit (`run_timeout`), or that an
error ended (a plug-in's that raised or exited, naming it) is a row marked failed with its
reason (`status`, `error`), and the suite goes on; Ctrl-C and the termination signals stop
every run's processes (the run's worker and its camera's render process), keeping the runs
that finished.

Navigators, each a named scenario whose `epm.driver` drives the EPM (diagrams/default.yaml),
all run through the one run loop (app/run.py `simulate`, which seeds the random context):
- "autonomy-truth" (scenario Navigation), "autonomy-detected" (NavigationDetected): the
  lumen follower (navigation/autonomy.py), steering from the lumen truth or from the lumen
  tracker on the camera's frames, on the capsule's true pose;
- "autonomy-sensors" (NavigationSensors): the follower on what the capsule senses, the
  tracker's lumen and the magnetic localiser's pose estimate, with finite-size magnets;
- "teleop-guided", "teleop-unguided": the simulated operator at the haptic device
  (scenario Teleop), with and without the pseudo-force on the hand;
- "package.module:function": a user's navigator (`!Plugin`; the interface is in
  navigation/plugin.py) on the task's scenario (default Navigation).
"""


from capsule_drake.app.benchmark.task import *  # noqa: F401,F403
from capsule_drake.app.benchmark.task import _detection_scores, _metrics  # noqa: F401
from capsule_drake.app.benchmark.pool import *  # noqa: F401,F403
from capsule_drake.app.benchmark.progress import *  # noqa: F401,F403
from capsule_drake.app.benchmark.tables import *  # noqa: F401,F403
