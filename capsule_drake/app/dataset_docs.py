"""The text files of a recorded dataset: README.md (for a person), camera.yaml and
sensors.yaml (for a program). Pure text from the recording's settings; app/record.py gathers
them, app/dataset.py writes the rest of the folder.

Every number a user needs to read the folder (intrinsics, mountings, rates, depth encoding)
is written into these files, so that the folder loads with numpy and OpenCV alone; the
README's example code is run by the tests exactly as written.
"""

import dataclasses
import datetime
import math

import yaml
from pydrake.math import RigidTransform

from capsule_drake.app.dataset import DEPTH_BEYOND, DEPTH_NONE, DEPTH_SCALE, quaternion_xyzw
from capsule_drake.perception.lumen_truth import FAR_FRACTION, RIM_ANGLE_DEG


@dataclasses.dataclass
class DatasetDescription:
    """What the README and the YAML files say of one recording.

    lens: the camera's `perception.Lens`. camera: its `CameraConfig`. X_BC: the camera's pose
    in the capsule body. streams: the `dataset.Stream`s written. imu, magnetometer, ahrs:
    their configs, or None when the stream is absent (with X_BS their mounting). The rest
    names the run: scenario, colon seed, noise seed, planned duration (s).
    """

    lens: object
    camera: object
    X_BC: RigidTransform
    streams: list
    imu: object = None
    magnetometer: object = None
    ahrs: object = None
    scenario_name: str = ""
    colon_seed: int = 0
    random_seed: int = 0
    duration: float = 0.0
    depth_full_scale: float = 0.2
    # How much later than its tick a sensor's sample measures the state (s): the plant's
    # step when it steps before the sensors (app/dataset.py, state_time); 0 otherwise.
    sensor_lag: float = 0.0
    # Polyps in the colon (their files are written when there is any).
    polyps: int = 0


def _pose(X: RigidTransform) -> dict:
    p = X.translation()
    return {"position_m": [round(float(v), 9) for v in p],
            "quaternion_xyzw": [round(float(v), 9) for v in quaternion_xyzw(X.rotation())]}


def _distortion(lens) -> tuple[str, list[float]]:
    """(name of the coefficients, values) of the lens model (OpenCV's order)."""
    if lens.model == "pinhole_radtan":
        return "k1 k2 p1 p2 k3", [float(v) for v in lens.config.radtan_coefficients]
    if lens.model == "kannala_brandt":
        return "k1 k2 k3 k4", [float(v) for v in lens.config.kb_coefficients]
    return "k1 k2 k3 k4", [0.0, 0.0, 0.0, 0.0]  # equidistant: Kannala-Brandt with zeros


def camera_yaml(d: DatasetDescription) -> str:
    """camera.yaml: the lens, its intrinsics (only the fields its model has), its mounting in
    the capsule, the frame rate and the depth encoding."""
    lens, camera = d.lens, d.camera
    names, values = _distortion(lens)
    text = {
        "model": lens.model,
        "opencv_model": "pinhole" if lens.model == "pinhole_radtan" else "fisheye",
        "width": lens.width,
        "height": lens.height,
        ("fov_deg" if lens.is_fisheye else "fov_deg_across_width"): float(lens.fov_deg),
        "fx": float(lens.fx), "fy": float(lens.fy), "cx": float(lens.cx), "cy": float(lens.cy),
        "K": [[float(lens.fx), 0.0, float(lens.cx)], [0.0, float(lens.fy), float(lens.cy)],
              [0.0, 0.0, 1.0]],
        "D": values,
        "D_names": names,
        "pixel_convention": "OpenCV: (u, v) = (column, row), the top-left pixel's centre is "
                            "(0, 0)",
        "mask": "mask.png: 255 where the lens sees (inside its image circle), 0 outside",
        "T_body_camera": _pose(d.X_BC),
        "frame_rate": ({"mode": "fixed", "fps": float(camera.fps)} if camera.fps_mode == "fixed"
                       else {"mode": "adaptive", "fps_min": float(camera.fps_min),
                             "fps_max": float(camera.fps_max)}),
        "latency_s": float(camera.latency),
        "depth": {
            "files": "Frames/Depth_XXXX.png (16-bit)",
            "quantity": "range along each pixel's ray from the camera centre (m), not z-depth",
            "metres": f"value / {DEPTH_SCALE:g} * {d.depth_full_scale:g}",
            "full_scale_m": float(d.depth_full_scale),
            "no_measurement_value": DEPTH_NONE,
            "beyond_full_scale_value": DEPTH_BEYOND,
            "near_clip_m": float(camera.near),
        },
    }
    return yaml.safe_dump(text, sort_keys=False, width=100, default_flow_style=None)


