"""A MuJoCo peer of the Default drag: the same tube, capsule and magnets, for a real-time factor
measured beside this project's in the same run.

    pip install -e '.[peer]'    # the peer's only extra (MuJoCo 3 or later)
    .venv/bin/python benchmarks/peer_mujoco.py [--sim-seconds 10] [--repeats 3] [--csv FILE]

Method. One process builds both: the project's Default station exactly as
benchmarks/bench_realtime.py does (`make_station(load_scenario(name="Default"))`, no Meshcat,
its own 2 ms plant step, Drake's Simulator), and the peer, a MuJoCo model written here in code
from the same colon object. For each repeat both start afresh, settle 1 s untimed, then
advance over `sim-seconds` in alternate chunks of 0.5 simulated seconds, each chunk timed
(wall clock), which goes first alternating, so that a change in the machine's speed during
the measurement (a shared VM's neighbours move it by ~25 %) falls on both alike (as
bench_realtime.py --versus does). Each engine's real-time factor is sim-seconds over its
chunks' total; printed per repeat with the ratio ours / peer, and their medians. Both are
deterministic, so one more, untimed pass of each, sampled at every step, gives the physical
comparison: the capsule's advance along the centreline (the project's station of the
capsule's centre, `Centerline.closest`), the total wall force on the capsule (median and
peak), the capsule centre's largest distance from the centreline against the wall radius
there, and its surface's largest excursion beyond the wall (`TubeColon.excursion` of its
axis points plus its radius). The GLIBC_TUNABLES allocator setting bench_realtime.py gives
its scenarios is set for this process too (it restarts itself with it), so both have it.

What is the same:
  - the colon: the Default's procedural colon (seed 0), through the project's loader;
  - the capsule: mass and central inertia read from the Default station's own plant
    (models/capsule.sdf: 12 g), its collision capsule (radius 5.8 mm, 19.9 mm cylinder), the
    internal magnet's frame (3 mm behind the centre, along the axis) and moment
    (`scenario.capsule.ipm.moment()`), the start pose (`capsule.model.start_pose` at
    capsule.start_s, at rest), gravity (the plant's);
  - the EPM: its pose at each step is the Default's own !AlongColon stage trajectory
    (`epm.paths.path_trajectory`, then `epm.poses.stage_to_pose`), evaluated at the step's
    start time, as Drake's kinematic stage feeds it to the magnet force;
  - the magnet: the Default's field model is "dipole", and the peer calls the same function
    the Default's MagneticForce calls, `physics.magnetics.dipole_pair_interaction_float`,
    for the force and torque on the capsule's magnet; the Default integrates the stiff part
    of that torque implicitly (magnet_force.implicit), and so does the peer, with the
    project's own `physics.implicit_torque.rotational_stiffness` and `implicit_torque`
    (--explicit-torque applies m x B as it is: at the Default's ~20 cm omega dt ~ 0.25, stable);
    the wrench goes in through `data.xfrc_applied` between mj_step1 and mj_step2 (MuJoCo's
    split step: the pose it is computed from is the step's start, as in Drake's discrete
    plant), shifted from the magnet's centre to the centre of mass;
  - the time step: the Default's plant.time_step (2 ms); MuJoCo's semi-implicit Euler.

What differs:
  - the wall's geometry: the Default's wall is rigid hydroelastic triangle-mesh chunks of the
    analytic wall `wall_radius(s, theta)`. MuJoCo collides a mesh only as its convex hull,
    and a user-defined SDF needs a compiled plugin, a height field cannot close a tube; so
    the peer's wall is the project's own convex pieces of that analytic wall
    (`anatomy.source.colon_wall_pieces`, the FastContact model's: ~10 mm long, chords within
    0.5 mm, 3 mm deep into the tissue), each a static mesh geom (its convex hull), those
    whose centroid lies from the anus to `--wall-margin` beyond the farthest the EPM goes in
    a run. The pieces bridge a fold's concave foot by a ramp (the capsule rides a little
    higher there) and only the run's stretch of tube exists (the Default holds all of it,
    its broad phase keeping the cost local). MuJoCo's own share of a step grows with the
    pieces: `--wall-margin 1.5` tiles the whole colon (2,666 pieces against ~540), which
    about doubled it on the 2-core VM (64 against 32 us a step, a 3 s trial);
  - the contact law: Drake's hydroelastic pressure field between the capsule's compliant
    layer (modulus 5 MPa, meshed at 4 mm) and the rigid wall, Hunt-Crossley dissipation
    5 s/m, Coulomb 0.2 (static = dynamic), solved by SAP's lagged approximation; MuJoCo's
    soft constraints, elliptic friction cone of 0.2 (sliding only, condim 3; no torsional or
    rolling friction), impratio 10, Newton solver. The mapping (`contact_mapping`): the
    Default's contact is probed once, in a small Drake plant of the capsule (the scenario's
    contact settings) lying on a rigid hydroelastic floor under 0.2 N and 1 N, for its
    stiffness (~7e4 N/m: penetration grows ~11 um from 0.2 N to 1 N) and its rest depth
    (~0.35 mm, nearly all of it the 4 mm tetrahedral mesh's flat facets inside the round
    shell, not elasticity). That contact's period (2 pi sqrt(m / k) ~ 2.5 ms) is about
    one step, and both engines can only treat it as near-rigid: solref = (2 dt, 1), the
    stiffest time constant MuJoCo lets a step have, critically damped (the Hunt-Crossley
    ratio, c / 2 sqrt(k m) with c = 5 s/m x the weight, is ~0.01, a ringing neither step
    resolves; SAP damps it within a step); solimp's impedance d (flat: dmin = dmax) is
    chosen so that the peer's capsule lying on a plane, which MuJoCo touches at two
    contacts (its segment's ends) of static stiffness m / (timeconst^2 dampratio^2 (1 - d))
    each, has the probed stiffness (d ~ 0.98); against the wall's pieces the capsule has one
    contact per piece it touches, so it is that stiff within a factor of ~2 either way, a
    micrometre at these loads. The probe's figures and the peer's own rest depth under the
    same loads are printed. The 0.35 mm facet inset is not copied:
    the peer's capsule is round, so it lies ~0.35 mm higher and rolls smoothly where
    Drake's rolls over facets;
  - what each computes in C/C++ against Python: in Drake, the plant, contact query and SAP
    solve are C++, and the station's Python systems (the magnet force with its implicit
    torque, the kinematic stage's pose, the EPM's drawn frame, its guard and clearance
    watch) run inside the Simulator's step events; in the peer, MuJoCo's step (collision,
    constraint solve, integration) is C, and per step Python evaluates the EPM's trajectory (Drake's
    PiecewisePolynomial), the dipole wrench and implicit torque (the project's Numba-compiled
    functions) and writes xfrc_applied: that Python is inside the peer's timed loop.

Run: PYTHONPATH=<where mujoco is> .venv/bin/python benchmarks/peer_mujoco.py --repeats 3
"""

