"""ContactMonitor: how hard the capsule is pressed against the colon wall."""

from __future__ import annotations

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.multibody.plant import ContactResults
from pydrake.systems.framework import LeafSystem

from capsule_drake.lifetime import id_values
from capsule_drake.physics.contact.foundation import empty_wall_contact


class ContactMonitor(LeafSystem):
    """Sums the magnitudes of all contact forces in the plant's ContactResults.

    In this scene only the capsule touches anything (the EPM and table have no collision
    geometry), so the sum is the total load between capsule and wall.

    .. pydrake_system::

        name: ContactMonitor
        input_ports:
        - contact_results
        output_ports:
        - contact_load
        - capsule_force_W
        - peak_pressure

    contact_load is a 1-vector in newtons: the sum over hydroelastic contact surfaces and
    point contacts of the magnitude of each one's resultant force.
    peak_pressure: the highest pressure (Pa) of the hydroelastic contact surfaces'
    pressure fields, at their vertices (`peak_contact_pressure`); 0 without contact, NaN
    when a point contact has no pressure to give.
    capsule_force_W: the net contact force on the capsule (N, world frame), when the
    capsule's collision geometries were given; zero otherwise.

    With `wall` (the compliant wall's foundation realisation, whose force is not Drake's
    contact) a second input, wall_contact (physics/contact/foundation.py WallContact), adds
    the wall's force and pressures to Drake's contact results (polyps, the tube's ends).

    Args:
        capsule_geometries: the capsule's collision GeometryIds, or their values (optional).
        wall: whether to read the wall's own contact (the station's contact.wall).
    """

    def __init__(self, capsule_geometries=(), wall: bool = False):
        super().__init__()
        # Their values: the ids a plant returns keep it alive (capsule_drake/lifetime.py).
        self._capsule = id_values(capsule_geometries)
        self._contact_results_port = self.DeclareAbstractInputPort(
            "contact_results", AbstractValue.Make(ContactResults()))
        self._wall = (self.DeclareAbstractInputPort("wall_contact",
                                                    AbstractValue.Make(empty_wall_contact()))
                      if wall else None)
        self._contact_load_port = self.DeclareVectorOutputPort(
            "contact_load", 1, self._calc_contact_load)
        self.DeclareVectorOutputPort("capsule_force_W", 3, self._calc_capsule_force)
        self.DeclareVectorOutputPort("peak_pressure", 1, self._calc_peak_pressure)

    def _wall_of(self, context):
        return self._wall.Eval(context) if self._wall is not None else None

    def _calc_peak_pressure(self, context, output):
        output.SetAtIndex(0, peak_contact_pressure(self._contact_results_port.Eval(context),
                                                   self._wall_of(context)))

    def _calc_capsule_force(self, context, output):
        output.SetFromVector(capsule_contact_force_W(self._contact_results_port.Eval(context),
                                                     self._capsule, self._wall_of(context)))

    def _calc_contact_load(self, context, output):
        results = self._contact_results_port.Eval(context)
        wall = self._wall_of(context)
        total = float(np.linalg.norm(wall.force_W)) if wall is not None else 0.0
        for i in range(results.num_hydroelastic_contacts()):
            total += np.linalg.norm(
                results.hydroelastic_contact_info(i).F_Ac_W().translational())
        for i in range(results.num_point_pair_contacts()):
            total += np.linalg.norm(results.point_pair_contact_info(i).contact_force())
        output.SetAtIndex(0, total)


def peak_contact_pressure(results, wall=None) -> float:
    """The highest pressure (Pa) over the hydroelastic contact surfaces of a plant's
    ContactResults: their pressure fields at the surfaces' vertices (the field is linear
    between them, so its maximum is at one), and over the compliant wall's cells (`wall`, a
    WallContact, if given). 0 with no contact; NaN with a point contact, which has a force
    but no pressure."""
    if results.num_point_pair_contacts():
        return float("nan")
    peak = float(wall.pressures.max()) if wall is not None and len(wall.pressures) else 0.0
    for i in range(results.num_hydroelastic_contacts()):
        surface = results.hydroelastic_contact_info(i).contact_surface()
        field = surface.tri_e_MN() if surface.is_triangle() else surface.poly_e_MN()
        for v in range(surface.num_vertices()):
            peak = max(peak, field.EvaluateAtVertex(v))
    return peak


def capsule_contact_force_W(results, capsule_geometries, wall=None) -> np.ndarray:
    """The net contact force (N, world frame) on the body of `capsule_geometries` (its
    GeometryIds, or their values: `lifetime.id_values`) in a plant's ContactResults:
    hydroelastic and point contacts alike; and the compliant wall's (`wall`, a WallContact,
    if given)."""
    capsule_geometries = id_values(capsule_geometries)
    total = np.array(wall.force_W, dtype=float) if wall is not None else np.zeros(3)
    for i in range(results.num_hydroelastic_contacts()):
        info = results.hydroelastic_contact_info(i)
        surface = info.contact_surface()
        force = info.F_Ac_W().translational()  # on the body of geometry M
        if surface.id_M().get_value() in capsule_geometries:
            total += force
        elif surface.id_N().get_value() in capsule_geometries:
            total -= force
    for i in range(results.num_point_pair_contacts()):
        info = results.point_pair_contact_info(i)
        pair = info.point_pair()
        if pair.id_B.get_value() in capsule_geometries:  # contact_force() acts on body B
            total += info.contact_force()
        elif pair.id_A.get_value() in capsule_geometries:
            total -= info.contact_force()
    return total


def capsule_contact_wrench_W(results, capsule_geometries, p_WBo,
                             wall=None) -> tuple[np.ndarray, np.ndarray]:
    """(torque, force) of the contact on the body of `capsule_geometries` (its GeometryIds,
    or their values) about its point p_WBo (N m, N; world frame): each hydroelastic
    contact's spatial force acts at its surface's centroid, each point contact's force at
    its contact point; the compliant wall's (`wall`, a WallContact about the body's origin,
    which p_WBo must be) added."""
    capsule_geometries = id_values(capsule_geometries)
    torque, force = np.zeros(3), np.zeros(3)
    if wall is not None:
        torque, force = np.array(wall.torque_W, dtype=float), np.array(wall.force_W, dtype=float)
    p_WBo = np.asarray(p_WBo, dtype=float)
    for i in range(results.num_hydroelastic_contacts()):
        info = results.hydroelastic_contact_info(i)
        surface = info.contact_surface()
        sign = (1.0 if surface.id_M().get_value() in capsule_geometries else
                -1.0 if surface.id_N().get_value() in capsule_geometries else 0.0)
        if sign:
            F = info.F_Ac_W()  # on the body of geometry M, at the centroid
            f = sign * F.translational()
            force += f
            torque += sign * F.rotational() + np.cross(surface.centroid() - p_WBo, f)
    for i in range(results.num_point_pair_contacts()):
        info = results.point_pair_contact_info(i)
        pair = info.point_pair()
        sign = (1.0 if pair.id_B.get_value() in capsule_geometries else
                -1.0 if pair.id_A.get_value() in capsule_geometries else 0.0)
        if sign:  # contact_force() acts on body B
            f = sign * info.contact_force()
            force += f
            torque += np.cross(info.contact_point() - p_WBo, f)
    return torque, force
