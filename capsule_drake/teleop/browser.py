"""The browser as the haptic master: keyboard, gamepad and sliders in Meshcat move a virtual
stylus; the capsule's camera view, the detected lumen and the force the operator would feel
are drawn in the same page. Meant to run paced in real time (`capsule-sim teleop --operator
browser`).

Controls (Meshcat buttons, each with a key): W / S push the stylus away / pull it back
(forward / backward), A / D left / right (yaw), R / F up / down (pitch), Space toggles the
clutch (held: the stylus moves without moving the EPM, for indexing), C re-centres the
stylus. Sliders set the stylus position directly. A gamepad, if the browser sees one, drives
the stylus's velocity: left stick yaw and pitch, right stick forward and back, button A
toggles the clutch. Meshcat buttons count clicks (no key-held state): each press nudges
the stylus by `key_step`.
"""

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.geometry import Rgba
from pydrake.perception import BaseField, Fields, PointCloud
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.systems.framework import BasicVector, EventStatus, LeafSystem
from pydrake.systems.sensors import ImageRgba8U

from capsule_drake.teleop.haptic_master import STYLUS_SIZE

# button name, key code, stylus direction (D frame) or an action
KEYS = (
    ("Forward (W)", "KeyW", (0.0, 0.0, -1.0)),
    ("Back (S)", "KeyS", (0.0, 0.0, 1.0)),
    ("Yaw left (A)", "KeyA", (-1.0, 0.0, 0.0)),
    ("Yaw right (D)", "KeyD", (1.0, 0.0, 0.0)),
    ("Pitch up (R)", "KeyR", (0.0, 1.0, 0.0)),
    ("Pitch down (F)", "KeyF", (0.0, -1.0, 0.0)),
)
CLUTCH = ("Clutch (Space)", "Space")
CENTRE = ("Re-centre (C)", "KeyC")
SLIDERS = ("stylus x (m)", "stylus y (m)", "stylus z (m)")
# The camera-view panel: its width (m), centre, and the viewpoint it faces (Meshcat's
# default view of the station, from the patient's right, above the table).
PANEL_WIDTH = 0.25
PANEL_CENTRE = (-0.12, 0.32, 0.42)
PANEL_FACES = (-0.55, -0.35, 0.65)


def panel_pose(centre=PANEL_CENTRE, faces=PANEL_FACES) -> RigidTransform:
    """Pose of a panel (drawn in its x-z plane) at `centre`, facing the point `faces`,
    upright."""
    centre = np.asarray(centre, dtype=float)
    y = centre - np.asarray(faces, dtype=float)
    y /= np.linalg.norm(y)
    z = np.array([0.0, 0.0, 1.0]) - y[2] * y
    z /= np.linalg.norm(z)
    return RigidTransform(RotationMatrix(np.column_stack([np.cross(y, z), y, z])), centre)


def key_motion(clicks: dict, step: float) -> np.ndarray:
    """Stylus displacement (m, D) for new clicks per button name."""
    motion = np.zeros(3)
    for name, _, direction in KEYS:
        motion += clicks.get(name, 0) * step * np.asarray(direction)
    return motion


def gamepad_velocity(axes, speed: float, dead_band: float = 0.15) -> np.ndarray:
    """Stylus velocity (m/s, D) from gamepad axes [lx, ly, rx, ry] (browser convention:
    +y down): left stick yaw / pitch, right stick forward / back."""
    a = np.zeros(4)
    a[:min(4, len(axes))] = np.asarray(axes, dtype=float)[:4]
    a = np.where(np.abs(a) > dead_band, a, 0.0)
    return speed * np.array([a[0], -a[1], a[3]])


