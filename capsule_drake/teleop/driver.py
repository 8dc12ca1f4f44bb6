"""Haptic teleoperation as the EPM's driver (`epm.driver: !Teleop {...}`).

    operator (simulated hand | browser | UDP device) --> HapticMaster / device
        --> [TeleopChannel: delay, jitter, loss, passivity] --> TeleopMapping --> EPM command
    pseudo_force.F_D + the capsule's contact (ContactMonitor) --> ForceFeedback
        --> [TeleopChannel] --> the device's motors, saturated to its limit
"""


import copy
import dataclasses

from pydrake.systems.primitives import Demultiplexer

from capsule_drake.perception.lumen_range import LumenRange
from capsule_drake.perception.lumen_truth import add_lumen_ray_from_truth
from capsule_drake.physics.contact_monitor import ContactMonitor
from capsule_drake.blocks import block, checked, need
from capsule_drake.schema import MAX_RATE, MIN_PERIOD, need_range
from capsule_drake.teleop.browser import BrowserOperator
from capsule_drake.teleop.channel import (TeleopChannel, TeleopChannelConfig,
                                          check_channel_config, check_passivity_config)
from capsule_drake.teleop.force_feedback import ForceFeedback
from capsule_drake.teleop.haptic_master import (STYLUS_SIZE, HapticDeviceConfig, HapticMaster,
                                                check_haptic_device_config)
from capsule_drake.teleop.mapping import MappingConfig, TeleopMapping, check_mapping_config
from capsule_drake.teleop.operator import (ForwardSpeed, OperatorConfig,
                                           SimulatedOperator, WayForward, check_operator_config)
from capsule_drake.teleop.udp import (UdpBridgeConfig, UdpHapticDevice, check_udp_address,
                                      check_udp_bridge_config)

OPERATORS = ("simulated", "browser", "udp")
LUMEN_SOURCES = ("tracker", "truth")


@dataclasses.dataclass
class Teleop:
    """Haptic teleoperation drives the EPM: the operator moves a stylus, the EPM follows the
    mapping, and the operator feels the pseudo-force (the scenario's `pseudo_force`; null:
    no guidance) plus the capsule's contact with the wall."""

    # Who holds the stylus: "simulated" (a model of a hand), "browser" (keyboard, gamepad
    # and sliders in Meshcat, paced in real time) or "udp" (a real device over the
    # network bridge).
    operator: str = "simulated"
    # The haptic device (Geomagic Touch figures).
    device: HapticDeviceConfig = dataclasses.field(default_factory=HapticDeviceConfig)
    # Stylus to EPM mapping (position or rate mode, scales, clutch).
    mapping: MappingConfig = dataclasses.field(default_factory=MappingConfig)
    # The simulated operator's hand and intent.
    simulated: OperatorConfig = dataclasses.field(default_factory=OperatorConfig)
    # What the simulated operator sees of the lumen: the lumen tracker's detection (needs
    # capsule.lumen_tracker) or the truth (needs capsule.camera).
    lumen_source: str = "tracker"
    # Delay, jitter and loss both ways, and the passivity scheme at the device. The scheme
    # (time-domain passivity) acts only when the link has delay, jitter or loss: with an
    # ideal link there is nothing to stabilise, and strict passivity would also mute the
    # guidance, which puts energy into the hand by design.
    channel: TeleopChannelConfig = dataclasses.field(default_factory=TeleopChannelConfig)
    # Device newtons per newton of the capsule's contact force with the wall.
    contact_gain: float = 1.0
    # The network bridge for a real device (operator "udp"): loopback by default.
    udp: UdpBridgeConfig = dataclasses.field(default_factory=UdpBridgeConfig)


