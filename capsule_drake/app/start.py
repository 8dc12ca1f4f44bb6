"""Where a run starts: the capsule let settle on the wall before the run (capsule.settle),
or where it rests on a colon that is not the procedural one; and the one place a
Simulator is made."""

from __future__ import annotations

import copy
import dataclasses
import sys

import numpy as np
from pydrake.common import RandomGenerator
from pydrake.common.eigen_geometry import Quaternion
from pydrake.math import RigidTransform
from pydrake.systems.analysis import ApplySimulatorConfig, Simulator, SimulatorConfig

from capsule_drake.anatomy import ColonSourceError, load_colon
from capsule_drake.anatomy.start_check import REST_SETTLE, pick_start
from capsule_drake.capsule.model import capsule_model
from capsule_drake.epm.paths import External, epm_start
from capsule_drake.epm.poses import stage_to_pose
from capsule_drake.epm.stage import Stage
from capsule_drake.scenario import CapsuleConfig, Scenario, ScenarioError
from capsule_drake.station import make_station


SETTLE_STEP = 5e-4
"""Plant step of the settling (s): where the capsule's first snap onto the wall, at
0.5-0.6 m/s, stays within 0.6 mm of it (docs/results/performance.md, "Time-step
convergence")."""


def simulator_for(diagram, config: SimulatorConfig | None = None, random_seed: int | None = None):
    """A Simulator of `diagram` with Drake's SimulatorConfig applied and, if given, the
    diagram's random context seeded: the one place a Simulator is made."""
    simulator = Simulator(diagram)
    if config is not None:
        ApplySimulatorConfig(config, simulator)
    if random_seed is not None:
        diagram.SetRandomContext(simulator.get_mutable_context(), RandomGenerator(random_seed))
    return simulator


def settled_start(scenario: Scenario) -> RigidTransform:
    """Where the capsule comes to rest when let settle (capsule.settle): the pose of
    `settled_state`. The run then starts there, at rest."""
    state = settled_state(scenario)
    return RigidTransform(Quaternion(state[:4] / np.linalg.norm(state[:4])), state[4:7])


def settled_state(scenario: Scenario) -> np.ndarray:
    """The capsule's state [q_WB (wxyz), p_WB, w_WB, v_WB] after it was let settle
    (capsule.settle), the first stage of such a run: the scenario's physics alone (its
    colon, contact, magnets; no sensors, no driver) simulated for `capsule.settle` seconds
    at SETTLE_STEP, the capsule starting on the centreline and the EPM held, on the
    kinematic stage, at the pose the run starts it at. Cached: runs of the same physics
    settle once per process."""
    physics = copy.deepcopy(scenario)
    physics.capsule = CapsuleConfig(start_s=scenario.capsule.start_s,
                                    ipm=scenario.capsule.ipm)
    physics.pseudo_force = None
    physics.epm.mount, physics.epm.driver = Stage(), External()
    physics.plant.time_step = SETTLE_STEP
    colon, _ = load_colon(scenario.colon)
    epm_pose = stage_to_pose(epm_start(scenario.epm, colon, scenario.capsule.start_s))
    key = (repr(physics), scenario.capsule.settle, tuple(epm_pose))
    if key not in _SETTLED:
        diagram = make_station(physics)
        simulator = simulator_for(diagram)
        context = simulator.get_mutable_context()
        diagram.GetInputPort("epm.command").FixValue(context, epm_pose)
        simulator.AdvanceTo(scenario.capsule.settle)
        if len(_SETTLED) >= 16:
            _SETTLED.clear()
        _SETTLED[key] = np.array(diagram.GetOutputPort("capsule.state").Eval(context))
    return _SETTLED[key].copy()


def start_where_it_rests(scenario: Scenario) -> Scenario:
    """The scenario with the capsule starting where it rests, on a colon that is not the
    procedural one (an imported mesh, the ex vivo segment): such a colon lies as its mesh
    was made, and the centreline at capsule.start_s may be no place to start (the imported
    tube of docs/guides/import-colon.md: the EPM 11 cm above its axis threw the capsule onto
    the roof at 2.2 m/s). The import's start check (anatomy/start_check.py `pick_start`)
    lets the capsule settle at capsule.start_s and, if it does not rest there, at up to five
    other starts, and keeps the first where it rests; the run then starts settled there
    (capsule.settle at least REST_SETTLE). A procedural colon's scenario is returned as it
    is.

    Raises:
        ScenarioError: the capsule rests at none of the starts (one line, what happened at
            each).
    """
    if scenario.colon.procedural:
        return scenario
    try:
        colon, _ = load_colon(scenario.colon)
    except ColonSourceError as e:
        raise ScenarioError(f"scenario: {e}") from None
    model = capsule_model()
    settle = max(scenario.capsule.settle, REST_SETTLE)

    def settled(start_s):
        capsule = dataclasses.replace(scenario.capsule, start_s=start_s, settle=settle)
        return settled_state(dataclasses.replace(scenario, capsule=capsule))

    try:
        start_s, note = pick_start(colon, scenario.capsule.start_s, model.radius,
                                   model.length + 2.0 * model.radius, settled)
    except ValueError as e:
        raise ScenarioError(f"scenario: {e}") from None
    if note:
        print(f"capsule-sim: note: {note}", file=sys.stderr)
    capsule = dataclasses.replace(scenario.capsule, start_s=start_s, settle=settle)
    return dataclasses.replace(scenario, capsule=capsule)


_SETTLED: dict = {}