class BrowserOperator(LeafSystem):
    """A virtual stylus driven from the Meshcat page (module docstring).

    .. pydrake_system::

        name: BrowserOperator
        input_ports:
        - feedback_force
        - rgb_image
        - frame_info
        - lumen_pixel (optional)
        - lumen_visible (optional)
        output_ports:
        - stylus
        - stylus_velocity

    Args:
        meshcat: the Meshcat instance (its page is the operator's console).
        device: HapticDeviceConfig (the workspace the virtual stylus moves in).
        camera: the capsule's CameraConfig (image size), or None.
        period: how often the page is read (s).
        key_step: stylus travel per key press (m).
        gamepad_speed: stylus speed at full stick (m/s).
    """

    def __init__(self, meshcat, device, camera=None, period: float = 0.02,
                 key_step: float = 0.004, gamepad_speed: float = 0.03):
        super().__init__()
        if meshcat is None:
            raise ValueError("teleop operator browser needs Meshcat (capsule-sim teleop "
                             "starts one)")
        self._meshcat = meshcat
        self._half = np.asarray(device.workspace_half_extents, dtype=float)
        self._period = period
        self._step = key_step
        self._speed = gamepad_speed
        width = camera.lens.width if camera is not None else 256
        height = camera.lens.height if camera is not None else 256
        for name, key, _ in KEYS:
            meshcat.AddButton(name, key)
        meshcat.AddButton(*CLUTCH)
        meshcat.AddButton(*CENTRE)
        for name, half in zip(SLIDERS, self._half):
            meshcat.AddSlider(name, -half, half, 0.001, 0.0)
        self._clicks = {name: 0 for name, _, _ in KEYS}
        self._clicks[CLUTCH[0]] = 0
        self._clicks[CENTRE[0]] = 0
        self._sliders = np.zeros(3)
        self._panel = panel_pose()
        self._gamepad_button = False
        self._feedback = self.DeclareVectorInputPort("feedback_force", 3)
        self._rgb = self.DeclareAbstractInputPort(
            "rgb_image", AbstractValue.Make(ImageRgba8U(width, height)))
        self._frame_info = self.DeclareVectorInputPort("frame_info", 4)
        self._lumen_pixel = self.DeclareVectorInputPort("lumen_pixel", 2)
        self._lumen_visible = self.DeclareVectorInputPort("lumen_visible", 1)
        # [p (3), v (3), clutch, frames shown]
        self._state = self.DeclareDiscreteState(BasicVector(np.r_[np.zeros(7), -1.0]))
        self.DeclareVectorOutputPort(
            "stylus", STYLUS_SIZE,
            lambda c, out: out.SetFromVector(np.concatenate([
                c.get_discrete_state(self._state).value()[:3], [1.0, 0.0, 0.0, 0.0],
                [c.get_discrete_state(self._state).value()[6], 0.0]])),
            {self.xd_ticket()})
        self.DeclareVectorOutputPort(
            "stylus_velocity", 3,
            lambda c, out: out.SetFromVector(c.get_discrete_state(self._state).value()[3:6]),
            {self.xd_ticket()})
        self.DeclarePeriodicDiscreteUpdateEvent(period, 0.0, self._update)

    def _new_clicks(self, name) -> int:
        count = self._meshcat.GetButtonClicks(name)
        new, self._clicks[name] = count - self._clicks[name], count
        return new

    def _update(self, context, discrete_state):
        x = context.get_discrete_state(self._state).value().copy()
        p = x[:3].copy()
        clicks = {name: self._new_clicks(name) for name, _, _ in KEYS}
        p += key_motion(clicks, self._step)
        if self._new_clicks(CLUTCH[0]) % 2:
            x[6] = 1.0 - x[6]
        if self._new_clicks(CENTRE[0]):
            p[:] = 0.0
        sliders = np.array([self._meshcat.GetSliderValue(name) for name in SLIDERS])
        if np.any(np.abs(sliders - self._sliders) > 1e-9):
            p = sliders.copy()
        gamepad = self._meshcat.GetGamepad()
        if gamepad.index is not None:
            p += self._period * gamepad_velocity(gamepad.axes, self._speed)
            pressed = bool(gamepad.button_values) and gamepad.button_values[0] > 0.5
            if pressed and not self._gamepad_button:
                x[6] = 1.0 - x[6]
            self._gamepad_button = pressed
        p = np.clip(p, -self._half, self._half)
        for name, value in zip(SLIDERS, p):
            self._meshcat.SetSliderValue(name, float(value))
        self._sliders = p.copy()
        x[3:6] = (p - x[:3]) / self._period
        x[:3] = p
        self._draw(context, x)
        discrete_state.set_value(self._state, x)
        return EventStatus.Succeeded()

    def _draw(self, context, x):
        """The camera view as a coloured point cloud on a panel beside the patient, turned to
        face the default viewpoint; the detected lumen as a green cross on it, and the
        force the operator feels as an orange arrow from its centre (2 cm per newton, D's x
        right and y up on the panel, z toward the viewer)."""
        m = self._meshcat
        X_WV = self._panel
        info = self._frame_info.Eval(context)
        if info[1] != x[7]:
            x[7] = info[1]
            rgb = self._rgb.Eval(context).data[::2, ::2, :3]
            h, w = rgb.shape[:2]
            v, u = np.mgrid[0:h, 0:w]
            size = PANEL_WIDTH / max(h, w)
            xyz = np.stack([(u - w / 2) * size, np.zeros_like(u, dtype=float),
                            (h / 2 - v) * size]).reshape(3, -1).astype(np.float32)
            cloud = PointCloud(h * w, Fields(BaseField.kXYZs | BaseField.kRGBs))
            cloud.mutable_xyzs()[:] = xyz
            cloud.mutable_rgbs()[:] = rgb.reshape(-1, 3).T
            m.SetObject("/teleop/camera_view", cloud, point_size=size * 1.5)
            m.SetTransform("/teleop/camera_view", X_WV)
            if self._lumen_visible.HasValue(context) and \
                    self._lumen_visible.Eval(context)[0] > 0.5:
                pixel = np.asarray(self._lumen_pixel.Eval(context)) / 2.0
                c = np.array([(pixel[0] - w / 2) * size, -0.003, (h / 2 - pixel[1]) * size])
                arms = [c + [-0.01, 0, 0], c + [0.01, 0, 0], c, c + [0, 0, -0.01],
                        c + [0, 0, 0.01]]
                m.SetLine("/teleop/lumen", X_WV.multiply(np.array(arms).T), 4.0,
                          Rgba(0.1, 1.0, 0.1, 1.0))
            else:
                m.Delete("/teleop/lumen")
        force = (np.asarray(self._feedback.Eval(context), dtype=float)
                 if self._feedback.HasValue(context) else np.zeros(3))
        if np.all(np.isfinite(force)):
            base = np.array([0.0, -0.006, 0.0])  # just in front of the panel
            tip = base + 0.02 * np.array([force[0], -force[2], force[1]])
            m.SetLine("/teleop/force", X_WV.multiply(np.column_stack([base, tip])),
                      8.0, Rgba(1.0, 0.5, 0.0, 1.0))