def sensors_yaml(d: DatasetDescription) -> str:
    """sensors.yaml: each sensor's mounting in the capsule body, rate, range and noise (SI)."""
    text = {}
    if d.imu is not None:
        c = d.imu
        text["imu"] = {
            "file": "imu.csv", "sample_rate_hz": float(c.sample_rate),
            "T_body_sensor": _pose(c.X_BS()),
            "accel_range_m_s2": float(c.accel_range), "gyro_range_rad_s": float(c.gyro_range),
            "accel_noise_density_m_s2_per_sqrt_hz": float(c.accel_noise_density),
            "gyro_noise_density_rad_s_per_sqrt_hz": float(c.gyro_noise_density),
            "accel_bias_random_walk_m_s2_per_sqrt_s": float(c.accel_bias_random_walk),
            "gyro_bias_random_walk_rad_s_per_sqrt_s": float(c.gyro_bias_random_walk),
            "accel_initial_bias_sigma_m_s2": float(c.accel_initial_bias_sigma),
            "gyro_initial_bias_sigma_rad_s": float(c.gyro_initial_bias_sigma),
            "resolution_bits": int(c.resolution_bits),
        }
    if d.ahrs is not None:
        text["ahrs"] = {"file": "ahrs.csv", "filter": "Mahony complementary filter with "
                        "gyro-bias estimation (no magnetic heading)",
                        "kp_rad_s": float(d.ahrs.kp), "ki_rad_s2": float(d.ahrs.ki)}
    if d.magnetometer is not None:
        c = d.magnetometer
        text["magnetometer"] = {
            "file": "magnetometer.csv", "sample_rate_hz": float(c.sample_rate),
            "T_body_sensor": _pose(c.X_BS()), "range_T": float(c.range),
            "noise_density_T_per_sqrt_hz": float(c.noise_density),
            "initial_bias_sigma_T": float(c.initial_bias_sigma),
            "resolution_bits": int(c.resolution_bits),
        }
    return yaml.safe_dump(text, sort_keys=False, width=100, default_flow_style=None)


def _fmt(values) -> str:
    """Numbers as Python reads them back exactly."""
    return ", ".join(repr(float(v)) for v in values)


