"""Meshcat: the scene, its contact forces, and the EPM's pose command."""

import numpy as np
from pydrake.geometry import (Cylinder, MeshcatVisualizer, MeshcatVisualizerParams, Rgba,
                              Sphere)
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.multibody.meshcat import ContactVisualizer, ContactVisualizerParams
from pydrake.systems.framework import EventStatus, LeafSystem


def add_meshcat(builder, parts, period: float):
    """Illustration geometry and contact forces in parts.meshcat, and (when something other
    than a path drives the EPM, or the arm carries it) a marker at the EPM's command; the
    view looks at the abdomen from the patient's right, above the table."""
    meshcat = parts.meshcat
    MeshcatVisualizer.AddToBuilder(builder, parts.scene_graph, meshcat,
                                   MeshcatVisualizerParams(publish_period=period))
    ContactVisualizer.AddToBuilder(builder, parts.plant, meshcat,
                                   ContactVisualizerParams(publish_period=period,
                                                           newtons_per_meter=20.0))
    meshcat.SetCameraPose(camera_in_world=[-0.55, -0.35, 0.65], target_in_world=[0.0, 0.0, 0.1])
    if parts.has("epm.command"):
        marker = builder.AddNamedSystem("epm_command_marker", CommandMarker(
            meshcat, parts.epm.magnet, period))
        builder.Connect(parts.output("epm.command"), marker.GetInputPort("epm_command"))


class CommandMarker(LeafSystem):
    """Shows an EPM pose command in Meshcat: a translucent copy of the magnet (moment along
    its axis) at [p_WE, m_hat_W], published every `period` (and into a recording)."""

    def __init__(self, meshcat, geometry, period: float, path: str = "/epm_command"):
        super().__init__()
        self._meshcat = meshcat
        self._path = path
        dims = geometry.dimensions
        shape = (Sphere(0.5 * dims[0]) if geometry.shape == "sphere" else
                 Cylinder(0.5 * dims[0], dims[1]) if geometry.shape == "cylinder" else
                 Cylinder(0.5 * float(np.hypot(dims[0], dims[1])), dims[2]))
        meshcat.SetObject(path, shape, Rgba(0.2, 0.6, 1.0, 0.3))
        self._command = self.DeclareVectorInputPort("epm_command", 6)
        self.DeclarePeriodicPublishEvent(period, 0.0, self._publish)

    def _publish(self, context):
        command = self._command.Eval(context)
        if not np.all(np.isfinite(command)) or np.linalg.norm(command[3:]) < 1e-9:
            return EventStatus.DidNothing()
        R = RotationMatrix.MakeFromOneVector(command[3:], 2)
        self._meshcat.SetTransform(self._path, RigidTransform(R, command[:3]),
                                   context.get_time())
        return EventStatus.Succeeded()