from __future__ import annotations

import argparse
import datetime
import importlib.metadata
import math
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np
from pydrake.common.eigen_geometry import Quaternion
from pydrake.geometry import AddRigidHydroelasticProperties, Box
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import AddMultibodyPlant, MultibodyPlantConfig
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder

from capsule_drake.anatomy import load_colon
from capsule_drake.anatomy.source import colon_wall_pieces
from capsule_drake.capsule.model import CAPSULE_BODY, capsule_model, start_pose
from capsule_drake.epm.paths import AlongColon, path_trajectory
from capsule_drake.epm.poses import stage_to_pose
from capsule_drake.models import configure_parser, model_url
from capsule_drake.physics.contact.common import set_capsule_properties
from capsule_drake.physics.contact.rigid import RigidWall, rigid_properties
from capsule_drake.physics.implicit_torque import implicit_torque, rotational_stiffness
from capsule_drake.physics.magnetics import DEFAULT_MIN_DISTANCE, dipole_pair_interaction_float
from capsule_drake.scenario import load_scenario
from capsule_drake.station import make_station, station_value

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_realtime import ALLOCATOR, cpu_name  # noqa: E402  (this folder's sibling)

SCENARIO = "Default"
WARM_UP = 1.0          # s settled before the timed window, as bench_realtime.py
PROBE_LOADS = (0.2, 1.0)   # N on the capsule in the contact probe
LYING_CONTACTS = 2     # MuJoCo's contacts of a capsule lying on a plane: its segment's ends


def import_mujoco():
    """MuJoCo, or exit with the one line that says how to get it."""
    try:
        import mujoco
    except ImportError:
        sys.exit("peer_mujoco.py needs MuJoCo: .venv/bin/pip install -e '.[peer]' "
                 "(or pip install mujoco)")
    return mujoco


