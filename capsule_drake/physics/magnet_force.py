"""MagneticForce: pairwise magnetic forces between magnets fixed to plant bodies (point
dipoles by default; the exact field of cylinder magnets as a fidelity option)."""

import dataclasses
import functools
import math
from typing import NamedTuple

import numpy as np
from pydrake.autodiffutils import AutoDiffXd
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform_
from pydrake.multibody.math import SpatialForce_, SpatialVelocity
from pydrake.multibody.plant import ExternallyAppliedSpatialForce, ExternallyAppliedSpatialForce_
from pydrake.multibody.tree import BodyIndex
from pydrake.systems.framework import LeafSystem_, ValueProducer
from pydrake.systems.primitives import ZeroOrderHold
from pydrake.systems.scalar_conversion import TemplateSystem

from capsule_drake.blocks import block
from capsule_drake.lifetime import CacheRef, weak_method
from capsule_drake.physics.implicit_torque import implicit_torque, mat_vec, rotational_stiffness
from capsule_drake.physics.magnetics import (
    DEFAULT_MIN_DISTANCE,
    cylinder_pair_interaction_float,
    dipole_pair_interaction,
    dipole_pair_interaction_float,
)
from capsule_drake.schema import MIN_PERIOD, need_range

FIELD_MODELS = ("dipole", "finite")


@dataclasses.dataclass
class MagnetSpec:
    """A permanent magnet rigidly attached to a body of a MultibodyPlant.

    YAML-loadable (``yaml_load_typed``); every field has a default.
    """

    # Unique name; prefixes the per-magnet output ports (``<name>.B_B``).
    name: str = "magnet"
    # Name of the plant body that carries the magnet.
    body: str = ""
    # Model instance of ``body``; needed only when the body name is ambiguous.
    model_instance: str = ""
    # Magnet centre M in the body frame B (m).
    p_BM: list[float] = dataclasses.field(default_factory=lambda: [0.0, 0.0, 0.0])
    # Magnetisation direction in the body frame B (normalised at construction).
    axis_B: list[float] = dataclasses.field(default_factory=lambda: [0.0, 0.0, 1.0])
    # Dipole moment magnitude (A m^2), e.g. ``MagnetGeometry(...).moment()``.
    moment: float = 0.0
    # [diameter, length] (m) of a cylinder magnetised along its axis (axis_B); empty: a
    # point. Read only by the "finite" field model.
    cylinder: list[float] = dataclasses.field(default_factory=list)
    # True: the magnet is on no plant body (`body`, `model_instance`, `p_BM` and `axis_B`
    # unused): its pose [p_WM, m_hat_W] comes from the input port ``<name>.pose``, as for
    # an external magnet placed by a commanded stage. Nothing is applied to it.
    posed: bool = False


class _ResolvedMagnet(NamedTuple):
    """A MagnetSpec bound to a plant: only indices and numbers, no plant reference."""

    name: str
    body_index: int  # -1 for a posed magnet
    p_BM: tuple  # (3,) floats
    m_B: tuple  # (3,) floats, moment vector in the body frame (A m^2)
    applies_force: bool  # False if the body is welded to the world
    cylinder: tuple  # () or (diameter, length)


class _MagnetValues(NamedTuple):
    """Per-context cache: everything the outputs need, one entry per magnet."""

    R_WB: list  # body orientations (3x3)
    B_W: list  # field of all other magnets at each magnet (T), world frame
    tau_W: list  # torque about the magnet centre (N m), world frame
    f_W: list  # force (N), world frame
    m_W: list = None  # moments (A m^2), world frame (float path)
    p_WM: list = None  # magnet centres (m), world frame (float path)


class _BodyInertia(NamedTuple):
    """What the implicit torque needs of a magnet's body."""

    p_McmM_B: dict   # magnet index -> its centre from the body's centre of mass (tuple)
    I_B: tuple       # central inertia in the body frame (rows)


def _central_inertia(plant, body_index, magnets):
    """A plant body's central inertia and its magnets' centres from its centre of mass,
    from its default spatial inertia."""
    body = plant.get_body(BodyIndex(body_index))
    M_BBo_B = body.default_spatial_inertia()
    p_BoBcm = np.asarray(M_BBo_B.get_com(), dtype=float)
    I_B = M_BBo_B.Shift(p_BoBcm).CalcRotationalInertia().CopyToFullMatrix3()
    return _BodyInertia(
        {i: tuple((np.array(m.p_BM, dtype=float) - p_BoBcm).tolist())
         for i, m in enumerate(magnets) if m.body_index == body_index},
        tuple(tuple(row) for row in np.asarray(I_B, dtype=float).tolist()))


