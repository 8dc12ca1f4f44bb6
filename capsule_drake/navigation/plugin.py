"""A user's navigator as the EPM's driver (`epm.driver: !Plugin {factory: ...}`).

Interface. `factory(context: NavigatorContext) -> LeafSystem`. The system needs an output
port `epm_command` ([p_WE (3), m_hat_W (3)]: the EPM's centre and unit moment direction,
world frame), and may have any of these input ports, connected by name:
`capsule_state` (13: quaternion wxyz, position, angular and linear velocity; ground truth),
`epm_pose` (6), `rgb_image` and `frame_info` (the camera's), `lumen_ray`, `lumen_visible`,
`lumen_confidence` (the lumen tracker's: switch it on with `capsule: {lumen_tracker: {}}`),
and `lumen_truth_ray`, `lumen_truth_visible` (the lumen truth, as a ray in the camera
frame; needs the camera). A user's lumen detector plugs into the tracker instead:
`capsule: {lumen_tracker: {detector: "package.module:function"}}`. A port of the wrong size
or kind is refused as the station is built (one line naming it); `rgb_image` is the
navigator's own copy of the camera's frame (what it writes into it, nothing else sees).

The command passes the EPM's guard on its way to the carrier, as every driver's does
(epm/guard.py): raised to the clearance floor (`floor_height`), its centre kept within the
workspace around the colon, a command that is not finite replaced by the last safe one; the
station's `epm.guard_counts` counts each. `epm.command` is the navigator's own command.
"""


import dataclasses

import numpy as np
from pydrake.common import pretty_class_name
from pydrake.systems.framework import PortDataType, System
from pydrake.systems.primitives import PassThrough

from capsule_drake.perception.lumen_truth import add_lumen_ray_from_truth
from capsule_drake.plugins import FAILURES, first_line, load_function
from capsule_drake.blocks import block
from capsule_drake.schema import ScenarioError

# The size of the command a navigator's `epm_command` port gives: [p_WE (3), m_hat_W (3)].
COMMAND_SIZE = 6
PLUGIN_INPUTS = {
    "capsule_state": None, "epm_pose": "epm.pose",
    "rgb_image": "capsule.camera.rgb_image", "frame_info": "capsule.camera.frame_info",
    "lumen_ray": "capsule.lumen_tracker.lumen_ray",
    "lumen_visible": "capsule.lumen_tracker.lumen_visible",
    "lumen_confidence": "capsule.lumen_tracker.lumen_confidence",
    "lumen_truth_ray": "capsule.lumen.lumen_pixel",
    "lumen_truth_visible": "capsule.lumen.lumen_pixel",
}


@dataclasses.dataclass
class Plugin:
    """A user's navigator drives the EPM: `factory` names "package.module:function" (the
    interface is in navigation/plugin.py)."""

    factory: str = ""


@dataclasses.dataclass
class NavigatorContext:
    """What a user's navigator factory is given.

    colon_length: the colon's centreline length (m; the goal is its end: the navigator is
    not given the centreline itself). lens: the camera's Lens (None without a camera).
    X_BC: the camera's pose in the capsule body. floor_height: function (x, y, m_hat) ->
    the lowest EPM centre height the clearance allows. start_command: the EPM's pose at the
    start, [p_WE, m_hat_W].
    """

    colon_length: float
    lens: object
    X_BC: object
    floor_height: object
    start_command: np.ndarray


def load_navigator(name: str, choices: str = "a navigator factory"):
    """The factory of a user's navigator "package.module:function"; ValueError (one line,
    offering `choices`) when it cannot be found."""
    return load_function("navigator", name, choices)


def check_plugin(config: Plugin) -> None:
    """Raises ValueError (one line) when the factory cannot be found."""
    load_navigator(config.factory)


@block("epm.driver", Plugin, check=lambda config, _: check_plugin(config),
       where="epm.driver (Plugin): factory: ")