# --- the contact mapping ----------------------------------------------------------------------

def drake_capsule_rest_depth(contact: RigidWall, time_step: float, load: float) -> float:
    """How far (m) the Default's capsule, lying on a rigid hydroelastic floor with the
    scenario's contact settings, sinks below its round shell's radius under `load` (N, its
    weight scaled), after 1 s."""
    builder = DiagramBuilder()
    plant, scene_graph = AddMultibodyPlant(MultibodyPlantConfig(
        time_step=time_step, discrete_contact_approximation="lagged",
        contact_model="hydroelastic_with_fallback"), builder)
    configure_parser(Parser(plant)).AddModels(url=model_url("capsule.sdf"))
    floor = rigid_properties(contact)
    AddRigidHydroelasticProperties(properties=floor)
    plant.RegisterCollisionGeometry(plant.world_body(), RigidTransform([0.0, 0.0, -0.05]),
                                    Box(0.2, 0.2, 0.1), "floor", floor)
    set_capsule_properties(plant, scene_graph, lambda: rigid_properties(contact),
                           contact.capsule_resolution_hint, contact.capsule_hydroelastic_modulus)
    body = plant.GetBodyByName(CAPSULE_BODY)
    plant.mutable_gravity_field().set_gravity_vector([0.0, 0.0, -load / body.default_mass()])
    plant.Finalize()
    diagram = builder.Build()
    simulator = Simulator(diagram)
    context = plant.GetMyMutableContextFromRoot(simulator.get_mutable_context())
    radius = capsule_model().radius
    # Lying on its side, turned about its axis so that it settles onto a facet of its mesh.
    plant.SetFreeBodyPose(context, body, RigidTransform(
        RotationMatrix.MakeYRotation(0.5 * math.pi) @ RotationMatrix.MakeZRotation(0.35),
        [0.0, 0.0, radius]))
    simulator.AdvanceTo(1.0)
    return radius - plant.EvalBodyPoseInWorld(context, body).translation()[2]


def contact_mapping(contact: RigidWall, time_step: float, mass: float) -> dict:
    """MuJoCo's solref and solimp for the Default's contact (module docstring)."""
    low, high = PROBE_LOADS
    depths = [drake_capsule_rest_depth(contact, time_step, load) for load in PROBE_LOADS]
    stiffness = (high - low) / (depths[1] - depths[0])
    timeconst, dampratio = 2.0 * time_step, 1.0
    # Static stiffness of one MuJoCo contact with flat impedance d: m / (tc^2 zeta^2 (1 - d));
    # the capsule lying on a plane has LYING_CONTACTS of them, which together are to have
    # the probed stiffness.
    d = 1.0 - LYING_CONTACTS * mass / (timeconst ** 2 * dampratio ** 2 * stiffness)
    d = min(max(d, 0.5), 0.9999)
    weight_damping = contact.hunt_crossley_dissipation * mass * 9.81
    return {"stiffness": stiffness, "depths": depths, "solref": (timeconst, dampratio),
            "solimp": (d, d, 0.001, 0.5, 2.0),
            "period": 2.0 * math.pi * math.sqrt(mass / stiffness),
            "hc_ratio": weight_damping / (2.0 * math.sqrt(stiffness * mass))}


def mujoco_rest_depth(mujoco, mapping: dict, friction: float, load: float,
                      time_step: float, mass: float, inertia: str) -> float:
    """The peer's capsule on a plane under `load` (N), with the mapped contact: how far (m)
    it sinks below its radius after 1 s."""
    radius, half = capsule_model().radius, 0.5 * capsule_model().length
    xml = f"""
<mujoco>
  <option timestep="{time_step}" gravity="0 0 {-load / mass}" cone="elliptic" impratio="10"/>
  <default><geom condim="3" friction="{friction} 0 0" solref="{_floats(mapping['solref'])}"
    solimp="{_floats(mapping['solimp'])}"/></default>
  <worldbody>
    <geom type="plane" size="0.1 0.1 0.01"/>
    <body pos="0 0 {radius}" euler="0 1.5707963 0">
      <freejoint/>
      <inertial pos="0 0 0" mass="{mass}" fullinertia="{inertia}"/>
      <geom type="capsule" size="{radius} {half}"/>
    </body>
  </worldbody>
</mujoco>"""
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    for _ in range(int(round(1.0 / time_step))):
        mujoco.mj_step(model, data)
    return radius - float(data.qpos[2])


