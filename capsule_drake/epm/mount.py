"""The EPM in a station: its carrier (stage or arm), where it starts, and its pose.

Two blocks: `epm.mount` (!Stage or !Arm) adds the carrier's model before the plant is
finalised (`add_epm_models`) and after it (`add_epm_mount`) starts it where its driver begins
(paths.py, `epm_start`) and puts the EPM's guard (`epm_guard`) before it; `epm.pose` adds
`epm_pose` ([p_WE, m_hat_W] from the plant). The driver (epm.driver in the scenario) is a
block of its own that commands it: a pose-command driver connects to
`parts.epm.command_input(builder, parts)`, the guard's input, whose safe command goes on to
the carrier, so that no driver's command (a user's plug-in, an !External input) reaches the
carrier unguarded. A path driver (!AlongColon, !HoldAbove) drives the carrier's joints with
its trajectory, built on the clearance floor (epm/poses.py), and sends no pose command.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.systems.framework import LeafSystem

from capsule_drake.blocks import block, checked
from capsule_drake.epm.arm import Arm, ArmMount, check_arm_config
from capsule_drake.epm.clearance import (CLEARANCE_TOLERANCE, EpmClearanceWatch,
                                        largest_pull)
from capsule_drake.epm.guard import (EpmCommandGuard, EpmGuard, command_workspace,
                                    floor_guard)
from capsule_drake.epm.paths import epm_start
from capsule_drake.epm.poses import stage_to_pose
from capsule_drake.epm.shaping import EpmPathShaper
from capsule_drake.epm.stage import (KinematicStageMount, Stage, StageMount, check_stage,
                                    check_stage_servo)
from capsule_drake.physics.magnetics import check_magnet_geometry
from capsule_drake.schema import need_range

EPM_BODY = "epm"


@dataclasses.dataclass
class EpmParts:
    """The EPM as the blocks after its mount see it."""

    magnet: object           # MagnetGeometry
    clearance: float         # smallest gap between the magnet and the skin (m)
    mount: object            # KinematicStageMount, StageMount or ArmMount
    instance: object         # the carrier's model instance (None: not in the plant)
    guard: EpmGuard          # the clearance floor (lowest_centre_height(x, y, m_hat))
    start_joints: np.ndarray = None    # the stage joints [x y z yaw pitch] at the start
    start_command: np.ndarray = None   # [p_WE, m_hat_W] at the start
    command_guard: object = None   # the EpmCommandGuard every pose command passes through
    driven: bool = False           # a pose-command driver is connected (command_input)

    def command_input(self, builder, parts):
        """The input a pose-command driver connects its [p_WE, m_hat_W] to: the guard's,
        whose safe command goes through the path shaper (`epm_path_shaper`, shaping.py: a
        path clear of the skin, at speeds the carrier can follow) to the carrier; exports
        the shaped command as epm.reference. One driver per EPM (a second one raises)."""
        if self.driven:
            raise RuntimeError("the EPM already has a pose-command driver")
        self.driven = True
        self.command_guard.watch()
        shaper = builder.AddNamedSystem("epm_path_shaper", EpmPathShaper(
            self.guard.lowest_centre_heights, self.mount.motion_limits(), self.start_command,
            period=parts.plant.time_step()))
        builder.Connect(self.command_guard.GetOutputPort("epm_command"),
                        shaper.GetInputPort("epm_command"))
        builder.Connect(shaper.GetOutputPort("epm_command"),
                        self.mount.carrier_input(builder, parts))
        parts.export(shaper.GetOutputPort("epm_command"), "epm.reference")
        return self.command_guard.GetInputPort("epm_command")


MAX_CLEARANCE = 0.5
"""Farthest the EPM may be kept from the skin (m): at 0.5 m its pull on the capsule is
~1e-4 of what it is at the working 10-15 cm, and the arm reaches 0.9 m."""


def check_epm_mount(mount, scenario) -> None:
    """The EPM's magnet, its clearance and its carrier."""
    epm = scenario.epm
    checked("epm.magnet.", check_magnet_geometry, epm.magnet)
    checked("", need_range, epm.clearance, "epm.clearance", f"[0, {MAX_CLEARANCE:g}]", "m",
            "farther, the EPM barely pulls the capsule")
    if isinstance(mount, Arm):
        checked("", check_arm_config, mount)
    else:
        checked("epm.mount.", check_stage, mount)
        if not mount.kinematic:
            pull, twist = largest_pull(epm.magnet, scenario.capsule.ipm, epm.clearance)
            checked("epm.mount: ", check_stage_servo, mount, pull, twist, epm.magnet,
                    CLEARANCE_TOLERANCE)