def _load_example(d: DatasetDescription) -> str:
    """The README's example: numpy and OpenCV only, the numbers of this recording."""
    lens = d.lens
    names, values = _distortion(lens)
    scale = d.depth_full_scale
    lines = [
        "import cv2",
        "import numpy as np",
        "",
        'root = "."  # this folder',
        "",
        "",
        "def rotation_matrix(q):",
        '    """3 x 3 rotation matrix of a quaternion in x, y, z, w order."""',
        "    x, y, z, w = np.asarray(q, dtype=float) / np.linalg.norm(q)",
        "    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],",
        "                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],",
        "                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])",
        "",
        "",
        "# Camera poses, one row per frame (camera-to-world: p_W = R_WC @ p_C + p_WC).",
        'frames = np.genfromtxt(f"{root}/frames.csv", delimiter=",", names=True)',
        'p_WC = np.loadtxt(f"{root}/SavedPosition.txt", ndmin=2)            # (N, 3) m',
        'q_WC = np.loadtxt(f"{root}/SavedRotationQuaternion.txt", ndmin=2)  # (N, 4) x, y, z, w',
        "k = 0  # a frame",
        "R_WC = rotation_matrix(q_WC[k])",
        "",
        "# Colour, depth, and where the lens sees.",
        'rgb = cv2.cvtColor(cv2.imread(f"{root}/Frames/FrameBuffer_{k:04d}.png"), '
        "cv2.COLOR_BGR2RGB)",
        'mask = cv2.imread(f"{root}/mask.png", cv2.IMREAD_GRAYSCALE) == 255',
        'raw = cv2.imread(f"{root}/Frames/Depth_{k:04d}.png", cv2.IMREAD_UNCHANGED)  # uint16',
        f"depth = raw * ({scale:g} / {DEPTH_SCALE:g})  # range along each pixel's ray (m)",
        f"depth[raw == {DEPTH_NONE}] = np.nan        # no measurement (outside the mask, or "
        f"nearer than {1000 * d.camera.near:g} mm)",
        f"depth[raw == {DEPTH_BEYOND}] = np.inf    # nothing within {scale:g} m",
        "",
        "# Each measured pixel's ray through the lens, scaled by its range: 3-D points.",
        f"fx, fy, cx, cy = {_fmt([lens.fx, lens.fy, lens.cx, lens.cy])}",
        "v, u = np.nonzero(np.isfinite(depth))",
    ]
    if lens.is_fisheye:
        lines += [
            f"k1, k2, k3, k4 = {_fmt(values)}  # Kannala-Brandt (OpenCV's fisheye)",
            "theta = np.linspace(0.0, np.radians(%s / 2), 20001)  # angle off the optical axis"
            % f"{lens.fov_deg:g}",
            "radius = theta * (1 + k1 * theta**2 + k2 * theta**4 + k3 * theta**6 "
            "+ k4 * theta**8)",
            "xd, yd = (u - cx) / fx, (v - cy) / fy",
            "t = np.interp(np.hypot(xd, yd), radius, theta)  # invert the lens's radius",
            "phi = np.arctan2(yd, xd)",
            "rays_C = np.column_stack([np.sin(t) * np.cos(phi), np.sin(t) * np.sin(phi), "
            "np.cos(t)])",
        ]
    else:
        lines += [
            "K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])",
            f"D = np.array([{_fmt(values)}])  # {names}",
            "pixels = np.column_stack([u, v]).astype(np.float64).reshape(-1, 1, 2)",
            "criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)",
            'if hasattr(cv2, "undistortPointsIter"):  # OpenCV 4',
            "    xy = cv2.undistortPointsIter(pixels, K, D, None, None, criteria)",
            "else:  # OpenCV 5",
            "    xy = cv2.undistortPoints(pixels, K, D, None, None, None, criteria)",
            "xy = xy.reshape(-1, 2)  # x / z, y / z of each pixel's ray",
            "rays_C = np.column_stack([xy, np.ones(len(xy))])",
            "rays_C /= np.linalg.norm(rays_C, axis=1, keepdims=True)",
        ]
    lines += [
        "points_C = rays_C * depth[v, u][:, None]",
        "points_W = points_C @ R_WC.T + p_WC[k]",
        "",
        "# Sensor streams: a CSV per sensor, columns named with their units.",
    ]
    if d.imu is not None:
        lines += [
            'imu = np.genfromtxt(f"{root}/imu.csv", delimiter=",", names=True)',
            'gyro = np.column_stack([imu["gx_rad_s"], imu["gy_rad_s"], imu["gz_rad_s"]])  '
            "# rad/s, in S",
            'accel = np.column_stack([imu["ax_m_s2"], imu["ay_m_s2"], imu["az_m_s2"]])  '
            "# m/s^2, in S",
        ]
    if d.ahrs is not None:
        lines += ['ahrs = np.genfromtxt(f"{root}/ahrs.csv", delimiter=",", names=True)']
    if d.magnetometer is not None:
        lines += ['magnetometer = np.genfromtxt(f"{root}/magnetometer.csv", delimiter=",", '
                  "names=True)  # T"]
    lines += [
        'truth = np.genfromtxt(f"{root}/ground_truth.csv", delimiter=",", names=True)',
        'q_WB = np.column_stack([truth["qx"], truth["qy"], truth["qz"], truth["qw"]])',
        'p_WB = np.column_stack([truth["x_m"], truth["y_m"], truth["z_m"]])',
    ]
    return "\n".join(lines)


