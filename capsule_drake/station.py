"""The capsule station: the one place that builds and wires the diagram.

    make_station(scenario, meshcat=None) -> Diagram

Blocks (each a named subsystem) and their wiring:

    epm_path (TrajectorySource) --> plant.epm_stage desired state (PD servos), or
    epm_path (poses) --> epm_arm_controller (guard, diff IK) --> plant.epm_arm desired state
    plant.body_poses --> magnet_force [--> magnet_force_hold] --> plant.applied_spatial_force
    scene_graph <--> plant (capsule, colon wall chunks or pieces, EPM stage, table)
    and, when the scenario switches them on:
    plant body poses, velocities, accelerations --> capsule.imu --> capsule.ahrs
    plant.body_poses --> capsule.magnetometer
    scene_graph.query_object --> capsule.camera --> capsule.lumen (with the capsule state)
    capsule.camera --> capsule.lumen_tracker --> pseudo_force (with the capsule state)

Exported ports, named `<instance>.<signal>`:
    capsule.state          [q (quaternion wxyz, p_WC); v (w_WC, v_WC)] of the capsule body
    capsule.B_C            field at the IPM in the capsule frame (T): a magnetometer's truth
    epm.pose               the EPM's centre and moment direction [p_WE, m_hat_W]
    epm.state              the carrier's joint state: stage [x y z yaw pitch, rates], or
                           the arm's [q (7), v (7)]
    epm.desired_state      the carrier's commanded joint state
    epm.command, epm.status  with the arm: the pose command [p_WE, m_hat_W] and the
                           controller's report (see EpmArmController)
    epm.F_W                spatial force on the EPM at its centre, world frame [torque; force]
    body_poses             every body's pose (list[RigidTransform])
    contact_results        the plant's ContactResults
    query_object           SceneGraph's query object (for cameras and distance queries)
    capsule.imu.*, capsule.ahrs.*, capsule.magnetometer.*, capsule.camera.*, capsule.lumen.*
                           the sensors' outputs, when the scenario has them (see README)
"""

from __future__ import annotations

import copy
import dataclasses
from pathlib import Path

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.common.yaml import yaml_dump_typed
from pydrake.geometry import (
    AddCompliantHydroelasticProperties,
    AddContactMaterial,
    AddRigidHydroelasticProperties,
    Box,
    Convex,
    GeometryInstance,
    IllustrationProperties,
    MakePhongIllustrationProperties,
    Mesh,
    MeshcatVisualizer,
    MeshcatVisualizerParams,
    PerceptionProperties,
    ProximityProperties,
    Role,
    RoleAssign,
)
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.multibody.meshcat import ContactVisualizer, ContactVisualizerParams
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import (
    AddMultibodyPlant,
    CoulombFriction,
    MultibodyPlant,
    ExternallyAppliedSpatialForce,
    MultibodyPlantConfig,
)
from pydrake.multibody.tree import PdControllerGains, QuaternionFloatingJoint
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import Demultiplexer, TrajectorySource, ZeroOrderHold

from capsule_drake.anatomy import build_colon, colon_assets, wall_pieces
from capsule_drake.anatomy.imported import imported_colon_assets
from capsule_drake.anatomy.windows import CameraWindows, camera_windows
from capsule_drake.epm.poses import (along_colon_trajectory, hold_above_trajectory,
                                    pose_trajectory)
from capsule_drake.scenario import AlongColon, HoldAbove, Scenario, ScenarioError
from capsule_drake.capsule.ahrs import MahonyAhrs
from capsule_drake.capsule.camera import (CameraConfig, add_camera_renderer,
                                          capsule_camera_for_frame, check_camera_config)
from capsule_drake.teleop.channel import TeleopChannel
from capsule_drake.physics.contact_monitor import ContactMonitor
from capsule_drake.epm.arm import (ARM_BASE, ARM_JOINTS, SHOULDER_HEIGHT,
                                           CommandMarker, EpmArmController, EpmGuard,
                                           MagnetPose, arm_base_pose, solve_posture)
from capsule_drake.teleop.force_feedback import ForceFeedback
from capsule_drake.teleop.haptic_master import STYLUS_SIZE, HapticMaster
from capsule_drake.capsule.imu import Imu, add_random_sources
from capsule_drake.perception.lumen_range import LumenRange
from capsule_drake.perception.lumen_tracker import LumenTracker
from capsule_drake.perception.lumen_truth import LumenTruth
from capsule_drake.physics.magnet_force import MagneticForce, MagnetSpec
from capsule_drake.capsule.magnetometer import Magnetometer
from capsule_drake.guidance.pseudo_force import PseudoForceField
from capsule_drake.capsule.render_worker import RenderWorker
from capsule_drake.epm.stage import PoseToStage
from capsule_drake.teleop.mapping import TeleopMapping
from capsule_drake.teleop.browser import BrowserOperator
from capsule_drake.teleop.operator import (ForwardSpeed, LumenRayFromTruth, SimulatedOperator,
                                           WayForward)
from capsule_drake.teleop.udp import UdpHapticDevice

MODELS_DIR = Path(__file__).resolve().parents[1] / "models"
PACKAGE = "capsule_drake"

CAPSULE_BODY = "capsule"
EPM_BODY = "epm"
STAGE_JOINTS = ("x", "y", "z", "yaw", "pitch")
# Where the arm's start-posture solve begins (rad): shoulder forward, elbow bent, flange down.
ARM_START_GUESS = (0.0, 0.6, 0.0, -1.2, 0.0, 1.2, 0.0)
TORSO_RGBA = np.array([0.93, 0.78, 0.68, 0.18])


def configure_parser(parser: Parser) -> Parser:
    """Registers the package://capsule_drake/ models with a parser."""
    parser.package_map().AddPackageXml(str(MODELS_DIR / "package.xml"))
    return parser


_COLONS: dict[str, object] = {}