def add_epm_models(parts, mount):
    """Before Finalize: the carrier (!Stage or !Arm); sets parts.epm."""
    epm = parts.scenario.epm
    if isinstance(mount, Arm):
        carrier = ArmMount(mount)
    elif mount.kinematic:
        carrier = KinematicStageMount(mount)
    else:
        carrier = StageMount(mount)
    instance = carrier.add_models(parts.plant, parts.parser)
    parts.epm = EpmParts(epm.magnet, epm.clearance, carrier, instance,
                         floor_guard(parts.colon.abdomen, epm.magnet, epm.clearance))


def add_epm_mount(builder, parts, mount):
    """After Finalize: the carrier starts where the driver begins (paths.py, `epm_start`),
    and the guard (`epm_guard`, EpmCommandGuard: the clearance floor of parts.epm.guard, the
    workspace around the colon) waits for a pose command; exports epm.guard_counts
    (guard.GUARD_COUNTS). Sets parts.epm.start_joints, start_command and command_guard."""
    epm = parts.epm
    epm.start_joints = epm_start(parts.scenario.epm, parts.colon, parts.start_s)
    epm.start_command = stage_to_pose(epm.start_joints)
    epm.mount.connect(builder, parts, epm.start_joints)
    epm.command_guard = builder.AddNamedSystem("epm_guard", EpmCommandGuard(
        epm.guard, command_workspace(parts.colon), epm.start_command,
        period=parts.plant.time_step()))
    parts.export(epm.command_guard.GetOutputPort("counts"), "epm.guard_counts")


for _mount in (Stage, Arm):
    block("epm.mount", _mount, check=check_epm_mount, models=add_epm_models,
          where="")(add_epm_mount)


@block("epm.pose")
def add_epm_pose(builder, parts, scenario):
    """`epm_pose`: the EPM's centre and moment direction, exported as epm.pose (the
    kinematic stage's own pose output, or read from the plant's body poses); and the watch
    on its clearance (`epm_clearance_watch`, clearance.py), which ends a simulation whose
    magnet, where it is, comes inside its clearance."""
    if parts.epm.instance is None:
        pose_output = parts.epm.mount.pose_output()
    else:
        plant = parts.plant
        pose = builder.AddNamedSystem("epm_pose", MagnetPose(
            plant, plant.GetBodyByName(EPM_BODY, parts.epm.instance)))
        builder.Connect(plant.get_body_poses_output_port(), pose.GetInputPort("body_poses"))
        pose_output = pose.GetOutputPort("pose")
    parts.export(pose_output, "epm.pose")
    watch = builder.AddNamedSystem("epm_clearance_watch", EpmClearanceWatch(
        parts.colon.abdomen, parts.epm.magnet, parts.epm.clearance))
    builder.Connect(pose_output, watch.GetInputPort("epm_pose"))


class MagnetPose(LeafSystem):
    """[p_WM (3), m_hat_W (3)]: a magnet body's centre and moment direction, from the
    plant's body poses (the moment along the body's `axis_B`)."""

    def __init__(self, plant, body, axis_B=(0.0, 0.0, 1.0)):
        super().__init__()
        self._index = int(body.index())
        self._axis_B = np.asarray(axis_B, dtype=float)
        self._poses = self.DeclareAbstractInputPort(
            "body_poses", AbstractValue.Make([RigidTransform()] * plant.num_bodies()))
        self.DeclareVectorOutputPort("pose", 6, self._calc)

    def _calc(self, context, output):
        X_WB = self._poses.Eval(context)[self._index]
        output.SetFromVector(np.concatenate([X_WB.translation(),
                                             X_WB.rotation().matrix() @ self._axis_B]))