def frame_with_z(direction):
    """A rotation matrix whose third column is the unit vector `direction` (floats or
    AutoDiffXd): the frame of a posed magnet, its moment along +z. Its x axis is the world
    axis least aligned with the direction, made orthogonal to it."""
    d = np.asarray(direction)
    values = [abs(a.value()) if hasattr(a, "value") else abs(float(a)) for a in d]
    e = np.zeros(3)
    e[int(np.argmin(values))] = 1.0
    x = e - (e @ d) * d
    x = x / np.sqrt(x @ x)
    y = np.array([d[1] * x[2] - d[2] * x[1], d[2] * x[0] - d[0] * x[2],
                  d[0] * x[1] - d[1] * x[0]])
    return np.stack([x, y, d], axis=1)


def _accumulate(sums, i, value):
    sums[i] = value if sums[i] is None else sums[i] + value


_ZERO3 = (0.0, 0.0, 0.0)


def _accumulate3(sums, i, value):
    """_accumulate for 3-tuples of floats; sums start as the shared ``_ZERO3``."""
    total = sums[i]
    if total is _ZERO3:
        sums[i] = value
    else:
        sums[i] = (total[0] + value[0], total[1] + value[1], total[2] + value[2])


def _resolve_magnets(plant, magnets):
    if not plant.is_finalized():
        raise ValueError("MagneticForce needs a finalized MultibodyPlant")
    names = [spec.name for spec in magnets]
    if len(set(names)) != len(names):
        raise ValueError(f"MagnetSpec names must be unique, got {names}")
    welded = {int(body.index()) for body in plant.GetBodiesWeldedTo(plant.world_body())}
    welded.add(int(plant.world_body().index()))
    resolved = []
    for spec in magnets:
        if spec.posed:
            cylinder = tuple(float(x) for x in spec.cylinder)
            resolved.append(_ResolvedMagnet(spec.name, -1, _ZERO3,
                                            (0.0, 0.0, float(spec.moment)), False, cylinder))
            continue
        if spec.model_instance:
            instance = plant.GetModelInstanceByName(spec.model_instance)
            body = plant.GetBodyByName(spec.body, instance)
        else:
            body = plant.GetBodyByName(spec.body)
        axis = np.asarray(spec.axis_B, dtype=float).reshape(3)
        norm = float(np.sqrt(axis @ axis))
        if norm == 0.0:
            raise ValueError(f"Magnet {spec.name!r}: axis_B must be nonzero")
        p_BM = np.asarray(spec.p_BM, dtype=float).reshape(3)
        m_B = axis * (float(spec.moment) / norm)
        cylinder = tuple(float(x) for x in spec.cylinder)
        if cylinder and not (len(cylinder) == 2 and min(cylinder) > 0.0
                             and all(np.isfinite(cylinder))):
            raise ValueError(f"Magnet {spec.name!r}: cylinder must be [diameter, length] > 0,"
                             f" got {list(spec.cylinder)}")
        index = int(body.index())
        resolved.append(
            _ResolvedMagnet(
                spec.name, index, tuple(p_BM.tolist()), tuple(m_B.tolist()),
                index not in welded, cylinder,
            )
        )
    return tuple(resolved)