def _floats(values) -> str:
    return " ".join(f"{v:.9g}" for v in values)


# --- the peer ------------------------------------------------------------------------------------

class Peer:
    """The Default drag in MuJoCo (module docstring). `reset()`, then `advance_to(t)`."""

    def __init__(self, mujoco, scenario, colon, plant, mapping: dict, wall_end_s: float,
                 implicit: bool):
        self.mj = mujoco
        self.colon = colon
        self.dt = float(scenario.plant.time_step)
        contact = scenario.contact
        model = capsule_model()
        body = plant.GetBodyByName(CAPSULE_BODY)
        spatial = body.default_spatial_inertia()
        com = np.asarray(spatial.get_com(), dtype=float)
        I = spatial.Shift(com).CalcRotationalInertia().CopyToFullMatrix3()
        self.mass = float(body.default_mass())
        self.I_B = tuple(tuple(row) for row in np.asarray(I).tolist())
        self.inertia_text = _floats([I[0, 0], I[1, 1], I[2, 2], I[0, 1], I[0, 2], I[1, 2]])
        self.p_BM = tuple(float(x) for x in model.X_BM.translation() - com)   # from the c.o.m.
        self.axis_B = tuple(float(x) for x in model.X_BM.rotation().col(2))
        self.com = tuple(float(x) for x in com)
        self.m_ipm = float(scenario.capsule.ipm.moment())
        self.m_epm = float(scenario.epm.magnet.moment())
        self.implicit = implicit
        epm = scenario.epm
        self.trajectory = path_trajectory(epm.driver, colon, scenario.capsule.start_s,
                                          epm.magnet, epm.clearance)
        X_WB0 = start_pose(colon, scenario.capsule.start_s)
        gravity = plant.gravity_field().gravity_vector()

        pieces = colon_wall_pieces(scenario.colon, contact.piece_axial_length,
                                   contact.piece_max_chord_depth)
        centroids = np.array([p.mean(axis=1) for p in pieces])
        s, _, _ = colon.centerline.closest(centroids)
        kept = [p for p, at in zip(pieces, np.atleast_1d(s)) if at <= wall_end_s]
        self.wall_end_s, self.wall_pieces = wall_end_s, len(kept)
        meshes = "\n".join(f'    <mesh name="wall{i}" vertex="{_floats(p.T.ravel())}"/>'
                           for i, p in enumerate(kept))
        geoms = "\n".join(f'    <geom name="wall{i}" type="mesh" mesh="wall{i}"/>'
                          for i in range(len(kept)))
        q = X_WB0.rotation().ToQuaternion()
        xml = f"""
<mujoco model="capsule_drake_default_peer">
  <compiler angle="radian"/>
  <option timestep="{self.dt}" gravity="{_floats(gravity)}" cone="elliptic" impratio="10"
          integrator="Euler"/>
  <default>
    <geom condim="3" friction="{contact.friction} 0 0" solref="{_floats(mapping['solref'])}"
          solimp="{_floats(mapping['solimp'])}"/>
  </default>
  <asset>
{meshes}
  </asset>
  <worldbody>
{geoms}
    <body name="capsule" pos="{_floats(X_WB0.translation())}"
          quat="{_floats([q.w(), q.x(), q.y(), q.z()])}">
      <freejoint name="capsule"/>
      <inertial pos="{_floats(com)}" mass="{self.mass}" fullinertia="{self.inertia_text}"/>
      <geom name="capsule" type="capsule" size="{model.radius} {0.5 * model.length}"/>
    </body>
  </worldbody>
</mujoco>"""
        start = time.perf_counter()
        self.model = mujoco.MjModel.from_xml_string(xml)
        self.compile_seconds = time.perf_counter() - start
        self.data = mujoco.MjData(self.model)
        self.body = self.model.body("capsule").id
        self.geom = self.model.geom("capsule").id
        self.reset()

    def reset(self):
        self._step1, self._step2 = self.mj.mj_step1, self.mj.mj_step2
        self.mj.mj_resetData(self.model, self.data)
        self.mj.mj_forward(self.model, self.data)
        self.previous = None     # the implicit torque's [w_{n-1}, tau(n-1)]

    @property
    def time(self) -> float:
        return float(self.data.time)

    def step(self):
        """One step: kinematics (mj_step1), the magnet's wrench from the pose it gives, the
        rest of the step (mj_step2)."""
        data = self.data
        self._step1(self.model, data)
        x, y, z, u, v, w = stage_to_pose(self.trajectory.value(data.time).ravel()).tolist()
        m_epm = self.m_epm
        (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = data.xmat[self.body].reshape(
            3, 3).tolist()
        cx, cy, cz = data.xipos[self.body].tolist()      # the centre of mass
        a, b, c = self.p_BM
        lever = (r00 * a + r01 * b + r02 * c, r10 * a + r11 * b + r12 * c,
                 r20 * a + r21 * b + r22 * c)
        p_WM = (cx + lever[0], cy + lever[1], cz + lever[2])
        a, b, c = self.axis_B
        k = self.m_ipm
        m_W = (k * (r00 * a + r01 * b + r02 * c), k * (r10 * a + r11 * b + r12 * c),
               k * (r20 * a + r21 * b + r22 * c))
        m_E, p_E = (m_epm * u, m_epm * v, m_epm * w), (x, y, z)
        pair = dipole_pair_interaction_float(
            m_E, m_W, (p_WM[0] - x, p_WM[1] - y, p_WM[2] - z), DEFAULT_MIN_DISTANCE)
        f, tau = pair.force_target, pair.torque_target
        if self.implicit:
            R = ((r00, r01, r02), (r10, r11, r12), (r20, r21, r22))
            w_B = data.qvel[3:6].tolist()    # the free joint's angular velocity, body frame
            w_W = (r00 * w_B[0] + r01 * w_B[1] + r02 * w_B[2],
                   r10 * w_B[0] + r11 * w_B[1] + r12 * w_B[2],
                   r20 * w_B[0] + r21 * w_B[1] + r22 * w_B[2])
            K = rotational_stiffness(m_W, p_WM, lever, ((m_E, p_E),), DEFAULT_MIN_DISTANCE)
            _, tau_cm, w_n = implicit_torque(tau, f, lever, K, R, self.I_B, w_W,
                                             self.previous, self.dt)
            self.previous = tuple(w_n) + tuple(tau_cm)
        else:
            tau_cm = (tau[0] + lever[1] * f[2] - lever[2] * f[1],
                      tau[1] + lever[2] * f[0] - lever[0] * f[2],
                      tau[2] + lever[0] * f[1] - lever[1] * f[0])
        data.xfrc_applied[self.body] = (f[0], f[1], f[2], tau_cm[0], tau_cm[1], tau_cm[2])
        self._step2(self.model, data)

    def advance_to(self, t: float):
        for _ in range(int(round((t - float(self.data.time)) / self.dt))):
            self.step()

    def split_seconds(self, t: float) -> tuple[float, float]:
        """(wall seconds in MuJoCo's C, in the rest: Python) of advancing to `t`, the two
        halves of each step timed apart."""
        in_c = [0.0]

        def timed(function):
            def call(model, data):
                start = time.perf_counter()
                function(model, data)
                in_c[0] += time.perf_counter() - start
            return call

        self._step1, self._step2 = timed(self.mj.mj_step1), timed(self.mj.mj_step2)
        start = time.perf_counter()
        self.advance_to(t)
        total = time.perf_counter() - start
        self._step1, self._step2 = self.mj.mj_step1, self.mj.mj_step2
        return in_c[0], total - in_c[0]

    def position(self) -> np.ndarray:
        return np.array(self.data.qpos[:3])

    def axis(self) -> np.ndarray:
        q = self.data.qpos[3:7]
        return np.asarray(RotationMatrix(Quaternion(q / np.linalg.norm(q))).col(2))

    def contact_force(self) -> float:
        """|total wall force on the capsule| (N) of the last step."""
        mj, data = self.mj, self.data
        total = np.zeros(3)
        f6 = np.zeros(6)
        for i in range(data.ncon):
            contact = data.contact[i]
            if self.geom not in (contact.geom1, contact.geom2):
                continue
            mj.mj_contactForce(self.model, data, i, f6)
            force = contact.frame.reshape(3, 3).T @ f6[:3]   # on geom2, from geom1
            total += force if contact.geom2 == self.geom else -force
        return float(np.linalg.norm(total))


# --- the project's side ---------------------------------------------------------------------------

class Ours:
    """The Default station in Drake's Simulator, as bench_realtime.py measures it."""

    def __init__(self, scenario):
        start = time.perf_counter()
        self.station = make_station(scenario)
        self.build_seconds = time.perf_counter() - start
        self.plant = station_value(self.station, "scene.plant")
        body = self.plant.GetBodyByName(CAPSULE_BODY)
        self.capsule_geometries = set(self.plant.GetCollisionGeometriesForBody(body))
        self.dt = float(scenario.plant.time_step)
        self.reset()

    def reset(self):
        self.simulator = Simulator(self.station)
        self.simulator.Initialize()
        self.context = self.simulator.get_context()

    @property
    def time(self) -> float:
        return float(self.context.get_time())

    def advance_to(self, t: float):
        self.simulator.AdvanceTo(t)

    def _state(self) -> np.ndarray:
        return self.station.GetOutputPort("capsule.state").Eval(self.context)

    def position(self) -> np.ndarray:
        return np.array(self._state()[4:7])

    def axis(self) -> np.ndarray:
        q = self._state()[:4]
        return np.asarray(RotationMatrix(Quaternion(q / np.linalg.norm(q))).col(2))

    def contact_force(self) -> float:
        """|total wall force on the capsule| (N), from the station's contact_results."""
        results = self.station.GetOutputPort("contact_results").Eval(self.context)
        total = np.zeros(3)
        for i in range(results.num_hydroelastic_contacts()):
            info = results.hydroelastic_contact_info(i)
            force = np.asarray(info.F_Ac_W().translational())   # on geometry M's body
            on_capsule = info.contact_surface().id_M() in self.capsule_geometries
            total += force if on_capsule else -force
        for i in range(results.num_point_pair_contacts()):
            info = results.point_pair_contact_info(i)
            force = np.asarray(info.contact_force())            # on body B
            on_capsule = info.point_pair().id_B in self.capsule_geometries
            total += force if on_capsule else -force
        return float(np.linalg.norm(total))


# --- measurement ----------------------------------------------------------------------------------

def paired_repeat(engines, colon, sim_seconds: float, chunk: float):
    """(seconds of wall clock each engine spent over `sim-seconds` after the warm-up, each
    one's advance along the centreline over them in m), advanced in alternate chunks (which
    goes first alternating). Each starts afresh."""
    for engine in engines:
        engine.reset()
        engine.advance_to(WARM_UP)
    s_warm = [colon.centerline.closest(engine.position())[0] for engine in engines]
    spent = [0.0] * len(engines)
    t, k = WARM_UP, 0
    end = WARM_UP + sim_seconds
    while t < end - 1e-9:
        t = min(t + chunk, end)
        order = range(len(engines)) if k % 2 == 0 else reversed(range(len(engines)))
        for i in order:
            start = time.perf_counter()
            engines[i].advance_to(t)
            spent[i] += time.perf_counter() - start
        k += 1
    return spent, [colon.centerline.closest(engine.position())[0] - s0
                   for engine, s0 in zip(engines, s_warm)]


def physics_pass(engine, colon, sim_seconds: float) -> dict:
    """One untimed run sampled at every step: where the capsule went and what the wall
    pressed on it, over the timed window (after the warm-up) and over all of it."""
    engine.reset()
    dt = engine.dt
    steps = int(round((WARM_UP + sim_seconds) / dt))
    model = capsule_model()
    along = np.linspace(-0.5 * model.length, 0.5 * model.length, 5)
    positions, axes, forces, times = [engine.position()], [engine.axis()], [0.0], [0.0]
    for n in range(1, steps + 1):
        engine.advance_to(n * dt)
        positions.append(engine.position())
        axes.append(engine.axis())
        forces.append(engine.contact_force())
        times.append(n * dt)
    positions, axes = np.array(positions), np.array(axes)
    forces, times = np.array(forces), np.array(times)
    s, dist, theta = colon.centerline.closest(positions)
    wall = colon.wall_radius(s, theta)
    points = (positions[:, None, :] + along[None, :, None] * axes[:, None, :]).reshape(-1, 3)
    excursion = colon.excursion(points).reshape(len(positions), -1).max(axis=1) + model.radius
    window = times >= WARM_UP - 1e-9
    at_warm_up = int(np.argmax(window))
    worst = int(np.argmax(np.where(window, dist, -np.inf)))
    moved = np.flatnonzero(window & (s > s[at_warm_up] + 0.01))
    return {
        "moved_at": float(times[moved[0]]) if len(moved) else float("nan"),
        "s_start": float(s[0]), "s_warm": float(s[at_warm_up]), "s_end": float(s[-1]),
        "s_max": float(s.max()),
        "advance_cm": 100.0 * float(s[-1] - s[at_warm_up]),
        "advance_all_cm": 100.0 * float(s[-1] - s[0]),
        "force_median": float(np.median(forces[window])),
        "force_p95": float(np.percentile(forces[window], 95)),
        "force_peak": float(forces[window].max()),
        "force_peak_all": float(forces[1:].max()),
        "dist_max_mm": 1e3 * float(dist[worst]), "wall_there_mm": 1e3 * float(wall[worst]),
        "s_there": float(s[worst]),
        "room_min_mm": 1e3 * float(np.min((wall - dist)[window])),
        "excursion_mm": 1e3 * float(excursion[window].max()),
        "excursion_all_mm": 1e3 * float(excursion.max()),
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sim-seconds", type=float, default=10.0)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--chunk", type=float, default=0.5,
                        help="simulated seconds each engine advances in turn (default 0.5)")
    parser.add_argument("--wall-margin", type=float, default=0.15,
                        help="tube tiled this far (m) beyond the farthest the EPM goes")
    parser.add_argument("--explicit-torque", action="store_true",
                        help="the peer applies m x B as it is (the Default: implicit)")
    parser.add_argument("--csv", default=None, help="also write the printed rows here")
    args = parser.parse_args()
    mujoco = import_mujoco()
    if "GLIBC_TUNABLES" not in os.environ:   # as bench_realtime.py's scenarios run
        os.execve(sys.executable, [sys.executable, os.path.abspath(__file__)] + sys.argv[1:],
                  dict(os.environ, GLIBC_TUNABLES=ALLOCATOR))

    load_before = os.getloadavg()
    scenario = load_scenario(name=SCENARIO)
    driver = scenario.epm.driver
    if not isinstance(driver, AlongColon):
        sys.exit(f"the {SCENARIO} scenario's EPM is no longer driven !AlongColon")
    colon, _ = load_colon(scenario.colon)
    ours = Ours(scenario)
    mass = float(ours.plant.GetBodyByName(CAPSULE_BODY).default_mass())
    mapping = contact_mapping(scenario.contact, scenario.plant.time_step, mass)
    run_end = WARM_UP + args.sim_seconds
    epm_end = (scenario.capsule.start_s + driver.lead
               + driver.speed * max(0.0, run_end - driver.settle_time))
    start = time.perf_counter()
    peer = Peer(mujoco, scenario, colon, ours.plant, mapping, epm_end + args.wall_margin,
                implicit=scenario.magnet_force.implicit and not args.explicit_torque)
    peer_build = time.perf_counter() - start
    check = [mujoco_rest_depth(mujoco, mapping, scenario.contact.friction, load,
                               peer.dt, peer.mass, peer.inertia_text) for load in PROBE_LOADS]

    rows = []

    def row(quantity, ours_value="", peer_value="", note=""):
        def text(v):
            return f"{v:.4g}" if isinstance(v, float) else str(v)
        cells = [quantity, text(ours_value), text(peer_value), note]
        rows.append(",".join(f'"{c}"' if ("," in c or '"' in c) else c for c in cells))
        print(rows[-1], flush=True)

    row("quantity", "ours (Drake)", "peer (MuJoCo)", "note")
    row("date", datetime.date.today().isoformat())
    row("machine", f"{platform.machine()} {cpu_name()} {os.cpu_count()} cores",
        note=f"Python {platform.python_version()}; GLIBC_TUNABLES={os.environ['GLIBC_TUNABLES']}")
    row("versions", f"drake {importlib.metadata.version('drake')}", f"mujoco {mujoco.__version__}")
    row("load average before (1/5/15 min)", " ".join(f"{x:.2f}" for x in load_before))
    row("scenario", f"{SCENARIO}: {scenario.contact.label()}, step "
        f"{1e3 * scenario.plant.time_step:g} ms, field {scenario.magnet_force.field_model}",
        f"{peer.wall_pieces} convex wall pieces to s = {peer.wall_end_s:.3f} m, "
        f"{'implicit' if peer.implicit else 'explicit'} magnet torque",
        f"{args.repeats} x {args.sim_seconds:g} s after {WARM_UP:g} s, chunks of "
        f"{args.chunk:g} s alternating")
    row("build (s)", ours.build_seconds, peer_build,
        f"peer: pieces + XML + compile ({peer.compile_seconds:.2f} s compile)")
    row("contact: rest depth at 0.2 / 1 N (mm)",
        " / ".join(f"{1e3 * d:.4f}" for d in mapping["depths"]),
        " / ".join(f"{1e3 * d:.4f}" for d in check),
        f"ours: the capsule on a rigid hydroelastic floor (mostly mesh facets); "
        f"stiffness {mapping['stiffness']:.3g} N/m, period {1e3 * mapping['period']:.2f} ms, "
        f"Hunt-Crossley ratio at the weight {mapping['hc_ratio']:.3f}")
    row("contact: peer's solref / solimp", "", f"{_floats(mapping['solref'])} / "
        f"{_floats(mapping['solimp'][:3])}",
        "solref (2 dt, 1); flat impedance d with 2 m / (tc^2 (1 - d)) = the probed stiffness")

    factors = []
    for k in range(args.repeats):
        spent, advance = paired_repeat([ours, peer], colon, args.sim_seconds, args.chunk)
        rtf = [args.sim_seconds / x for x in spent]
        factors.append((rtf[0], rtf[1], rtf[0] / rtf[1]))
        row(f"real-time factor, repeat {k + 1}", rtf[0], rtf[1],
            f"ratio ours / peer {rtf[0] / rtf[1]:.3f}; advance over the window (cm) ours "
            f"{100 * advance[0]:.2f}, peer {100 * advance[1]:.2f}")
    a, b, r = zip(*factors)
    row("real-time factor, median", statistics.median(a), statistics.median(b),
        f"ratio ours / peer (median of repeats) {statistics.median(r):.3f}")
    row("load average after (1/5/15 min)", " ".join(f"{x:.2f}" for x in os.getloadavg()))
    peer.reset()
    peer.advance_to(WARM_UP)
    in_c, in_python = peer.split_seconds(run_end)
    steps = args.sim_seconds / peer.dt
    row("peer's step: MuJoCo (C) / the rest (Python) (us)", "",
        f"{1e6 * in_c / steps:.1f} / {1e6 * in_python / steps:.1f}",
        "one more pass, each step's mj_step1 and mj_step2 timed apart (the timers' own cost "
        "falls in the Python share)")

    physics = [physics_pass(engine, colon, args.sim_seconds) for engine in (ours, peer)]

    def both(name):
        return physics[0][name], physics[1][name]

    row("centreline station: start / at 1 s / end (m)",
        *(f"{p['s_start']:.4f} / {p['s_warm']:.4f} / {p['s_end']:.4f}" for p in physics),
        "the capsule centre's (Centerline.closest)")
    row("advance over the timed window (cm)", *both("advance_cm"),
        f"from t = {WARM_UP:g} s to {run_end:g} s; the EPM moves "
        f"{100 * driver.speed * (run_end - max(WARM_UP, driver.settle_time)):.1f} cm")
    row("advance from the start (cm)", *both("advance_all_cm"), f"t = 0 to {run_end:g} s")
    row("first 1 cm past the station at 1 s, at t (s)", *both("moved_at"),
        "when the capsule breaks free and follows the EPM")
    row("wall force on the capsule: median / p95 (N)",
        *(f"{p['force_median']:.4f} / {p['force_p95']:.4f}" for p in physics),
        "over the timed window, every step")
    row("wall force on the capsule: peak (N)", *both("force_peak"), "over the timed window")
    row("wall force on the capsule: peak from t = 0 (N)", *both("force_peak_all"),
        "includes the start's snap onto the wall")
    row("largest centre distance from the centreline (mm)",
        *(f"{p['dist_max_mm']:.2f} (wall radius there {p['wall_there_mm']:.2f}, "
          f"s = {p['s_there']:.3f} m)" for p in physics), "over the timed window")
    row("least room between centre and wall (mm)", *both("room_min_mm"),
        f"wall radius - centre distance; the capsule's radius is {1e3 * capsule_model().radius:g}")
    row("largest surface excursion beyond the wall (mm)", *both("excursion_mm"),
        "TubeColon.excursion of 5 axis points + radius; timed window")
    row("largest surface excursion from t = 0 (mm)", *both("excursion_all_mm"), "")
    row("farthest station reached (m)", *both("s_max"),
        f"the peer's tube is tiled to {peer.wall_end_s:.3f} m")
    if args.csv:
        Path(args.csv).write_text("\n".join(rows) + "\n")


if __name__ == "__main__":
    main()