def add_plugin(builder, parts, config: Plugin):
    """`navigator`, the user's system, connected by its input ports' names; its command
    goes to the EPM's carrier and is exported as epm.command."""
    name = config.factory
    context = NavigatorContext(parts.colon.centerline.length,
                               parts.shared("capsule.camera.lens", None),
                               parts.capsule.X_BC, parts.epm.guard.lowest_centre_height,
                               np.array(parts.epm.start_command))
    try:
        system = load_navigator(name)(context)
    except FAILURES as e:  # the user's code (or its sys.exit()): one line, naming it
        raise ScenarioError(f"scenario: epm.driver: navigator {name!r} failed to build its "
                            f"system ({first_line(e)})") from None
    if not isinstance(system, System):
        raise ScenarioError(f"scenario: epm.driver: navigator {name!r} returned a "
                            f"{type(system).__name__}, not a Drake LeafSystem")
    if not system.HasOutputPort("epm_command"):
        raise ScenarioError(f"scenario: epm.driver: navigator {name!r} has no output port "
                            "'epm_command'")
    command = system.GetOutputPort("epm_command")
    if not (command.get_data_type() == PortDataType.kVectorValued
            and command.size() == COMMAND_SIZE):
        raise ScenarioError(f"scenario: epm.driver: navigator {name!r}: output port "
                            f"'epm_command' is {_kind(command)}; the station needs a vector of "
                            f"size {COMMAND_SIZE}")
    system = builder.AddNamedSystem("navigator", system)
    truth = None
    for i in range(system.num_input_ports()):
        port = system.get_input_port(i)
        input_name = port.get_name()
        if input_name not in PLUGIN_INPUTS:
            raise ScenarioError(
                f"scenario: epm.driver: navigator {name!r}: input port {input_name!r} is not "
                f"one of {', '.join(PLUGIN_INPUTS)}")
        source = PLUGIN_INPUTS[input_name]
        if source is not None and not parts.has(source):
            raise ScenarioError(
                f"scenario: epm.driver: navigator {name!r}: input {input_name!r} needs "
                f"{source!r}, which this scenario does not have (switch on the camera or "
                "the lumen tracker)")
        if input_name.startswith("lumen_truth_"):
            if truth is None:
                truth = add_lumen_ray_from_truth(builder, parts, "lumen_truth_ray")
            given = truth.GetOutputPort(input_name.removeprefix("lumen_truth_"))
        elif source is None:
            given = parts.capsule_state
        else:
            given = parts.output(source)
        _connect_input(builder, name, given, port)
    builder.Connect(command, parts.epm.command_input(builder, parts))
    parts.export(command, "epm.command")
    return system


def _connect_input(builder, name: str, given, port) -> None:
    """Connects the station's output port `given` to the navigator's input `port`, or raises
    ScenarioError (one line) when the port does not take what `given` gives. A value that is
    not a vector (the camera's image) reaches the navigator through a copy of its own: what
    the navigator does to it, no other system sees."""
    vector = PortDataType.kVectorValued
    fits = (given.get_data_type() == port.get_data_type()
            and (given.size() == port.size() if given.get_data_type() == vector
                 else type(given.Allocate()) is type(port.Allocate())))
    if not fits:
        raise ScenarioError(f"scenario: epm.driver: navigator {name!r}: input port "
                            f"{port.get_name()!r} is {_kind(port)}; the station gives it "
                            f"{_kind(given)}")
    if given.get_data_type() != vector:
        copy = builder.AddNamedSystem(f"navigator.{port.get_name()}",
                                      PassThrough(given.Allocate()))
        builder.Connect(given, copy.get_input_port())
        given = copy.get_output_port()
    builder.Connect(given, port)


def _kind(port) -> str:
    """What a port carries, as a user would say it: "a vector of size 6", "an abstract
    value (Image[PixelType.kRgba8U])"."""
    if port.get_data_type() == PortDataType.kVectorValued:
        return f"a vector of size {port.size()}"
    return f"an abstract value ({pretty_class_name(type(port.Allocate().get_value()))})"