def check_teleop(teleop: Teleop) -> None:
    """Raises ValueError naming the first impossible field (on its own; what it needs of
    the rest of the scenario is checked with the scenario). With the udp operator, the
    bridge's host must resolve and its address bind (`check_udp_address`)."""
    if teleop.operator not in OPERATORS:
        raise ValueError(f"operator must be one of {', '.join(OPERATORS)}, "
                         f"got {teleop.operator!r}")
    if teleop.lumen_source not in LUMEN_SOURCES:
        raise ValueError(f"lumen_source must be one of {', '.join(LUMEN_SOURCES)}, got "
                         f"{teleop.lumen_source!r}")
    need_range(teleop.contact_gain, "contact_gain", "[0, 100]", "",
               "device newtons per newton of contact")
    check_haptic_device_config(teleop.device)
    device = teleop.device
    need_range(device.workspace_half_extents, "device.workspace_half_extents", "(0, 0.5]", "m",
               "a desktop haptic device reaches ~16 x 12 x 7 cm")
    need_range(device.servo_rate, "device.servo_rate", f"[1, {MAX_RATE:g}]", "Hz",
               "haptic servos run at ~1 kHz")
    need_range(device.stylus_mass, "device.stylus_mass", "[0.001, 10]", "kg")
    check_mapping_config(teleop.mapping)
    mapping = teleop.mapping
    need_range(mapping.period, "mapping.period", f">= {MIN_PERIOD:g}", "s")
    need_range(mapping.max_pitch_deg, "mapping.max_pitch_deg", "[0, 90]", "deg")
    need_range(mapping.max_lead_deg, "mapping.max_lead_deg", "[0, 180]", "deg")
    check_operator_config(teleop.simulated)
    hand = teleop.simulated
    need_range(hand.period, "simulated.period", f"[{MIN_PERIOD:g}, 1]", "s")
    need_range(hand.reaction_time, "simulated.reaction_time", "[0, 2]", "s",
               "a hand reacts to what it sees in ~0.2-0.3 s; its delay line holds one "
               "sample per period of it")
    if round(hand.reaction_time / hand.period) < 2:
        # SimulatedOperator's delay line reads its last two samples.
        raise ValueError(f"simulated.reaction_time {hand.reaction_time} s must be at least "
                         f"1.5 x simulated.period ({1.5 * hand.period:g} s): the operator's "
                         "delay line holds at least two samples")
    for name in ("forward", "backward"):
        check_channel_config(getattr(teleop.channel, name), f"channel.{name}.")
    check_passivity_config(teleop.channel.passivity, "channel.passivity.")
    check_udp_bridge_config(teleop.udp)
    if teleop.operator == "udp":
        check_udp_address(teleop.udp)


def check_teleop_driver(teleop: Teleop, scenario) -> None:
    checked("epm.driver (Teleop): ", check_teleop, teleop)
    if teleop.operator == "simulated":
        need(scenario.capsule.camera is not None,
             "epm.driver (Teleop) operator simulated needs capsule.camera (it watches "
             "the image)")
        need(teleop.lumen_source == "truth" or scenario.capsule.lumen_tracker is not None,
             "epm.driver (Teleop) lumen_source tracker needs capsule.lumen_tracker")