def dataset_readme(d: DatasetDescription, frames_note: str = "") -> str:
    """README.md of a recorded dataset: what each file holds, in which units and frames, and
    how to load it."""
    lens, camera = d.lens, d.camera
    scale = d.depth_full_scale
    names = {s.name: s for s in d.streams}
    rate = (f"{camera.fps:g} frames/s" if camera.fps_mode == "fixed"
            else f"{camera.fps_min:g}-{camera.fps_max:g} frames/s, faster while the view moves")
    if lens.is_fisheye:
        lens_text = (f"{lens.model.replace('_', '-')} fisheye, {lens.fov_deg:g} degrees across "
                     f"its image circle, {lens.width} x {lens.height} px")
    else:
        lens_text = (f"pinhole with radial-tangential distortion, {lens.fov_deg:g} degrees "
                     f"across the width, {lens.width} x {lens.height} px")
    out = [
        f"# Capsule dataset: scenario {d.scenario_name}, colon seed {d.colon_seed}",
        "",
        f"Recorded with capsule_drake (`capsule-sim record`) on "
        f"{datetime.date.today().isoformat()}: a capsule driven through a simulated colon "
        f"(procedural colon seed {d.colon_seed}, sensor noise seed {d.random_seed}, "
        f"{d.duration:g} s planned), seen by its camera ({lens_text}, {rate}), with its IMU, "
        "attitude estimate and magnetometer, and the ground truth of each. Everything loads "
        "with numpy and OpenCV: see *Loading it* at the end." + frames_note,
        "",
        "## Conventions",
        "",
        "- **Units**: SI (m, s, rad, m/s^2, T). A column's name ends with its unit "
        "(`_m`, `_s`, `_rad_s`, `_m_s` for m/s, `_m_s2` for m/s^2, `_T`, `_px`); quaternion "
        "components (`qx, qy, qz, qw`) and flags have none.",
        "- **Quaternions**: always in the order **x, y, z, w** (scalar last), in every file, "
        "as SimCol3D's `SavedRotationQuaternion`, ROS messages and SciPy's "
        "`Rotation.from_quat` have them. A quaternion q_AB (Hamilton convention) is the "
        "orientation of frame B in frame A: it turns vectors from B into A, "
        "`v_A = R(q_AB) v_B`. The example below converts one to a matrix.",
        "- **Frames** (one letter each; X_AB is frame B's pose in A):",
        "  - W, world: right-handed, metres; z up (anterior: the patient lies supine on the "
        "table, whose top is z = 0), x to the patient's left, y toward the head.",
        "  - B, the capsule body: origin at its geometric centre, +z along its axis toward the "
        "camera's dome.",
        "  - C, the camera: origin at the lens's centre (the dome's apex), +z along the "
        "optical axis, +x right and +y down in the image (OpenCV's and Drake's convention). "
        "Its pose in B is `T_body_camera` in camera.yaml.",
        "  - S, a sensor's own frame (IMU, magnetometer): its pose in B is `T_body_sensor` in "
        "sensors.yaml.",
        "- **Times**: seconds of simulated time from the start of the run. Each stream starts "
        "at its first real sample (no placeholder rows) and each row is stamped with the time "
        "its sample was taken." + (
            f" The sensors tick every sample period from t = 0 and each sample measures the "
            f"state one simulator step ({1000 * d.sensor_lag:g} ms) after its tick, so their "
            f"rows are stamped {d.sensor_lag:g}, {d.sensor_lag:g} + period, ...; the ground "
            f"truth is on its ticks (interpolate it to compare it with a sensor). A frame is "
            f"stamped with its tick, or one step later where rounding put the tick just past "
            f"the simulator's step (e.g. the frame at 0.3 s shows the state at 0.302 s)."
            if d.sensor_lag > 0 else ""),
        "- **Pixels**: (u, v) = (column, row); the centre of the top-left pixel is (0, 0).",
        "",
        "## Files",
        "",
        "| file | one row / file per | content |",
        "|---|---|---|",
        "| `Frames/FrameBuffer_XXXX.png` | frame | colour image, 8-bit RGB (black outside the "
        "lens's image circle) |",
        "| `Frames/Depth_XXXX.png` | frame | 16-bit range image (below) |",
        "| `mask.png` | (one) | 8-bit: 255 inside the lens's image circle (the pixels that see "
        "anything), 0 outside |",
        "| `frames.csv` | frame | `index, time_s`: the frame's number XXXX and its exposure "
        "time |",
        "| `SavedPosition.txt` | frame | `tx ty tz` (m, space-separated): p_WC, the camera's "
        "centre in W |",
        "| `SavedRotationQuaternion.txt` | frame | `qx qy qz qw` (space-separated): q_WC, the "
        "camera's orientation in W (camera-to-world) |",
        "| `lumen_truth.csv` | frame | where the lumen is in the image (below) |",
    ]
    if "imu" in names:
        out.append(f"| `imu.csv` | IMU sample ({1 / names['imu'].period:g} Hz) | measured and "
                   "true specific force and angular rate, in S (below) |")
    if "ahrs" in names:
        out.append(f"| `ahrs.csv` | AHRS estimate ({1 / names['ahrs'].period:g} Hz) | "
                   "`time_s, qx, qy, qz, qw`: the estimated q_WB |")
    if "magnetometer" in names:
        out.append(f"| `magnetometer.csv` | sample ({1 / names['magnetometer'].period:g} Hz) | "
                   "measured and true magnetic flux density, in S (below) |")
    if "ground_truth" in names:
        out.append(f"| `ground_truth.csv` | sample (every {names['ground_truth'].period:g} s) | "
                   "the capsule's "
                   "true pose and velocity (below) |")
    if d.polyps:
        out += [
            "| `Frames/Lesions_XXXX.png` | frame | 16-bit instance mask: 0 where no lesion is "
            "seen, k + 1 on lesion k (a polyp, or a diverticulum's sac seen through its neck) |",
            f"| `lesions.csv` | lesion ({d.polyps}) | Paris type (or `diverticulum`), size (mm; "
            "a diverticulum's neck), size class, "
            "segment, arc length (m), its top in W (m), frames that show it, their largest "
            "pixel area |",
            "| `lesion_frames.csv` | polyp seen in a frame | `frame, polyp, pixel_area, "
            "box_x_px, box_y_px, box_w_px, box_h_px` |",
            "| `lesions_coco.json` | (one) | COCO instances: every frame an image, one "
            "annotation per polyp it shows (mask as compressed RLE, box, area; "
            "`lesion_index`, `size_mm`, `size_class`, `segment`); categories the Paris types "
            "and diverticulum "
            "(written at the end; `lesion_frames.jsonl` holds its rows as they come) |",
        ]
    out += [
        "| `camera.yaml` | (one) | lens model, intrinsics K and distortion D (OpenCV's "
        "order), image size, mounting T_body_camera, frame rate, depth encoding |",
        "| `sensors.yaml` | (one) | each sensor's mounting T_body_sensor, rate, range and "
        "noise |",
        "| `metrics.json`, `scenario.yaml`, `logs.npz` | (one) | the run's metrics, its full "
        "scenario (to record it again) and its logs |",
        "| `wall_pressure.npz`, `wall_pressure.png` | (one) | the contact's pressure on the "
        "colon wall per patch (1 cm along by 30 degrees around): each patch's peak and longest "
        "time above 330 kPa and 4.0 kPa, and its picture (none without a pressure field) |",
        "",
        "### Depth (`Frames/Depth_XXXX.png`)",
        "",
        f"Range along each pixel's ray from the camera centre (not z-depth: beyond 90 degrees "
        f"off axis z-depth means nothing), 16-bit, full scale {scale:g} m:",
        "",
        f"- `{DEPTH_NONE}`: no measurement: outside the lens's image circle (`mask.png` is 0 "
        f"there), or tissue nearer than the near clip ({1000 * camera.near:g} mm);",
        f"- `1`-`{DEPTH_BEYOND - 1}`: range in metres = value / {DEPTH_SCALE:g} x {scale:g} "
        f"(steps of {1e6 * scale / DEPTH_SCALE:.1f} um);",
        f"- `{DEPTH_BEYOND}`: nothing within {scale:g} m (the lumen far ahead; the light leaves "
        "under 4 % there).",
        "",
        "### Lens",
        "",
    ]
    if lens.is_fisheye:
        out += [
            f"`{lens.model}`: a ray at angle theta off the optical axis and azimuth phi lands at "
            "radius r = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8) (OpenCV's "
            "`cv2.fisheye` model; k = 0 for the equidistant lens), u = fx r cos(phi) + cx, "
            f"v = fy r sin(phi) + cy, for theta up to {lens.fov_deg / 2:g} degrees. "
            f"fx = {lens.fx:.6g}, fy = {lens.fy:.6g}, cx = {lens.cx:.6g}, cy = {lens.cy:.6g} px; "
            f"D = [{_fmt(_distortion(lens)[1])}].",
        ]
    else:
        out += [
            "`pinhole_radtan`: OpenCV's pinhole model with radial-tangential distortion "
            "(`cv2.projectPoints` with D = k1, k2, p1, p2, k3). "
            f"fx = {lens.fx:.6g}, fy = {lens.fy:.6g}, cx = {lens.cx:.6g}, cy = {lens.cy:.6g} px; "
            f"D = [{_fmt(_distortion(lens)[1])}].",
        ]
    if camera.latency > 0:
        out += ["", f"Frames reach the writer {1000 * camera.latency:g} ms after their exposure "
                "(a capsule's radio link); every time and pose of a frame is its exposure's."]
    out += [
        "",
        "### Lumen truth (`lumen_truth.csv`)",
        "",
        "`index, time_s, u_px, v_px, visible, x_m, y_m, z_m, s_m, far_u_px, far_v_px, "
        "far_visible`: the centreline point 5 cm "
        "ahead of the camera along the colon, (x, y, z) in W and s its arc length from the "
        "colon's anal end; (u, v) its pixel through the lens; visible = 1 when it is inside the "
        "field of view and not hidden by nearer tissue (checked against the frame's depth). "
        "Then the image-side truth, read from the frame's range alone: (far_u, far_v) the "
        f"range-weighted centre of the farthest {100 * FAR_FRACTION:g} % of the lens's field "
        "of view (each pixel counted by the solid angle it sees; what sees past the "
        "depth's full scale counts as that scale), far_visible = 1 when that centre lies at "
        f"least {RIM_ANGLE_DEG:g} degrees inside the field's edge (a far "
        "region hugging the rim "
        "is the lumen's ends seen past a wall; NaN pixel when the view has no farther part). "
        "Computed from the frame's own pose and depth.",
    ]
    if "imu" in names:
        imu = d.imu
        out += [
            "",
            "### IMU (`imu.csv`)",
            "",
            "`time_s, ax_m_s2, ay_m_s2, az_m_s2, gx_rad_s, gy_rad_s, gz_rad_s`, then the same "
            "with `_true` (e.g. `ax_true_m_s2`): the accelerometer's specific force (m/s^2: "
            "acceleration minus gravity, so +9.81 up at rest) and the gyroscope's angular "
            "velocity of S relative to W (rad/s), both expressed in the sensor frame S; "
            "measured (white noise, bias random walk, turn-on bias, range, 16-bit "
            "quantisation) and true. Ranges: "
            f"+-{imu.accel_range:.4g} m/s^2 (+-{imu.accel_range / 9.80665:g} g) and "
            f"+-{imu.gyro_range:.4g} rad/s (+-{math.degrees(imu.gyro_range):g} deg/s): the "
            "measured values saturate beyond them, the true ones do not.",
        ]
    if "ahrs" in names:
        out += [
            "",
            "### Attitude estimate (`ahrs.csv`)",
            "",
            "`time_s, qx, qy, qz, qw`: the on-board filter's estimate of q_WB (Mahony's "
            "complementary filter on the measured IMU samples, with gyro-bias estimation). It "
            "starts from the true start attitude; its first row is its first estimate, one IMU "
            "period after the start. It has no heading reference (the external magnet swamps "
            "the earth's field), so its yaw drifts with the gyro's bias; a rotation faster "
            "than the gyro's range is measured clipped, and the estimate then departs from the "
            "truth.",
        ]
    if "magnetometer" in names:
        out += [
            "",
            "### Magnetometer (`magnetometer.csv`)",
            "",
            "`time_s, bx_T, by_T, bz_T`, then `bx_true_T, by_true_T, bz_true_T`: the magnetic "
            "flux density of the external magnet at the sensor, in S (T), measured (noise, "
            f"turn-on bias, +-{d.magnetometer.range:g} T range, quantisation) and true. The "
            "capsule's own magnet is left out (a real capsule calibrates its constant field "
            "away).",
        ]
    if "ground_truth" in names:
        out += [
            "",
            "### Ground truth (`ground_truth.csv`)",
            "",
            "`time_s, x_m, y_m, z_m, qx, qy, qz, qw, wx_rad_s, wy_rad_s, wz_rad_s, vx_m_s, "
            "vy_m_s, vz_m_s`: the capsule body's pose in W (p_WB, q_WB) and its angular "
            "velocity w_WB and the velocity of its origin v_WB, both expressed in W. The "
            "camera's pose is X_WC = X_WB T_body_camera (camera.yaml); at a frame's time "
            "(interpolate between rows where it falls between two) it is the frame's row of "
            "SavedPosition / SavedRotationQuaternion.",
        ]
    out += [
        "",
        "## Loading it",
        "",
        "With numpy and OpenCV only (`pip install numpy opencv-python`), from this folder:",
        "",
        "```python",
        _load_example(d),
        "```",
        "",
        "## Compared with SimCol3D",
        "",
        "The same names for the frames and poses (`Frames/FrameBuffer_XXXX.png`, "
        "`Frames/Depth_XXXX.png`, `SavedPosition.txt`, `SavedRotationQuaternion.txt` with "
        "qx qy qz qw), one folder per sequence instead of the `_<sequence>` suffixes. "
        "Differences: the world frame is right-handed and in metres (SimCol3D's Unity frame is "
        "left-handed); depth is range along the ray, with 0 for no measurement and 65535 for "
        "beyond the full scale; the lens is a fisheye unless camera.yaml says pinhole; the "
        "sensor streams, mask and lumen truth are additions.",
        "",
    ]
    return "\n".join(out)