def colon_for(scenario: Scenario):
    """The scenario's colon (built once per process for equal parameters)."""
    key = yaml_dump_typed(scenario.colon)
    if key not in _COLONS:
        if len(_COLONS) >= 4:
            _COLONS.pop(next(iter(_COLONS)))
        if scenario.colon.source == "procedural":
            _COLONS[key] = build_colon(scenario.colon)
        else:
            try:
                _COLONS[key] = imported_colon_assets(scenario.colon)[0]
            except (ValueError, FileNotFoundError) as e:  # MeshImportError is a ValueError
                first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
                raise ScenarioError(f"scenario: colon.source: {first}") from None
    return _COLONS[key]


def capsule_start_pose(colon, s: float) -> RigidTransform:
    """Capsule on the centerline at arc length s, its axis (camera forward) down the lumen."""
    p = colon.centerline.point_at(s)
    z = colon.centerline.tangent_at(s)
    x = np.cross([0.0, 0.0, 1.0], z)
    if np.linalg.norm(x) < 1e-6:
        x = np.cross([1.0, 0.0, 0.0], z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return RigidTransform(RotationMatrix(np.column_stack([x, y, z])), p)


def _epm_trajectory(scenario: Scenario, colon):
    path = scenario.epm.path
    make = {AlongColon: along_colon_trajectory, HoldAbove: hold_above_trajectory}[type(path)]
    try:
        return make(colon, scenario.capsule.start_s, path, scenario.epm.clearance,
                    scenario.epm.magnet)
    except ValueError as e:
        raise ScenarioError(f"scenario: {e}") from None


def _contact_properties(scenario: Scenario) -> ProximityProperties:
    props = ProximityProperties()
    mu = scenario.contact.friction
    AddContactMaterial(dissipation=scenario.contact.hunt_crossley_dissipation,
                       point_stiffness=scenario.contact.point_stiffness,
                       friction=CoulombFriction(mu, mu), properties=props)
    return props


def wall_pieces_for(scenario: Scenario, colon):
    """The colon wall's convex pieces (built once per process for equal parameters)."""
    contact = scenario.contact
    key = (yaml_dump_typed(scenario.colon), contact.piece_axial_length,
           contact.piece_max_chord_depth)
    if key not in _PIECES:
        _PIECES.clear()
        _PIECES[key] = wall_pieces(colon, axial_length=contact.piece_axial_length,
                                   max_chord_depth=contact.piece_max_chord_depth)
    return _PIECES[key]


_PIECES: dict[tuple, list] = {}


def add_colon_wall(plant, scenario: Scenario, colon) -> int:
    """Registers the colon wall's collision geometry on the world body, by the scenario's
    contact model; returns how many geometries it took."""
    world = plant.world_body()
    if scenario.contact.model == "convex_pieces":
        pieces = wall_pieces_for(scenario, colon)
        for i, vertices in enumerate(pieces):
            name = f"colon_piece_{i:04d}"
            plant.RegisterCollisionGeometry(world, RigidTransform(), Convex(vertices, name),
                                            name, _contact_properties(scenario))
        return len(pieces)
    chunks = colon_assets(scenario.colon).collision_objs
    for i, chunk in enumerate(chunks):
        props = _contact_properties(scenario)
        AddRigidHydroelasticProperties(properties=props)
        plant.RegisterCollisionGeometry(world, RigidTransform(), Mesh(str(chunk)),
                                        f"colon_wall_{i:02d}", props)
    boxes = colon.collision_boxes
    for i, (extents, centre) in enumerate(boxes):
        props = _contact_properties(scenario)
        AddRigidHydroelasticProperties(properties=props)
        plant.RegisterCollisionGeometry(world, RigidTransform(centre), Box(*extents),
                                        f"colon_surround_{i:02d}", props)
    return len(chunks) + len(boxes)


def add_colon_visuals(plant, scenario: Scenario, perception: bool = True):
    """The mucosa (its look from the mesh's own material; seen by every renderer if
    `perception`) and the torso (drawn for orientation only: cameras never see it).
    With a capsule camera the cameras see the wall of `add_camera_walls` instead."""
    assets = colon_assets(scenario.colon)
    world = plant.world_body()
    mucosa = GeometryInstance(RigidTransform(), Mesh(str(assets.visual_obj)), "colon_mucosa")
    mucosa.set_illustration_properties(IllustrationProperties())
    if perception:
        mucosa.set_perception_properties(PerceptionProperties())
    plant.RegisterVisualGeometry(world, mucosa)
    torso = GeometryInstance(RigidTransform(), Mesh(str(assets.torso_obj)), "torso")
    rgba = colon_for(scenario).abdomen.display_rgba or TORSO_RGBA
    torso.set_illustration_properties(MakePhongIllustrationProperties(rgba))
    plant.RegisterVisualGeometry(world, torso)


def add_camera_walls(plant, scene_graph, scenario: Scenario, colon, config: CameraConfig):
    """The colon wall as capsule cameras see it, and their renderers. Call before Finalize,
    after every other model: the cameras see nothing else (the geometry registered so far
    loses its perception role).

    The camera mesh is cut into windows along the colon (anatomy/windows.py), each accepted
    by a renderer of its own (`<config.renderer_name>.<k>`, added here), so a frame draws
    only the stretch the camera is in. Returns renderer_for(p_WC) -> the renderer for a
    camera at p_WC (a `CameraWalls`); another camera in the colon sees the wall through it.
    """
    assets = colon_assets(scenario.colon)
    windows = camera_windows(colon, assets.visual_obj.parent, config.far,
                             config.window_spacing)
    if len(windows.objs) == 1:
        names = [config.renderer_name]
    else:
        names = [f"{config.renderer_name}.{k:02d}" for k in range(len(windows.objs))]
    for name in names:
        add_camera_renderer(scene_graph, config, name)
    visuals = [(f"window_{k:02d}", obj, name)
               for k, (obj, name) in enumerate(zip(windows.objs, names))]
    # pydrake cannot set the ("renderer", "accepting") property (a set of names), so the
    # walls come as an SDF model with <drake:accepting_renderer> tags.
    body = "".join(
        f"<visual name='{name}'><geometry><mesh><uri>{Path(obj).resolve().as_uri()}</uri>"
        f"</mesh></geometry><drake:accepting_renderer>{renderer}</drake:accepting_renderer>"
        "</visual>" for name, obj, renderer in visuals)
    sdf = ("<?xml version='1.0'?><sdf version='1.9' xmlns:drake='http://drake.mit.edu'>"
           f"<model name='camera_walls_{config.renderer_name}'><static>true</static>"
           f"<link name='walls'>{body}"
           "</link></model></sdf>")
    instance, = Parser(plant).AddModelsFromString(sdf, "sdf")
    for index in plant.GetBodyIndices(instance):
        for geometry_id in plant.GetVisualGeometriesForBody(plant.get_body(index)):
            scene_graph.RemoveRole(plant.get_source_id(), geometry_id, Role.kIllustration)
    # A capsule camera sees only the inside of the colon. Everything else (the capsule's own
    # shell, the EPM, the arm, the table) would sit in every window's renderer, unseen, and
    # each renderer re-poses its moving geometry at every physics step: with the arm's links
    # in 16 renderers that cost ~1.5 s per simulated second (measured), more than drawing.
    inspector = scene_graph.model_inspector()
    source = plant.get_source_id()
    for geometry_id in inspector.GetAllGeometryIds(Role.kPerception):
        if not inspector.BelongsToSource(geometry_id, source):
            continue
        body = plant.GetBodyFromFrameId(inspector.GetFrameId(geometry_id))
        if not plant.GetModelInstanceName(body.model_instance()).startswith("camera_walls_"):
            scene_graph.RemoveRole(source, geometry_id, Role.kPerception)
    return CameraWalls(windows, names, colon.centerline)


@dataclasses.dataclass
class CameraWalls:
    """The camera windows and their renderers; called with a camera's world position, it
    names the renderer to draw with (the window of the centreline foot's arc length)."""

    windows: CameraWindows
    renderer_names: list[str]
    centerline: object

    def __call__(self, p_WC) -> str:
        s = self.centerline.closest(np.asarray(p_WC, dtype=float))[0]
        return self.renderer_names[self.windows.index_at(s)]


def add_capsule_drag(plant, scenario: Scenario):
    """With a speed-dependent resistance in the scenario (contact.drag_*), the capsule's
    floating joint is declared here, with that damping (relative to the world, where the
    colon is); otherwise Finalize gives it a free one. Call before Finalize."""
    c = scenario.contact
    if c.drag_translational > 0.0 or c.drag_rotational > 0.0:
        add_damped_capsule_joint(plant, c.drag_translational, c.drag_rotational)


def add_damped_capsule_joint(plant, translational: float, angular: float):
    """The capsule's floating joint "capsule_floating", damped against the world
    (N s/m, N m s). Call before Finalize."""
    capsule = plant.GetBodyByName(CAPSULE_BODY)
    return plant.AddJoint(QuaternionFloatingJoint(
        "capsule_floating", plant.world_frame(), capsule.body_frame(),
        angular_damping=angular, translational_damping=translational))


def set_capsule_contact(plant, scene_graph, scenario: Scenario):
    """Gives the capsule's collision geometry the scenario's contact properties (compliant
    hydroelastic, or point contact for the convex-pieces wall). Call before Finalize."""
    capsule = plant.GetBodyByName(CAPSULE_BODY)
    for geometry_id in plant.GetCollisionGeometriesForBody(capsule):
        props = _contact_properties(scenario)
        if scenario.contact.model == "convex_pieces":
            scene_graph.AssignRole(plant.get_source_id(), geometry_id, props,
                                   RoleAssign.kReplace)
            continue
        AddCompliantHydroelasticProperties(
            resolution_hint=scenario.contact.capsule_resolution_hint,
            hydroelastic_modulus=scenario.contact.capsule_hydroelastic_modulus,
            properties=props)
        scene_graph.AssignRole(plant.get_source_id(), geometry_id, props, RoleAssign.kReplace)


def _add_capsule_sensors(builder, plant, scenario: Scenario, magnets, X_WB0):
    """IMU (+ AHRS) and magnetometer on the capsule, as the scenario asks; their outputs are
    exported as capsule.imu.<signal>, capsule.ahrs.<signal>, capsule.magnetometer.<signal>."""
    capsule = plant.GetBodyByName(CAPSULE_BODY)
    config = scenario.capsule
    if config.imu is not None:
        imu = builder.AddNamedSystem("capsule.imu", Imu(plant, capsule, config.imu))
        imu.connect_to_plant(builder, plant)
        for i in range(imu.num_output_ports()):
            name = imu.get_output_port(i).get_name()
            builder.ExportOutput(imu.get_output_port(i), f"capsule.imu.{name}")
        if config.ahrs is not None:
            ahrs_config = config.ahrs
            if not ahrs_config.initial_q_WB:
                q = X_WB0.rotation().ToQuaternion()
                ahrs_config = dataclasses.replace(ahrs_config,
                                                  initial_q_WB=[q.w(), q.x(), q.y(), q.z()])
            gravity = float(np.linalg.norm(plant.gravity_field().gravity_vector()))
            ahrs = builder.AddNamedSystem("capsule.ahrs", MahonyAhrs(
                config.imu.sample_rate, ahrs_config, R_BS=config.imu.X_BS().rotation(),
                gravity=gravity))
            builder.Connect(imu.GetOutputPort("accel"), ahrs.get_accel_input_port())
            builder.Connect(imu.GetOutputPort("gyro"), ahrs.get_gyro_input_port())
            builder.ExportOutput(ahrs.get_q_WB_output_port(), "capsule.ahrs.q_WB")
            builder.ExportOutput(ahrs.get_gyro_bias_output_port(), "capsule.ahrs.gyro_bias")
    if config.magnetometer is not None:
        magnetometer = builder.AddNamedSystem("capsule.magnetometer", Magnetometer(
            plant, capsule, magnets, config.magnetometer, field_model=scenario.magnet_model))
        builder.Connect(plant.get_body_poses_output_port(),
                        magnetometer.get_body_poses_input_port())
        add_random_sources(builder, magnetometer.get_noise_input_ports(), magnetometer.period())
        builder.ExportOutput(magnetometer.get_B_S_output_port(), "capsule.magnetometer.B_S")
        builder.ExportOutput(magnetometer.get_B_S_true_output_port(),
                             "capsule.magnetometer.B_S_true")


def _add_camera(builder, plant, scene_graph, scenario: Scenario, colon, capsule_instance,
                renderer_for):
    """The capsule camera (its own renderer, light at the lens) and the lumen ground truth;
    exported as capsule.camera.<signal> and capsule.lumen.<signal>."""
    config = scenario.capsule.camera
    camera_frame = plant.GetFrameByName("camera", capsule_instance)
    # With camera walls the camera sees only the anchored wall (add_camera_walls), so its
    # depth image can be drawn on demand, and frames with latency on another core.
    static = renderer_for is not None
    worker = (RenderWorker(scenario.colon, config)
              if static and config.latency > 0.0 and config.render_process else None)
    camera = builder.AddNamedSystem("capsule.camera", capsule_camera_for_frame(
        plant, camera_frame, config, renderer_for, static_scene=static, worker=worker))
    builder.Connect(scene_graph.get_query_output_port(), camera.get_query_object_input_port())
    builder.ExportOutput(camera.get_rgb_image_output_port(), "capsule.camera.rgb_image")
    builder.ExportOutput(camera.get_depth_image_output_port(), "capsule.camera.depth_image")
    builder.ExportOutput(camera.get_frame_info_output_port(), "capsule.camera.frame_info")
    builder.ExportOutput(camera.get_frame_pose_output_port(), "capsule.camera.frame_pose")
    lumen = builder.AddNamedSystem("capsule.lumen", LumenTruth(
        colon, camera.lens, camera_frame.GetFixedPoseInBodyFrame(),
        lookahead=scenario.capsule.lumen_lookahead, depth_is_range=True))
    builder.Connect(plant.get_state_output_port(capsule_instance),
                    lumen.GetInputPort("capsule_state"))
    builder.Connect(camera.get_depth_image_output_port(), lumen.GetInputPort("depth"))
    for name in ("lumen_pixel", "lumen_visible", "lumen_point_W"):
        builder.ExportOutput(lumen.GetOutputPort(name), f"capsule.lumen.{name}")
    if scenario.capsule.lumen_tracker is not None:
        tracker = builder.AddNamedSystem("capsule.lumen_tracker", LumenTracker(
            camera.lens, scenario.capsule.lumen_tracker, period=camera.tick(),
            delay=camera.latency() + 1e-6))
        builder.Connect(camera.get_rgb_image_output_port(), tracker.GetInputPort("rgb_image"))
        builder.Connect(camera.get_frame_info_output_port(), tracker.GetInputPort("frame_info"))
        for i in range(tracker.num_output_ports()):
            port = tracker.get_output_port(i)
            builder.ExportOutput(port, f"capsule.lumen_tracker.{port.get_name()}")


def _add_pseudo_force(builder, plant, scenario: Scenario, colon, capsule_instance):
    """The operator's pseudo-force from the lumen tracker (when there is one) and the
    capsule's state; exported as pseudo_force.<signal>."""
    X_BC = plant.GetFrameByName("camera", capsule_instance).GetFixedPoseInBodyFrame()
    force = builder.AddNamedSystem("pseudo_force", PseudoForceField(
        colon, scenario.pseudo_force, X_BC))
    builder.Connect(plant.get_state_output_port(capsule_instance),
                    force.GetInputPort("capsule_state"))
    if scenario.capsule.lumen_tracker is not None:
        tracker = builder.GetSubsystemByName("capsule.lumen_tracker")
        for name in ("lumen_ray", "lumen_visible", "lumen_confidence"):
            builder.Connect(tracker.GetOutputPort(name), force.GetInputPort(name))
    for i in range(force.num_output_ports()):
        port = force.get_output_port(i)
        builder.ExportOutput(port, f"pseudo_force.{port.get_name()}")


def _add_teleop(builder, plant, scene_graph, scenario: Scenario, colon, capsule_instance,
                trajectory, meshcat):
    """The haptic loop (scenario.teleop): operator -> device -> channel -> mapping -> EPM
    command (returned, for the mount), and force feedback (pseudo-force + the capsule's
    contact, saturated) -> channel -> passivity -> device; the channel only when the link
    is not ideal (teleop.channel_energy then). Exports teleop.<signal>."""
    teleop = scenario.teleop
    capsule = plant.GetBodyByName(CAPSULE_BODY)
    X_BC = plant.GetFrameByName("camera", capsule_instance).GetFixedPoseInBodyFrame()
    X_B_ipm = plant.GetFrameByName("ipm", capsule_instance).GetFixedPoseInBodyFrame()
    floor_guard = EpmGuard(colon.abdomen, scenario.epm.magnet, scenario.epm.clearance,
                           np.zeros(3), np.inf)
    first = pose_trajectory(trajectory).value(trajectory.start_time()).ravel()
    start = capsule_start_pose(colon, scenario.capsule.start_s)
    mapping = builder.AddNamedSystem("teleop.mapping", TeleopMapping(
        teleop.mapping, X_BC, X_B_ipm.translation(), floor_guard.lowest_centre_height,
        first, start.rotation().col(2)))
    builder.Connect(plant.get_state_output_port(capsule_instance),
                    mapping.GetInputPort("capsule_state"))
    if teleop.mapping.assist and scenario.capsule.lumen_tracker is not None:
        tracker = builder.GetSubsystemByName("capsule.lumen_tracker")
        builder.Connect(tracker.GetOutputPort("lumen_ray"), mapping.GetInputPort("lumen_ray"))
        builder.Connect(tracker.GetOutputPort("lumen_visible"),
                        mapping.GetInputPort("lumen_visible"))
        camera = builder.GetSubsystemByName("capsule.camera")
        if scenario.capsule.camera.render_depth:
            free = builder.AddNamedSystem("teleop.lumen_range",
                                          LumenRange(scenario.capsule.camera.far))
            builder.Connect(camera.GetOutputPort("depth_image"),
                            free.GetInputPort("depth_image"))
            builder.Connect(tracker.GetOutputPort("lumen_pixel"),
                            free.GetInputPort("lumen_pixel"))
            builder.Connect(tracker.GetOutputPort("lumen_visible"),
                            free.GetInputPort("lumen_visible"))
            builder.Connect(free.GetOutputPort("range"), mapping.GetInputPort("lumen_range"))
            builder.ExportOutput(free.GetOutputPort("range"), "teleop.lumen_range")

    # What the operator feels: the pseudo-force (if any) and the capsule's contact.
    monitor = builder.AddNamedSystem("teleop.contact", ContactMonitor(
        plant.GetCollisionGeometriesForBody(capsule)))
    builder.Connect(plant.get_contact_results_output_port(),
                    monitor.GetInputPort("contact_results"))
    rpy = (scenario.pseudo_force.device_from_camera_rpy_deg
           if scenario.pseudo_force is not None else (180.0, 0.0, 0.0))
    feedback = builder.AddNamedSystem("teleop.feedback", ForceFeedback(
        X_BC, teleop.contact_gain, teleop.device.force_limit, rpy))
    builder.Connect(monitor.GetOutputPort("capsule_force_W"),
                    feedback.GetInputPort("capsule_force_W"))
    builder.Connect(plant.get_state_output_port(capsule_instance),
                    feedback.GetInputPort("capsule_state"))
    if scenario.pseudo_force is not None:
        builder.Connect(builder.GetSubsystemByName("pseudo_force").GetOutputPort("F_D"),
                        feedback.GetInputPort("pseudo_force_D"))

    # The link between device and robot. An ideal one (no delay, jitter or loss: the
    # default, as the seed paper assumes) is a wire: nothing to stabilise, and the two 1 kHz
    # channel systems would cost ~0.2 s per simulated second for nothing.
    channel = None
    force_to_device = feedback.GetOutputPort("F_D")
    if not all(c.delay == 0 and c.jitter == 0 and c.loss == 0
               for c in (teleop.channel.forward, teleop.channel.backward)):
        channel = builder.AddNamedSystem("teleop.channel", TeleopChannel(
            STYLUS_SIZE, copy.deepcopy(teleop.channel)))
        builder.Connect(channel.GetOutputPort("stylus_out"), mapping.GetInputPort("stylus"))
        builder.Connect(channel.GetOutputPort("stylus_age"),
                        mapping.GetInputPort("stylus_age"))
        builder.Connect(feedback.GetOutputPort("F_D"), channel.GetInputPort("force_in"))
        force_to_device = channel.GetOutputPort("force_out")

    if teleop.operator == "simulated":
        device = builder.AddNamedSystem("teleop.device", HapticMaster(teleop.device))
        hand = builder.AddNamedSystem("teleop.operator", SimulatedOperator(
            teleop.simulated, teleop.device.workspace_half_extents))
        builder.Connect(device.GetOutputPort("stylus"), hand.GetInputPort("stylus"))
        builder.Connect(device.GetOutputPort("stylus_velocity"),
                        hand.GetInputPort("stylus_velocity"))
        builder.Connect(hand.GetOutputPort("hand_force"), device.GetInputPort("hand_force"))
        builder.Connect(hand.GetOutputPort("buttons"), device.GetInputPort("buttons"))
        speed = builder.AddNamedSystem("teleop.forward_speed",
                                       ForwardSpeed(X_BC.rotation().col(2)))
        builder.Connect(plant.get_state_output_port(capsule_instance),
                        speed.GetInputPort("capsule_state"))
        builder.Connect(speed.GetOutputPort("forward_speed"),
                        hand.GetInputPort("forward_speed"))
        way = builder.AddNamedSystem("teleop.way_forward", WayForward(
            X_BC.rotation().matrix(), start.translation()))
        builder.Connect(plant.get_state_output_port(capsule_instance),
                        way.GetInputPort("capsule_state"))
        builder.Connect(way.GetOutputPort("way_C"), hand.GetInputPort("way_forward"))
        if teleop.lumen_source == "tracker":
            tracker = builder.GetSubsystemByName("capsule.lumen_tracker")
            builder.Connect(tracker.GetOutputPort("lumen_visible"),
                            hand.GetInputPort("lumen_visible"))
            builder.Connect(tracker.GetOutputPort("lumen_ray"), hand.GetInputPort("lumen_ray"))
        else:
            truth = builder.AddNamedSystem("teleop.lumen_seen", LumenRayFromTruth(
                builder.GetSubsystemByName("capsule.camera").lens))
            lumen = builder.GetSubsystemByName("capsule.lumen")
            builder.Connect(lumen.GetOutputPort("lumen_pixel"), truth.GetInputPort("pixel"))
            builder.Connect(lumen.GetOutputPort("lumen_visible"),
                            truth.GetInputPort("visible"))
            builder.Connect(truth.GetOutputPort("visible"), hand.GetInputPort("lumen_visible"))
            builder.Connect(truth.GetOutputPort("ray"), hand.GetInputPort("lumen_ray"))
        builder.ExportOutput(hand.GetOutputPort("intent"), "teleop.intent")
        builder.Connect(force_to_device, device.GetInputPort("feedback_force"))
        if channel is not None:
            builder.Connect(device.GetOutputPort("stylus_velocity"),
                            channel.GetInputPort("stylus_velocity"))
        builder.ExportOutput(device.GetOutputPort("motor_force"), "teleop.motor_force")
    elif teleop.operator == "udp":
        device = builder.AddNamedSystem("teleop.device", UdpHapticDevice(teleop.udp))
        builder.Connect(force_to_device, device.GetInputPort("force_D"))
        builder.Connect(device.GetOutputPort("link_ok"), mapping.GetInputPort("link_ok"))
        builder.ExportOutput(device.GetOutputPort("link_ok"), "teleop.link_ok")
        builder.ExportOutput(device.GetOutputPort("stats"), "teleop.udp_stats")
    else:  # browser
        device = builder.AddNamedSystem("teleop.device", BrowserOperator(
            meshcat, teleop.device, scenario.capsule.camera))
        builder.Connect(force_to_device, device.GetInputPort("feedback_force"))
        for name in ("rgb_image", "frame_info"):
            builder.Connect(builder.GetSubsystemByName("capsule.camera").GetOutputPort(name),
                            device.GetInputPort(name))
        if scenario.capsule.lumen_tracker is not None:
            tracker = builder.GetSubsystemByName("capsule.lumen_tracker")
            for name in ("lumen_pixel", "lumen_visible"):
                builder.Connect(tracker.GetOutputPort(name), device.GetInputPort(name))
    if channel is not None:
        split = builder.AddNamedSystem("teleop.stylus_position",
                                       Demultiplexer([3, STYLUS_SIZE - 3]))
        builder.Connect(device.GetOutputPort("stylus"), split.get_input_port())
        builder.Connect(device.GetOutputPort("stylus"), channel.GetInputPort("stylus_in"))
        builder.Connect(split.get_output_port(0), channel.GetInputPort("stylus_position"))
        builder.ExportOutput(channel.GetOutputPort("energy"), "teleop.channel_energy")
    else:
        builder.Connect(device.GetOutputPort("stylus"), mapping.GetInputPort("stylus"))
    builder.ExportOutput(device.GetOutputPort("stylus"), "teleop.stylus")
    builder.ExportOutput(feedback.GetOutputPort("F_D"), "teleop.feedback_D")
    builder.ExportOutput(monitor.GetOutputPort("capsule_force_W"), "teleop.contact_force_W")
    builder.ExportOutput(mapping.GetOutputPort("heading"), "teleop.heading")
    return mapping.GetOutputPort("epm_command")


def _add_meshcat(builder, plant, scene_graph, meshcat, period: float):
    """Illustration geometry and contact forces in Meshcat; the view looks at the abdomen
    from the patient's right, above the table."""
    MeshcatVisualizer.AddToBuilder(builder, scene_graph, meshcat,
                                   MeshcatVisualizerParams(publish_period=period))
    ContactVisualizer.AddToBuilder(builder, plant, meshcat,
                                   ContactVisualizerParams(publish_period=period,
                                                           newtons_per_meter=20.0))
    meshcat.SetCameraPose(camera_in_world=[-0.55, -0.35, 0.65], target_in_world=[0.0, 0.0, 0.1])


class StageMount:
    """The EPM on the five-axis stage (models/epm_stage.sdf), its joints' PD servos driven
    straight from the path's stage trajectory."""

    model_name = "epm_stage"

    def __init__(self, scenario: Scenario):
        self.scenario = scenario

    def add_models(self, plant, parser):
        """Before Finalize: the stage, its servo gains; returns its model instance."""
        self.instance, = parser.AddModels(url=f"package://{PACKAGE}/epm_stage.sdf")
        # The stage is a servo that holds the EPM wherever it is sent (a stiff robot arm
        # would); its weight is the stage's business, not the simulation's.
        plant.set_gravity_enabled(self.instance, False)
        epm = self.scenario.epm
        for name in STAGE_JOINTS:
            gains = epm.translation_gains if name in ("x", "y", "z") else epm.rotation_gains
            plant.GetJointActuatorByName(name, self.instance).set_controller_gains(
                PdControllerGains(p=gains.p, d=gains.d))
        return self.instance

    def connect(self, builder, plant, colon, trajectory, external_command: bool = False):
        """After Finalize: start where the path begins, follow it (or, with
        `external_command`, a pose command: returns the input port to connect it to);
        exports epm.state (stage joints [x y z yaw pitch, rates]) and epm.desired_state."""
        actuated = [plant.get_joint_actuator(i).joint().name()
                    for i in plant.GetJointActuatorIndices(self.instance)]
        assert tuple(actuated) == STAGE_JOINTS, actuated
        q0 = trajectory.value(trajectory.start_time()).ravel()
        for name, value in zip(STAGE_JOINTS, q0):
            joint = plant.GetJointByName(name, self.instance)
            if name in ("x", "y", "z"):
                joint.set_default_translation(value)
            else:
                joint.set_default_angle(value)
        builder.ExportOutput(plant.get_state_output_port(self.instance), "epm.state")
        if external_command:
            stage = builder.AddNamedSystem("epm_stage_command", PoseToStage(q0))
            builder.Connect(stage.get_output_port(),
                            plant.get_desired_state_input_port(self.instance))
            builder.ExportOutput(stage.get_output_port(), "epm.desired_state")
            return stage.GetInputPort("epm_command")
        epm_path = builder.AddNamedSystem(
            "epm_path", TrajectorySource(trajectory, output_derivative_order=1))
        builder.Connect(epm_path.get_output_port(),
                        plant.get_desired_state_input_port(self.instance))
        builder.ExportOutput(epm_path.get_output_port(), "epm.desired_state")
        return None


class ArmMount:
    """The EPM on the 7-DoF arm (models/epm_arm.sdf): the path's poses go through the
    EpmArmController (guard, differential IK) to the joints' PD servos."""

    model_name = "epm_arm"

    def __init__(self, scenario: Scenario):
        self.scenario = scenario
        self.config = scenario.epm.arm

    def add_models(self, plant, parser):
        """Before Finalize: the arm welded at its base pose, its servo gains."""
        self.instance, = parser.AddModels(url=f"package://{PACKAGE}/epm_arm.sdf")
        plant.WeldFrames(plant.world_frame(), plant.GetFrameByName(ARM_BASE, self.instance),
                         arm_base_pose(self.config))
        # A torque-controlled arm compensates its own weight; the magnet's pull it must bear.
        plant.set_gravity_enabled(self.instance, False)
        for name, p, d in zip(ARM_JOINTS, self.config.joint_stiffness,
                              self.config.joint_damping):
            plant.GetJointActuatorByName(name, self.instance).set_controller_gains(
                PdControllerGains(p=p, d=d))
        return self.instance

    def controller_plant(self):
        """The controller's own model: the arm alone, welded at the same pose."""
        arm = MultibodyPlant(0.0)
        instance, = configure_parser(Parser(arm)).AddModels(
            url=f"package://{PACKAGE}/epm_arm.sdf")
        arm.WeldFrames(arm.world_frame(), arm.GetFrameByName(ARM_BASE, instance),
                       arm_base_pose(self.config))
        arm.Finalize()
        return arm

    def connect(self, builder, plant, colon, trajectory, external_command: bool = False):
        """After Finalize: the controller, the arm's start posture (solved to reach the
        path's first pose), the path as its command (or, with `external_command`, returns
        the controller's command input to connect); exports epm.state (arm [q, v]),
        epm.desired_state, epm.command (the path's) and epm.status (see EpmArmController)."""
        scenario = self.scenario
        poses = pose_trajectory(trajectory)
        first = poses.value(poses.start_time()).ravel()
        shoulder = arm_base_pose(self.config).multiply([0.0, 0.0, SHOULDER_HEIGHT])
        guard = EpmGuard(colon.abdomen, scenario.epm.magnet, scenario.epm.clearance,
                         shoulder, self.config.reach)
        arm = self.controller_plant()
        guess = (np.radians(self.config.posture_deg) if self.config.posture_deg
                 else np.array(ARM_START_GUESS))
        probe = EpmArmController(arm, self.config, guard, guess)
        q0, position_error, axis_error = solve_posture(probe, guess, first[:3], first[3:])
        if position_error > 1e-3 or axis_error > 1e-2:
            raise ScenarioError(
                f"scenario: epm.arm cannot reach the path's first pose (misses by "
                f"{position_error * 1000:.1f} mm, {np.degrees(axis_error):.1f} deg): move "
                "epm.arm.base_xyz closer or give epm.arm.posture_deg")
        posture = np.radians(self.config.posture_deg) if self.config.posture_deg else q0
        controller = builder.AddNamedSystem("epm_arm_controller", EpmArmController(
            arm, dataclasses.replace(self.config, posture_deg=list(np.degrees(posture))),
            guard, q0))
        for name, value in zip(ARM_JOINTS, q0):
            plant.GetJointByName(name, self.instance).set_default_angle(value)
        builder.Connect(plant.get_state_output_port(self.instance),
                        controller.GetInputPort("arm_state"))
        builder.Connect(controller.GetOutputPort("arm_desired_state"),
                        plant.get_desired_state_input_port(self.instance))
        builder.ExportOutput(plant.get_state_output_port(self.instance), "epm.state")
        builder.ExportOutput(controller.GetOutputPort("arm_desired_state"),
                             "epm.desired_state")
        builder.ExportOutput(controller.GetOutputPort("status"), "epm.status")
        if external_command:
            return controller.GetInputPort("epm_command")
        epm_path = builder.AddNamedSystem("epm_path", TrajectorySource(poses))
        builder.Connect(epm_path.get_output_port(), controller.GetInputPort("epm_command"))
        builder.ExportOutput(epm_path.get_output_port(), "epm.command")
        return None


def make_station(scenario: Scenario, meshcat=None, *, apply_magnet_force: bool = True,
                 external_epm_command: bool = False):
    """Builds the diagram for `scenario`; adds Meshcat visualisation only if `meshcat` is given.

    Pure construction: the scenario is not modified, nothing is simulated.
    `apply_magnet_force=False` leaves the magnet system's outputs available but does not
    apply its forces (the capsule lies on the wall under gravity): for ablation benchmarks.
    `external_epm_command=True` (without teleop): the EPM follows the diagram's input port
    `epm.command` ([p_WE, m_hat_W]) instead of the scenario's path, e.g. from a navigator.
    """
    if external_epm_command and scenario.teleop is not None:
        raise ScenarioError("scenario: an external EPM command and teleop both drive the EPM")
    colon = colon_for(scenario)
    # The capsule must start inside the colon, clear of both end caps.
    half_length = 0.02
    if not half_length <= scenario.capsule.start_s <= colon.centerline.length - half_length:
        raise ScenarioError(
            f"scenario: capsule.start_s {scenario.capsule.start_s} m is outside this colon "
            f"(the capsule fits between {half_length} and "
            f"{colon.centerline.length - half_length:.3f} m)")
    builder = DiagramBuilder()
    plant, scene_graph = AddMultibodyPlant(
        MultibodyPlantConfig(
            time_step=scenario.time_step,
            discrete_contact_approximation=scenario.contact.discrete_contact_approximation,
            # Point contact is cheap enough that sampling outputs is a measurable cost.
            use_sampled_output_ports=scenario.contact.model != "convex_pieces"),
        builder)
    plant.set_name("plant")
    parser = configure_parser(Parser(plant))
    capsule_instance, = parser.AddModels(url=f"package://{PACKAGE}/capsule.sdf")
    mount = ArmMount(scenario) if scenario.epm.mount == "arm" else StageMount(scenario)
    epm_instance = mount.add_models(plant, parser)
    parser.AddModels(url=f"package://{PACKAGE}/table.sdf")
    add_colon_wall(plant, scenario, colon)
    camera_config = scenario.capsule.camera
    add_colon_visuals(plant, scenario, perception=camera_config is None)
    renderer_for = None
    if camera_config is not None:
        try:
            check_camera_config(camera_config)
        except ValueError as e:
            raise ScenarioError(f"scenario: capsule.camera: {e}") from None
        renderer_for = add_camera_walls(plant, scene_graph, scenario, colon, camera_config)
    set_capsule_contact(plant, scene_graph, scenario)
    add_capsule_drag(plant, scenario)

    plant.Finalize()

    # Initial state: capsule on the centerline at its start, the EPM where its path begins.
    start_pose = capsule_start_pose(colon, scenario.capsule.start_s)
    if plant.HasJointNamed("capsule_floating"):  # declared with damping (add_capsule_drag)
        plant.GetJointByName("capsule_floating").SetDefaultPose(start_pose)
    else:
        plant.SetDefaultFloatingBaseBodyPose(plant.GetBodyByName(CAPSULE_BODY), start_pose)
    trajectory, _ = _epm_trajectory(scenario, colon)
    command_input = mount.connect(
        builder, plant, colon, trajectory,
        external_command=scenario.teleop is not None or external_epm_command)
    if external_epm_command:
        builder.ExportInput(command_input, "epm.command")

    X_C_ipm = plant.GetFrameByName("ipm", capsule_instance).GetFixedPoseInBodyFrame()

    def cylinder(geometry):
        return list(geometry.dimensions) if geometry.shape == "cylinder" else []

    magnets = [
        MagnetSpec(name="ipm", body=CAPSULE_BODY, model_instance="capsule",
                   p_BM=list(X_C_ipm.translation()),
                   axis_B=list(X_C_ipm.rotation().col(2)),
                   moment=scenario.capsule.ipm.moment(),
                   cylinder=cylinder(scenario.capsule.ipm)),
        MagnetSpec(name="epm", body=EPM_BODY, model_instance=mount.model_name,
                   p_BM=[0.0, 0.0, 0.0], axis_B=[0.0, 0.0, 1.0],
                   moment=scenario.epm.magnet.moment(),
                   cylinder=cylinder(scenario.epm.magnet)),
    ]
    magnet_force = builder.AddNamedSystem("magnet_force", MagneticForce(
        plant, magnets, field_model=scenario.magnet_model))
    builder.Connect(plant.get_body_poses_output_port(),
                    magnet_force.get_body_poses_input_port())
    if apply_magnet_force:
        force_port = magnet_force.get_applied_spatial_force_output_port()
        if scenario.magnet_update_period > scenario.time_step:
            # Typed as list[ExternallyAppliedSpatialForce], empty until the first sample.
            no_forces = AbstractValue.Make([ExternallyAppliedSpatialForce()])
            no_forces.set_value([])
            hold = builder.AddNamedSystem("magnet_force_hold", ZeroOrderHold(
                scenario.magnet_update_period, no_forces))
            builder.Connect(force_port, hold.get_input_port())
            force_port = hold.get_output_port()
        builder.Connect(force_port, plant.get_applied_spatial_force_input_port())

    # A sensor's configuration is checked by the system it configures: a bad value is the
    # user's mistake, reported as such.
    try:
        _add_capsule_sensors(builder, plant, scenario, magnets,
                             capsule_start_pose(colon, scenario.capsule.start_s))
    except ValueError as e:
        raise ScenarioError(f"scenario: capsule sensors: {e}") from None
    if scenario.capsule.camera is not None:
        try:
            _add_camera(builder, plant, scene_graph, scenario, colon, capsule_instance,
                        renderer_for)
        except ValueError as e:
            raise ScenarioError(f"scenario: capsule.camera: {e}") from None

    if scenario.pseudo_force is not None:
        _add_pseudo_force(builder, plant, scenario, colon, capsule_instance)
    if scenario.teleop is not None:
        command_output = _add_teleop(builder, plant, scene_graph, scenario, colon,
                                     capsule_instance, trajectory, meshcat)
        builder.Connect(command_output, command_input)
        builder.ExportOutput(command_output, "epm.command")

    builder.ExportOutput(plant.get_state_output_port(capsule_instance), "capsule.state")
    builder.ExportOutput(magnet_force.get_B_B_output_port("ipm"), "capsule.B_C")
    epm_pose = builder.AddNamedSystem("epm_pose", MagnetPose(
        plant, plant.GetBodyByName(EPM_BODY, epm_instance)))
    builder.Connect(plant.get_body_poses_output_port(), epm_pose.GetInputPort("body_poses"))
    builder.ExportOutput(epm_pose.GetOutputPort("pose"), "epm.pose")
    builder.ExportOutput(magnet_force.get_F_W_output_port("epm"), "epm.F_W")
    builder.ExportOutput(plant.get_body_poses_output_port(), "body_poses")
    builder.ExportOutput(plant.get_contact_results_output_port(), "contact_results")
    builder.ExportOutput(scene_graph.get_query_output_port(), "query_object")

    if meshcat is not None:
        _add_meshcat(builder, plant, scene_graph, meshcat, scenario.visual_period)
        if scenario.epm.mount == "arm" or scenario.teleop is not None:
            marker = builder.AddNamedSystem("epm_command_marker", CommandMarker(
                meshcat, scenario.epm.magnet, scenario.visual_period))
            source = (builder.GetSubsystemByName("teleop.mapping").GetOutputPort("epm_command")
                      if scenario.teleop is not None
                      else builder.GetSubsystemByName("epm_path").get_output_port())
            builder.Connect(source, marker.GetInputPort("epm_command"))

    diagram = builder.Build()
    diagram.set_name("capsule_station")
    return diagram