@TemplateSystem.define("MagneticForce_", T_list=[float, AutoDiffXd])
def MagneticForce_(T):
    class Impl(LeafSystem_[T]):
        """Magnetic forces and fields between magnets fixed to plant bodies.

        Each magnet is a point dipole (``capsule_drake.physics.magnetics``, after Mahoney
        & Abbott, IJRR 2016) at a fixed point ``M`` of a body ``B``. For every
        pair, the force and torque are summed onto both magnets, so any number of
        magnets is supported (cost grows with the number of pairs).

        .. pydrake_system::

            name: MagneticForce
            input_ports:
            - body_poses
            output_ports:
            - applied_spatial_force
            - <name>.B_B
            - <name>.F_W

        - ``body_poses``: ``list[RigidTransform]`` X_WB of every plant body;
          connect from ``plant.get_body_poses_output_port()``.
        - ``applied_spatial_force``: ``list[ExternallyAppliedSpatialForce]``,
          one per magnet on a body that is not welded to the world: torque (N m)
          and force (N) in world, applied at the magnet centre
          (``p_BoBq_B = p_BM``), so the lever arm about the body origin and the
          centre of mass is kept. Connect to the plant's
          ``get_applied_spatial_force_input_port()``.
        - ``<name>.B_B`` (3, T): field of all the other magnets at this magnet,
          expressed in its body frame, what an on-board magnetometer at M reads.
        - ``<name>.F_W`` (6, [torque N m; force N]): spatial force on this
          magnet's body at the magnet centre, in world. Given for welded magnets
          too; for an external magnet held by a robot this is the reaction wrench
          the robot carries.

        All outputs are computed once per context into a cache entry that
        depends only on ``body_poses``. A discrete plant's ``body_poses`` does
        not depend on its applied-force input, so this makes no algebraic loop.
        Scalar types: float and AutoDiffXd (``ToAutoDiffXd()`` for
        linearisation). The float path is a separate plain-float kernel
        (tested against the generic one) with preallocated output forces: at
        1 kHz its Python cost is most of what this system adds to a step.

        Args:
            plant: a finalized MultibodyPlant (any scalar type); only body
                indices and welds are read, at construction.
            magnets: list of MagnetSpec (unique names).
            min_distance: guard radius (m) of the dipole model, see
                ``capsule_drake.physics.magnetics.dipole_field``.
            field_model: "dipole" (every magnet a point dipole; float and AutoDiffXd) or
                "finite" (float only): in each pair with a magnet given a ``cylinder``
                shape, the larger such magnet's exact field
                (``magnetics.cylinder_pair_interaction_float``), the other magnet
                integrated over its cylinder if it has one, else a point. Within 1 % of
                magpylib's meshed force and torque at 8-25 cm, where the dipole is off by
                up to 60 % (tests/test_finite_magnets.py).
            implicit_step: the plant's step (s) to integrate the magnets' torques
                implicitly over (float only; 0: explicit). Then connect
                ``get_body_spatial_velocities_input_port()``. See
                ``_declare_implicit_torque``.
            implicit_magnets: the names of the magnets whose bodies' torques are implicit
                (None: every magnet on a body that is not welded to the world).
        """

        def _construct(
            self, plant, magnets, min_distance=DEFAULT_MIN_DISTANCE, converter=None,
            field_model="dipole", implicit_step=0.0, implicit_magnets=None,
        ):
            magnets = _resolve_magnets(plant, magnets)
            if implicit_magnets is not None:
                unknown = set(implicit_magnets) - {m.name for m in magnets}
                if unknown:
                    raise ValueError(f"MagneticForce implicit_magnets: no magnet named "
                                     f"{sorted(unknown)}")
            inertias = {m.body_index: _central_inertia(plant, m.body_index, magnets)
                        for m in magnets if m.applies_force and (
                            implicit_magnets is None or m.name in implicit_magnets)
                        } if implicit_step > 0 else {}
            Impl._setup(self, magnets, min_distance, converter, field_model,
                        implicit_step, inertias)

        def _construct_copy(self, other, converter=None):
            # The implicit torque is float only: a converted copy applies the torque as is
            # (linearisation differentiates the forces, not the integrator).
            Impl._setup(self, other._magnets, other._min_distance, converter,
                        other._field_model, 0.0, other._inertias)

        def _setup(self, magnets, min_distance, converter, field_model, implicit_step=0.0,
                   inertias=None):
            if field_model not in FIELD_MODELS:
                raise ValueError(f"MagneticForce field_model must be one of {FIELD_MODELS},"
                                 f" got {field_model!r}")
            if field_model == "finite" and T is not float:
                raise ValueError(
                    "MagneticForce field_model 'finite' is float only (the exact cylinder "
                    "field carries no derivatives): linearise with field_model 'dipole'")
            LeafSystem_[T].__init__(self, converter)
            self._magnets = magnets
            self._inertias = inertias or {}
            self._field_model = field_model
            self._min_distance = float(min_distance)
            # Resolve templates and indices once: a template lookup per call
            # costs microseconds, comparable to the physics itself.
            self._make_applied_force = ExternallyAppliedSpatialForce_[T]
            self._make_spatial_force = SpatialForce_[T]
            self._body_indices = [BodyIndex(max(m.body_index, 0)) for m in magnets]
            if T is float:
                # Fast path (see _calc_magnet_values_float): plain floats.
                self._pair = dipole_pair_interaction_float
                # The finite model's pair function also takes the magnets' indices.
                self._pair_ij = (self._finite_pair_function(magnets)
                                 if field_model == "finite" else None)
                self._p_BM = [np.array(m.p_BM) for m in magnets]
                calc_values = self._calc_magnet_values_float
                calc_applied = self._calc_applied_spatial_force_float
            else:
                self._pair = dipole_pair_interaction
                self._p_BM = [np.array([T(x) for x in m.p_BM]) for m in magnets]
                calc_values = self._calc_magnet_values
                calc_applied = self._calc_applied_spatial_force
            self._m_B = [np.array(m.m_B) for m in magnets]
            # The applied forces, built once: a calc only replaces their F_Bq_W.
            # set_value() copies them into the output, so reuse is safe.
            self._applied = []
            for i, magnet in enumerate(magnets):
                if magnet.applies_force:
                    force = self._make_applied_force()
                    force.body_index = self._body_indices[i]
                    force.p_BoBq_B = self._p_BM[i]
                    self._applied.append((i, force))
            self._applied_forces = [force for _, force in self._applied]

            self._body_poses_port = self.DeclareAbstractInputPort(
                "body_poses", AbstractValue.Make([RigidTransform_[T]()])
            )
            # Posed magnets: [p_WM, m_hat_W] from an input port each (None for the others).
            self._pose_ports = [
                self.DeclareVectorInputPort(f"{m.name}.pose", 6) if m.body_index < 0 else None
                for m in magnets]
            self._moments = [float(np.linalg.norm(m.m_B)) for m in magnets]
            self._cache = CacheRef(self, self.DeclareCacheEntry(
                description="magnet fields and wrenches",
                value_producer=ValueProducer(
                    allocate=AbstractValue.Make(_MagnetValues([], [], [], [])).Clone,
                    calc=weak_method(calc_values),
                ),
                prerequisites_of_calc={self._body_poses_port.ticket()} | {
                    port.ticket() for port in self._pose_ports if port is not None},
            ))
            deps = {self._cache.ticket()}
            self._implicit_step = float(implicit_step) if T is float else 0.0
            if self._implicit_step > 0.0:
                deps = self._declare_implicit_torque()
                calc_applied = self._calc_applied_spatial_force_implicit
            self._applied_spatial_force_port = self.DeclareAbstractOutputPort(
                "applied_spatial_force",
                lambda: AbstractValue.Make([ExternallyAppliedSpatialForce_[T]()]),
                weak_method(calc_applied),
                prerequisites_of_calc=deps,
            )
            self._B_B_ports = []
            self._F_W_ports = []
            for i, magnet in enumerate(magnets):
                self._B_B_ports.append(
                    self.DeclareVectorOutputPort(
                        f"{magnet.name}.B_B",
                        3,
                        functools.partial(self._calc_B_B, i),
                        prerequisites_of_calc=deps,
                    )
                )
                self._F_W_ports.append(
                    self.DeclareVectorOutputPort(
                        f"{magnet.name}.F_W",
                        6,
                        functools.partial(self._calc_F_W, i),
                        prerequisites_of_calc=deps,
                    )
                )

        # --- the implicit magnetic torque (float only) ------------------------
        def _declare_implicit_torque(self):
            """With `implicit_step` h (the plant's step), the torque on each free magnet
            body is integrated implicitly in its stiff part (physics/implicit_torque.py):
            held by friction, a capsule feels tau0 exactly; free, it is integrated by
            linearly implicit Euler. The step's forces stay explicit. The state: per free
            body [w_{n-1}, tau(n-1) about its centre of mass], then a started flag;
            updated at every plant step."""
            self._velocities_port = self.DeclareAbstractInputPort(
                "body_spatial_velocities", AbstractValue.Make([SpatialVelocity()]))
            self._implicit_bodies = [i for i, _ in self._applied
                                     if self._magnets[i].body_index in self._inertias]
            n = len(self._implicit_bodies)
            self._implicit_state = self.DeclareDiscreteState(6 * n + 1)
            self._implicit_cache = CacheRef(self, self.DeclareCacheEntry(
                description="implicit magnet torques",
                value_producer=ValueProducer(
                    allocate=AbstractValue.Make([]).Clone,
                    calc=weak_method(self._calc_implicit_torques)),
                prerequisites_of_calc={
                    self._cache.ticket(), self._velocities_port.ticket(),
                    self.discrete_state_ticket(self._implicit_state)}))
            # Unrestricted, as the discrete plant's own step: the diagram computes every
            # unrestricted update from the same context (the state before the step), where
            # a discrete update would see the state after it.
            self.DeclarePeriodicUnrestrictedUpdateEvent(self._implicit_step, 0.0,
                                                        self._update_implicit_state)
            return {self._implicit_cache.ticket()}

        def get_body_spatial_velocities_input_port(self):
            """Only with an implicit torque: connect the plant's
            ``get_body_spatial_velocities_output_port()``."""
            return self._velocities_port

        def _calc_implicit_torques(self, context, abstract_value):
            """Per free magnet: (tau applied about the magnet centre, the same about the
            body's centre of mass, w_n), 3-sequences of plain floats
            (implicit_torque.implicit_torque)."""
            values = self._cache.Eval(context)
            velocities = self._velocities_port.Eval(context)
            state = tuple(context.get_discrete_state(self._implicit_state).value().tolist())
            started = state[-1] > 0.0
            h = self._implicit_step
            out = []
            for k, i in enumerate(self._implicit_bodies):
                magnet = self._magnets[i]
                R = values.R_WB[i]
                inertia = self._inertias[magnet.body_index]
                w = tuple(velocities[magnet.body_index].rotational().tolist())
                # Lever arm from the centre of mass to the magnet centre, in world.
                r = mat_vec(R, inertia.p_McmM_B[i])
                K = rotational_stiffness(
                    values.m_W[i], values.p_WM[i], r,
                    tuple((values.m_W[j], values.p_WM[j]) for j in range(len(self._magnets))
                          if j != i), self._min_distance)
                previous = state[6 * k:6 * k + 6] if started else None
                out.append(implicit_torque(values.tau_W[i], values.f_W[i], r, K, R,
                                           inertia.I_B, w, previous, h))
            abstract_value.set_value(out)

        def _update_implicit_state(self, context, state):
            torques = self._implicit_cache.Eval(context)
            value = []
            for _, tau_cm, w in torques:
                value += w + tau_cm
            value.append(1.0)
            state.get_mutable_discrete_state(self._implicit_state).SetFromVector(value)

        def _calc_applied_spatial_force_implicit(self, context, output):
            values = self._cache.Eval(context)
            implicit = dict(zip(self._implicit_bodies, self._implicit_cache.Eval(context)))
            make_spatial_force = self._make_spatial_force
            for i, force in self._applied:
                tau = implicit[i][0] if i in implicit else tuple(values.tau_W[i])
                force.F_Bq_W = make_spatial_force(np.array(tau + tuple(values.f_W[i])))
            output.set_value(self._applied_forces)

        @staticmethod
        def _finite_pair_function(magnets):
            """A pair function (i, j) -> interaction that treats the larger magnet with a
            cylinder shape as a finite source, the other as a point or (with a cylinder
            shape) an integrated cylinder; pairs with no cylinder stay dipoles. The roles
            are fixed by the magnets, so they are decided here, once per pair."""
            def strength(k):
                return sum(x * x for x in magnets[k].m_B)

            swapped = {}
            for i in range(len(magnets)):
                for j in range(i + 1, len(magnets)):
                    ci, cj = magnets[i].cylinder, magnets[j].cylinder
                    if ci or cj:
                        swapped[i, j] = not (ci and (not cj or strength(i) >= strength(j)))

            def pair(m_i, m_j, p, d_min, i, j):
                swap = swapped.get((i, j))
                if swap is None:
                    return dipole_pair_interaction_float(m_i, m_j, p, d_min)
                ci, cj = magnets[i].cylinder, magnets[j].cylinder
                if not swap:
                    return cylinder_pair_interaction_float(
                        m_i, m_j, p, *ci, target_size=cj or None, min_distance=d_min)
                # j is the finite source: swap the roles, then swap the results back.
                r = cylinder_pair_interaction_float(
                    m_j, m_i, (-p[0], -p[1], -p[2]), *cj, target_size=ci or None,
                    min_distance=d_min)
                return r._replace(
                    field_at_target=r.field_at_source, field_at_source=r.field_at_target,
                    force_target=r.force_source, torque_target=r.torque_source,
                    force_source=r.force_target, torque_source=r.torque_target)

            return pair

        def field_model(self):
            return self._field_model

        # --- port accessors -------------------------------------------------
        def get_body_poses_input_port(self):
            return self._body_poses_port

        def get_pose_input_port(self, name):
            """The input [p_WM, m_hat_W] of the posed magnet `name`."""
            port = self._pose_ports[self._index_of(name)]
            if port is None:
                raise KeyError(f"magnet {name!r} is on a plant body, not posed")
            return port

        def get_applied_spatial_force_output_port(self):
            return self._applied_spatial_force_port

        def get_B_B_output_port(self, name):
            return self._B_B_ports[self._index_of(name)]

        def get_F_W_output_port(self, name):
            return self._F_W_ports[self._index_of(name)]

        def magnet_names(self):
            return [m.name for m in self._magnets]

        def min_distance(self):
            return self._min_distance

        def _index_of(self, name):
            for i, magnet in enumerate(self._magnets):
                if magnet.name == name:
                    return i
            raise KeyError(f"No magnet named {name!r}; have {self.magnet_names()}")

        # --- calculations ---------------------------------------------------
        def _calc_magnet_values(self, context, abstract_value):
            poses = self._body_poses_port.Eval(context)
            n = len(self._magnets)
            R_WB, p_WM, m_W = [], [], []
            for i, magnet in enumerate(self._magnets):
                if self._pose_ports[i] is not None:
                    pose = self._pose_ports[i].Eval(context)
                    direction = pose[3:] / np.sqrt(pose[3:] @ pose[3:])
                    R = frame_with_z(direction)
                    R_WB.append(R)
                    p_WM.append(np.asarray(pose[:3]))
                    m_W.append(self._moments[i] * direction)
                    continue
                X_WB = poses[magnet.body_index].GetAsMatrix34()
                R = X_WB[:, :3]
                R_WB.append(R)
                p_WM.append(X_WB[:, 3] + R @ self._p_BM[i])
                m_W.append(R @ self._m_B[i])
            # None = nothing accumulated yet (avoids adding zero arrays).
            B_W = [None] * n
            tau_W = [None] * n
            f_W = [None] * n
            pair = self._pair
            d_min = self._min_distance
            for i in range(n):
                for j in range(i + 1, n):
                    # i is the source, j the target: p points from i to j.
                    result = pair(m_W[i], m_W[j], p_WM[j] - p_WM[i], d_min)
                    _accumulate(B_W, j, result.field_at_target)
                    _accumulate(B_W, i, result.field_at_source)
                    _accumulate(f_W, j, result.force_target)
                    _accumulate(tau_W, j, result.torque_target)
                    _accumulate(f_W, i, result.force_source)
                    _accumulate(tau_W, i, result.torque_source)
            zero = np.zeros(3) if T is float else np.array([T(0.0)] * 3)
            for values in (B_W, tau_W, f_W):
                for i in range(n):
                    if values[i] is None:
                        values[i] = zero
            abstract_value.set_value(_MagnetValues(R_WB, B_W, tau_W, f_W))

        def _calc_magnet_values_float(self, context, abstract_value):
            """_calc_magnet_values for T = float, in plain Python floats.

            Same result; numpy's per-call overhead on 3-vectors would cost more
            than the arithmetic. Vectors are 3-tuples, R_WB tuples of rows.
            """
            poses = self._body_poses_port.Eval(context)
            R_WB, p_WM, m_W = [], [], []
            for magnet, pose_port, moment in zip(self._magnets, self._pose_ports,
                                                 self._moments):
                if pose_port is not None:
                    x, y, z, u, v, w = pose_port.Eval(context).tolist()
                    scale = 1.0 / math.sqrt(u * u + v * v + w * w)
                    p_WM.append((x, y, z))
                    m_W.append((moment * u * scale, moment * v * scale, moment * w * scale))
                    R_WB.append(None)   # made only if its B_B is asked for (_calc_B_B)
                    continue
                # One array out of the bindings (each costs ~1 us) and one tolist().
                (r00, r01, r02, x), (r10, r11, r12, y), (r20, r21, r22, z) = poses[
                    magnet.body_index
                ].GetAsMatrix34().tolist()
                a, b, c = magnet.p_BM
                p_WM.append(
                    (
                        r00 * a + r01 * b + r02 * c + x,
                        r10 * a + r11 * b + r12 * c + y,
                        r20 * a + r21 * b + r22 * c + z,
                    )
                )
                a, b, c = magnet.m_B
                m_W.append(
                    (
                        r00 * a + r01 * b + r02 * c,
                        r10 * a + r11 * b + r12 * c,
                        r20 * a + r21 * b + r22 * c,
                    )
                )
                R_WB.append(((r00, r01, r02), (r10, r11, r12), (r20, r21, r22)))
            n = len(p_WM)
            B_W, tau_W, f_W = [_ZERO3] * n, [_ZERO3] * n, [_ZERO3] * n
            pair, pair_ij = self._pair, self._pair_ij
            d_min = self._min_distance
            for i in range(n):
                xi, yi, zi = p_WM[i]
                for j in range(i + 1, n):
                    # i is the source, j the target: p points from i to j.
                    xj, yj, zj = p_WM[j]
                    p = (xj - xi, yj - yi, zj - zi)
                    result = (pair(m_W[i], m_W[j], p, d_min) if pair_ij is None
                              else pair_ij(m_W[i], m_W[j], p, d_min, i, j))
                    _accumulate3(B_W, j, result.field_at_target)
                    _accumulate3(B_W, i, result.field_at_source)
                    _accumulate3(f_W, j, result.force_target)
                    _accumulate3(tau_W, j, result.torque_target)
                    _accumulate3(f_W, i, result.force_source)
                    _accumulate3(tau_W, i, result.torque_source)
            abstract_value.set_value(_MagnetValues(R_WB, B_W, tau_W, f_W, m_W, p_WM))

        def _calc_applied_spatial_force(self, context, output):
            values = self._cache.Eval(context)
            make_spatial_force = self._make_spatial_force
            for i, force in self._applied:
                force.F_Bq_W = make_spatial_force(values.tau_W[i], values.f_W[i])
            output.set_value(self._applied_forces)

        def _calc_applied_spatial_force_float(self, context, output):
            values = self._cache.Eval(context)
            make_spatial_force = self._make_spatial_force
            tau_W, f_W = values.tau_W, values.f_W
            for i, force in self._applied:
                # One 6-vector: the (tau, f) constructor converts each
                # 3-tuple through Eigen, several times slower.
                force.F_Bq_W = make_spatial_force(np.array(tau_W[i] + f_W[i]))
            output.set_value(self._applied_forces)

        def _calc_B_B(self, i, context, output):
            values = self._cache.Eval(context)
            R_WB = values.R_WB[i]
            if R_WB is None:   # a posed magnet (float path)
                pose = self._pose_ports[i].Eval(context)
                R_WB = frame_with_z(pose[3:] / np.linalg.norm(pose[3:]))
            output.SetFromVector(np.asarray(R_WB).T @ np.asarray(values.B_W[i]))

        def _calc_F_W(self, i, context, output):
            values = self._cache.Eval(context)
            output.SetFromVector(np.concatenate((values.tau_W[i], values.f_W[i])))

    return Impl