def load_example_code(readme: str) -> str:
    """The Python block of a dataset's README.md (for the tests, which run it as written)."""
    start = readme.index("```python\n") + len("```python\n")
    return readme[start:readme.index("```", start)]


def splits_readme(rule: str, fractions, counts: dict) -> str:
    """README.md at the top of a batch of recordings: the splits and their rule."""
    train, val, test = fractions
    return "\n".join([
        "# Capsule datasets, one folder per colon seed",
        "",
        "Each `seed_XXXX/` folder is one recording (its README.md describes the files). "
        "`splits.csv` says which seed belongs to which split: columns `seed, split, folder`.",
        "",
        f"Rule: {rule}. Fractions asked: train {train:g}, val {val:g}, test {test:g}; "
        f"seeds in each: " + ", ".join(f"{name} {n}" for name, n in counts.items()) + ".",
        "",
    ])


# Knuth's multiplicative constant: floor(2^32 x (sqrt(5) - 1) / 2).
GOLDEN_32 = 2654435769


def split_position(seed: int) -> float:
    """u in [0, 1) of a seed: (seed x 2654435769 mod 2^32) / 2^32, the golden-ratio sequence
    in exact integer arithmetic: consecutive seeds spread evenly over [0, 1)."""
    return ((int(seed) * GOLDEN_32) % 2**32) / 2**32


def split_of_seed(seed: int, fractions) -> str:
    """The split ("train", "val" or "test") of a colon seed: a fixed function of the seed and
    the fractions alone, so that recordings made in separate batches never put one seed in
    two splits. train if u < f_train, val if u < f_train + f_val, else test
    (u = `split_position(seed)`)."""
    train, val, _ = fractions
    u = split_position(seed)
    if u < train:
        return "train"
    if u < train + val:
        return "val"
    return "test"


SPLIT_RULE = ("u = (seed x 2654435769 mod 2^32) / 2^32 (the golden-ratio sequence, which "
              "spreads consecutive seeds evenly); train if u < f_train, val if "
              "u < f_train + f_val, else test. A seed's split depends on the seed and the "
              "fractions only, so batches recorded separately combine without a seed in two "
              "splits")


def split_counts(seeds, fractions) -> dict:
    counts = {"train": 0, "val": 0, "test": 0}
    for seed in seeds:
        counts[split_of_seed(seed, fractions)] += 1
    return counts
