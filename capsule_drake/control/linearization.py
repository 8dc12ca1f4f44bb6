"""The capsule and its magnet as a linearisable Drake diagram, the EPM's pose its input.

`capsule_magnet_diagram` builds: the capsule (models/capsule.sdf) free in space with gravity
and the colon's speed-proportional resistance (its floating joint's damping), and
`EpmWrench`, which applies the EPM's dipole force and torque at the capsule's magnet from
the exported input `epm_pose` [p_WE (3), m_hat_W (3)]. The EPM is a commanded pose, as the
stage or arm servo makes it. Every system is scalar-convertible and the discrete plant is
built with `use_sampled_output_ports=False`, so `Linearize` and
`FirstOrderTaylorApproximation` work on it (docs/sources.md section 6).

`hover_operating_point` gives the state and input at which the capsule hangs still, its
magnet along a heading, under the EPM (`analysis.hold_against_gravity`).
"""

from __future__ import annotations

import numpy as np
from pydrake.autodiffutils import AutoDiffXd
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform, RigidTransform_, RotationMatrix
from pydrake.multibody.math import SpatialForce_
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import (AddMultibodyPlant, ExternallyAppliedSpatialForce_,
                                     MultibodyPlantConfig)
from pydrake.multibody.tree import BodyIndex
from pydrake.systems.framework import DiagramBuilder, LeafSystem_
from pydrake.systems.scalar_conversion import TemplateSystem

from capsule_drake.capsule.model import CAPSULE_BODY
from capsule_drake.control.analysis import hold_against_gravity
from capsule_drake.lifetime import weak_method
from capsule_drake.models import configure_parser, model_url
from capsule_drake.scene_geometry import add_damped_capsule_joint
from capsule_drake.physics.magnetics import dipole_force, dipole_torque


@TemplateSystem.define("EpmWrench_", T_list=[float, AutoDiffXd])
def EpmWrench_(T):
    class Impl(LeafSystem_[T]):
        """The dipole force and torque of an EPM at a commanded pose on a magnet fixed to a
        plant body.

        .. pydrake_system::

            name: EpmWrench
            input_ports:
            - body_poses
            - epm_pose
            output_ports:
            - applied_spatial_force

        epm_pose: [p_WE, m_hat_W] (the EPM's centre and moment direction; normalised here).
        applied_spatial_force: one ExternallyAppliedSpatialForce on the body at the magnet.

        Args:
            body_index: the body carrying the magnet (int).
            p_BM: the magnet's centre in the body (3).
            m_B: its moment in the body (3, A m^2).
            epm_moment: the EPM's moment (A m^2).
        """

        def _construct(self, body_index, p_BM, m_B, epm_moment, converter=None):
            LeafSystem_[T].__init__(self, converter)
            self._args = (int(body_index), tuple(float(x) for x in p_BM),
                          tuple(float(x) for x in m_B), float(epm_moment))
            self._poses = self.DeclareAbstractInputPort(
                "body_poses", AbstractValue.Make([RigidTransform_[T]()]))
            self._epm = self.DeclareVectorInputPort("epm_pose", 6)
            self.DeclareAbstractOutputPort(
                "applied_spatial_force",
                lambda: AbstractValue.Make([ExternallyAppliedSpatialForce_[T]()]),
                weak_method(self._calc))

        def _construct_copy(self, other, converter=None):
            Impl._construct(self, *other._args, converter=converter)

        def _calc(self, context, output):
            body_index, p_BM, m_B, epm_moment = self._args
            X_WB = self._poses.Eval(context)[body_index]
            R = X_WB.rotation().matrix()
            p_WM = X_WB.translation() + R @ np.array(p_BM)
            m_W = R @ np.array(m_B)
            epm = self._epm.Eval(context)
            direction = epm[3:]
            m_E = epm_moment * direction / np.sqrt(direction @ direction)
            offset = p_WM - epm[:3]
            force = ExternallyAppliedSpatialForce_[T]()
            force.body_index = BodyIndex(body_index)
            force.p_BoBq_B = np.array(p_BM)
            force.F_Bq_W = SpatialForce_[T](dipole_torque(m_E, m_W, offset),
                                            dipole_force(m_E, m_W, offset))
            output.set_value([force])

    return Impl


EpmWrench = EpmWrench_[None]


def capsule_magnet_diagram(ipm_moment: float, epm_moment: float, time_step: float = 1e-3,
                           drag_translational: float = 2.0, drag_rotational: float = 6e-5):
    """(diagram, plant): the free capsule, gravity, the floating joint's damping (the
    colon's resistance, N s/m and N m s), and the EPM's wrench from the input `epm_pose`."""
    builder = DiagramBuilder()
    plant, _ = AddMultibodyPlant(MultibodyPlantConfig(
        time_step=time_step, use_sampled_output_ports=False), builder)
    configure_parser(Parser(plant)).AddModels(url=model_url("capsule.sdf"))
    capsule = plant.GetBodyByName(CAPSULE_BODY)
    add_damped_capsule_joint(plant, drag_translational, drag_rotational)
    plant.Finalize()
    X_B_ipm = plant.GetFrameByName("ipm").GetFixedPoseInBodyFrame()
    wrench = builder.AddNamedSystem("epm_wrench", EpmWrench(
        int(capsule.index()), X_B_ipm.translation(),
        ipm_moment * X_B_ipm.rotation().col(2), epm_moment))
    builder.Connect(plant.get_body_poses_output_port(), wrench.GetInputPort("body_poses"))
    builder.Connect(wrench.GetOutputPort("applied_spatial_force"),
                    plant.get_applied_spatial_force_input_port())
    builder.ExportInput(wrench.GetInputPort("epm_pose"), "epm_pose")
    builder.ExportOutput(plant.get_state_output_port(), "state")
    return builder.Build(), plant


def hover_operating_point(diagram, plant, p_WM, heading, epm_moment: float,
                          ipm_moment: float):
    """A context of `diagram` in which the capsule's magnet hangs still at p_WM, along the
    unit `heading` (horizontal), and the EPM pose (fixed on `epm_pose`) that holds it there
    against gravity. Returns (context, epm_pose)."""
    heading = np.asarray(heading, dtype=float)
    heading = heading / np.linalg.norm(heading)
    capsule = plant.GetBodyByName(CAPSULE_BODY)
    weight = capsule.default_mass() * float(np.linalg.norm(plant.gravity_field().gravity_vector()))
    p_E, m_hat = hold_against_gravity(p_WM, heading, weight, epm_moment, ipm_moment)
    # The body's z along the heading (the magnet's axis), x horizontal.
    x = np.cross([0.0, 0.0, 1.0], heading)
    x = x / np.linalg.norm(x)
    R_WB = RotationMatrix(np.column_stack([x, np.cross(heading, x), heading]))
    p_BM = plant.GetFrameByName("ipm").GetFixedPoseInBodyFrame().translation()
    context = diagram.CreateDefaultContext()
    plant_context = plant.GetMyContextFromRoot(context)
    plant.SetFreeBodyPose(plant_context, capsule,
                          RigidTransform(R_WB, np.asarray(p_WM) - R_WB @ p_BM))
    epm_pose = np.concatenate([p_E, m_hat])
    diagram.GetInputPort("epm_pose").FixValue(context, epm_pose)
    return context, epm_pose