MagneticForce = MagneticForce_[None]


@dataclasses.dataclass
class MagnetForceConfig:
    """The force and torque between the EPM and the capsule's magnet."""

    # Field model: "dipole" (point dipoles: fast, differentiable, off by 18 % at 10 cm and
    # 3 % at 20 cm from the EPM) or "finite" (the exact field of a cylinder EPM and the
    # capsule's cylinder magnet integrated over its volume: within 0.1 % of a meshed
    # reference; float only). Spheres are exact dipoles in either; cuboids have only the
    # dipole model.
    field_model: str = "dipole"
    # Period at which the force is recomputed (s); 0 = every plant step. Holding it over
    # 2 ms halves the Python cost per step; the held force is stable while the magnet's
    # rotational stiffness keeps omega * period < ~1 (omega ~ 500 rad/s at the 10 cm the
    # EPM's clearance allows at most).
    update_period: float = 0.0
    # False: the forces are computed (and the outputs available) but not applied, so the
    # capsule lies on the wall under gravity: for ablation benchmarks.
    apply: bool = True
    # True (default): the magnet's torque is integrated implicitly in its stiff part (the
    # rotational stiffness of m x B about the capsule's centre of mass;
    # MagneticForce._declare_implicit_torque), so that the plant's step is not bounded by
    # the magnet's turning (explicitly omega h < 2: 1.1 ms at the closest clearance,
    # physics/step_bound.py). Only with update_period 0. False: explicit, as before.
    implicit: bool = True