@block("epm.driver", Teleop, check=check_teleop_driver)
def add_teleop(builder, parts, teleop: Teleop):
    """The haptic loop: operator -> device -> channel -> mapping -> EPM command (to the
    EPM's carrier, exported as epm.command), and force feedback (pseudo-force + the
    capsule's contact, saturated) -> channel -> passivity -> device; the channel only when
    the link is not ideal (teleop.channel_energy then). Exports teleop.<signal>."""
    plant = parts.plant
    capsule = parts.capsule_body
    capsule_state = parts.capsule_state
    X_BC = parts.capsule.X_BC
    has_tracker = parts.has("capsule.lumen_tracker.lumen_ray")
    mapping = builder.AddNamedSystem("teleop.mapping", TeleopMapping(
        teleop.mapping, X_BC, parts.capsule.X_BM.translation(),
        parts.epm.guard.lowest_centre_height, parts.epm.start_command,
        parts.X_WB0.rotation().col(2)))
    builder.Connect(capsule_state, mapping.GetInputPort("capsule_state"))
    def tracker(name):
        return parts.output(f"capsule.lumen_tracker.{name}")

    if teleop.mapping.assist and has_tracker:
        builder.Connect(tracker("lumen_ray"), mapping.GetInputPort("lumen_ray"))
        builder.Connect(tracker("lumen_visible"), mapping.GetInputPort("lumen_visible"))
        camera = parts.shared("capsule.camera.config")
        if camera.render_depth:
            free = builder.AddNamedSystem("teleop.lumen_range", LumenRange(camera.far))
            builder.Connect(parts.output("capsule.camera.depth_image"),
                            free.GetInputPort("depth_image"))
            builder.Connect(tracker("lumen_pixel"), free.GetInputPort("lumen_pixel"))
            builder.Connect(tracker("lumen_visible"), free.GetInputPort("lumen_visible"))
            builder.Connect(free.GetOutputPort("range"), mapping.GetInputPort("lumen_range"))
            parts.export(free.GetOutputPort("range"), "teleop.lumen_range")

    # What the operator feels: the pseudo-force (if any) and the capsule's contact.
    wall = parts.has("contact.wall")
    monitor = builder.AddNamedSystem("teleop.contact", ContactMonitor(
        plant.GetCollisionGeometriesForBody(capsule), wall=wall))
    builder.Connect(plant.get_contact_results_output_port(),
                    monitor.GetInputPort("contact_results"))
    if wall:
        builder.Connect(parts.output("contact.wall"), monitor.GetInputPort("wall_contact"))
    rpy = parts.shared("pseudo_force.device_from_camera_rpy_deg", (180.0, 0.0, 0.0))
    feedback = builder.AddNamedSystem("teleop.feedback", ForceFeedback(
        X_BC, teleop.contact_gain, teleop.device.force_limit, rpy))
    builder.Connect(monitor.GetOutputPort("capsule_force_W"),
                    feedback.GetInputPort("capsule_force_W"))
    builder.Connect(capsule_state, feedback.GetInputPort("capsule_state"))
    if parts.has("pseudo_force.F_D"):
        builder.Connect(parts.output("pseudo_force.F_D"), feedback.GetInputPort("pseudo_force_D"))

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
        builder.Connect(capsule_state, speed.GetInputPort("capsule_state"))
        builder.Connect(speed.GetOutputPort("forward_speed"),
                        hand.GetInputPort("forward_speed"))
        way = builder.AddNamedSystem("teleop.way_forward", WayForward(
            X_BC.rotation().matrix(), parts.X_WB0.translation()))
        builder.Connect(capsule_state, way.GetInputPort("capsule_state"))
        builder.Connect(way.GetOutputPort("way_C"), hand.GetInputPort("way_forward"))
        if teleop.lumen_source == "tracker":
            builder.Connect(tracker("lumen_visible"), hand.GetInputPort("lumen_visible"))
            builder.Connect(tracker("lumen_ray"), hand.GetInputPort("lumen_ray"))
        else:
            truth = add_lumen_ray_from_truth(builder, parts, "teleop.lumen_seen")
            builder.Connect(truth.GetOutputPort("visible"), hand.GetInputPort("lumen_visible"))
            builder.Connect(truth.GetOutputPort("ray"), hand.GetInputPort("lumen_ray"))
        parts.export(hand.GetOutputPort("intent"), "teleop.intent")
        builder.Connect(force_to_device, device.GetInputPort("feedback_force"))
        if channel is not None:
            builder.Connect(device.GetOutputPort("stylus_velocity"),
                            channel.GetInputPort("stylus_velocity"))
        parts.export(device.GetOutputPort("motor_force"), "teleop.motor_force")
    elif teleop.operator == "udp":
        device = builder.AddNamedSystem("teleop.device", UdpHapticDevice(teleop.udp))
        builder.Connect(force_to_device, device.GetInputPort("force_D"))
        builder.Connect(device.GetOutputPort("link_ok"), mapping.GetInputPort("link_ok"))
        parts.export(device.GetOutputPort("link_ok"), "teleop.link_ok")
        parts.export(device.GetOutputPort("stats"), "teleop.udp_stats")
        parts.share("teleop.device.address", device.address)
    else:  # browser
        device = builder.AddNamedSystem("teleop.device", BrowserOperator(
            parts.meshcat, teleop.device, parts.shared("capsule.camera.config")))
        builder.Connect(force_to_device, device.GetInputPort("feedback_force"))
        for name in ("rgb_image", "frame_info"):
            builder.Connect(parts.output(f"capsule.camera.{name}"), device.GetInputPort(name))
        if has_tracker:
            for name in ("lumen_pixel", "lumen_visible"):
                builder.Connect(tracker(name), device.GetInputPort(name))
    if channel is not None:
        split = builder.AddNamedSystem("teleop.stylus_position",
                                       Demultiplexer([3, STYLUS_SIZE - 3]))
        builder.Connect(device.GetOutputPort("stylus"), split.get_input_port())
        builder.Connect(device.GetOutputPort("stylus"), channel.GetInputPort("stylus_in"))
        builder.Connect(split.get_output_port(0), channel.GetInputPort("stylus_position"))
        parts.export(channel.GetOutputPort("energy"), "teleop.channel_energy")
    else:
        builder.Connect(device.GetOutputPort("stylus"), mapping.GetInputPort("stylus"))
    parts.export(device.GetOutputPort("stylus"), "teleop.stylus")
    parts.export(feedback.GetOutputPort("F_D"), "teleop.feedback_D")
    parts.export(monitor.GetOutputPort("capsule_force_W"), "teleop.contact_force_W")
    parts.export(mapping.GetOutputPort("heading"), "teleop.heading")
    command = mapping.GetOutputPort("epm_command")
    builder.Connect(command, parts.epm.command_input(builder, parts))
    parts.export(command, "epm.command")
    return mapping