def check_magnet_force_config(config: MagnetForceConfig, magnets: dict) -> None:
    """Raises ValueError naming the first impossible field. `magnets`: where -> geometry."""
    if config.field_model not in FIELD_MODELS:
        raise ValueError(f"magnet_force.field_model must be one of {', '.join(FIELD_MODELS)}, "
                         f"got {config.field_model!r}")
    if config.update_period != 0:
        need_range(config.update_period, "magnet_force.update_period", f">= {MIN_PERIOD:g}",
                   "s", "or 0: every step; a shorter period is an event that recomputes the "
                   "force more often than any plant step can use")
    if config.implicit and config.update_period != 0:
        raise ValueError("magnet_force.implicit needs update_period 0 (the torque is made "
                         "implicit at every plant step), got update_period "
                         f"{config.update_period:g} s")
    if config.field_model == "finite":
        for where, geometry in magnets.items():
            if geometry.shape not in ("cylinder", "sphere") or geometry.legacy:
                raise ValueError(
                    "magnet_force.field_model 'finite' needs cylinder or sphere magnets "
                    f"without the legacy moment, but {where} is a "
                    f"{'legacy ' if geometry.legacy else ''}{geometry.shape}")


def _cylinder(geometry):
    return list(geometry.dimensions) if geometry.shape == "cylinder" else []


def check_magnet_force(config: MagnetForceConfig, scenario) -> None:
    check_magnet_force_config(config, {"epm.magnet": scenario.epm.magnet,
                                       "capsule.ipm": scenario.capsule.ipm})


@block("magnet_force", MagnetForceConfig, check=check_magnet_force, where="")
def add_magnet_force(builder, parts, config: MagnetForceConfig, *, epm_body: str = "epm"):
    """`magnet_force` between the capsule's magnet (frame M of the capsule) and the EPM
    (its body's origin, moment along +z; or the kinematic stage's pose), applied to the
    plant (through `magnet_force_hold` when it is held between updates); exports capsule.ipm_field_B (the field at the IPM in
    the capsule frame, a magnetometer's truth) and epm.F_W (the reaction on the EPM)."""
    plant = parts.plant
    X_BM = parts.capsule.X_BM
    parts.magnets = [
        MagnetSpec(name="ipm", body=parts.capsule_body.name(), model_instance="capsule",
                   p_BM=list(X_BM.translation()), axis_B=list(X_BM.rotation().col(2)),
                   moment=parts.ipm.moment(), cylinder=_cylinder(parts.ipm)),
        MagnetSpec(name="epm", body=epm_body, model_instance=parts.epm.mount.model_name or "",
                   p_BM=[0.0, 0.0, 0.0], axis_B=[0.0, 0.0, 1.0],
                   moment=parts.epm.magnet.moment(), cylinder=_cylinder(parts.epm.magnet),
                   posed=parts.epm.instance is None),
    ]
    parts.field_model = config.field_model
    implicit = config.apply and config.implicit and config.update_period <= plant.time_step()
    force = builder.AddNamedSystem("magnet_force", MagneticForce(
        plant, parts.magnets, field_model=config.field_model,
        implicit_step=plant.time_step() if implicit else 0.0,
        # The capsule's magnet: the EPM, on an arm, is heavy and servoed.
        implicit_magnets=["ipm"]))
    builder.Connect(plant.get_body_poses_output_port(), force.get_body_poses_input_port())
    if implicit:
        builder.Connect(plant.get_body_spatial_velocities_output_port(),
                        force.get_body_spatial_velocities_input_port())
    if parts.epm.instance is None:   # the kinematic stage: the EPM where it is commanded
        builder.Connect(parts.epm.mount.pose_output(), force.get_pose_input_port("epm"))
    if config.apply:
        port = force.get_applied_spatial_force_output_port()
        if config.update_period > plant.time_step():
            # Typed as list[ExternallyAppliedSpatialForce], empty until the first sample.
            no_forces = AbstractValue.Make([ExternallyAppliedSpatialForce()])
            no_forces.set_value([])
            hold = builder.AddNamedSystem("magnet_force_hold", ZeroOrderHold(
                config.update_period, no_forces))
            builder.Connect(port, hold.get_input_port())
            port = hold.get_output_port()
        parts.applied_forces.append(port)   # wired by the applied_forces block (scene.py)
    parts.export(force.get_B_B_output_port("ipm"), "capsule.ipm_field_B")
    parts.export(force.get_F_W_output_port("epm"), "epm.F_W")
    return force
