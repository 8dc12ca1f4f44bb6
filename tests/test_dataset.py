"""DatasetWriter: what it writes can be read back exactly (images, depth encoding, poses,
streams from their first real sample)."""

import cv2
import numpy as np
from pydrake.common.eigen_geometry import Quaternion
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform, RollPitchYaw, RotationMatrix
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder, LeafSystem
from pydrake.systems.primitives import ConstantValueSource, ConstantVectorSource
from pydrake.systems.sensors import ImageDepth32F, ImageRgba8U

from capsule_drake.app.dataset import DatasetWriter, Stream, encode_depth, read_depth_png
from capsule_drake.perception.lumen_truth import far_region


class FrameClock(LeafSystem):
    """A camera stand-in's frame time: the start of the current 0.1 s frame period."""

    def __init__(self):
        super().__init__()
        self.DeclareVectorOutputPort(
            "frame_time", 1,
            lambda context, out: out.SetAtIndex(0, np.floor(context.get_time() / 0.1 + 1e-9) * 0.1))


def test_writer_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    rgb = ImageRgba8U(32, 24)
    rgb.mutable_data[:] = rng.integers(0, 255, size=(24, 32, 4), dtype=np.uint8)
    depth = ImageDepth32F(32, 24)
    depth.mutable_data[:] = rng.uniform(0.001, 0.19, size=(24, 32, 1)).astype(np.float32)
    depth.mutable_data[0, 5, 0] = np.inf  # nothing within range: 65535
    depth.mutable_data[5, 5, 0] = 0.0     # nearer than the near clip: no measurement
    mask = np.ones((24, 32), dtype=bool)
    mask[:, :3] = False                   # outside the lens's circle: no measurement
    X_WC = RigidTransform(RotationMatrix(RollPitchYaw(0.3, -0.2, 1.0)), [0.1, -0.2, 0.08])
    pose = np.concatenate([X_WC.rotation().matrix().ravel(), X_WC.translation()])
    seen = []

    def lumen_truth(X, depth_m):
        seen.append((X, depth_m))
        return np.array([100.5, 80.25]), True, np.array([0.1, 0.2, 0.3]), 0.4

    builder = DiagramBuilder()
    writer = builder.AddSystem(DatasetWriter(
        tmp_path, frame_check_period=0.02, mask=mask, depth_full_scale=0.2,
        lumen_truth=lumen_truth, texts={"camera.yaml": "model: test\n"},
        streams=[Stream("imu", ("ax", "ay", "az"), 0.01),
                 # A sensor whose first real sample is at 0.05 s, its entries reordered, its
                 # rows stamped 2 ms after the sample time.
                 Stream("late", ("b", "a"), 0.01, first_sample=0.05, order=(1, 0),
                        stamp_shift=0.002),
                 Stream("truth", ("x",), 0.05, after_update=False)]))
    for name, source in [("rgb", ConstantValueSource(AbstractValue.Make(rgb))),
                         ("depth", ConstantValueSource(AbstractValue.Make(depth))),
                         ("frame_pose", ConstantVectorSource(pose)),
                         ("imu", ConstantVectorSource([0.1, -9.81, 0.5])),
                         ("late", ConstantVectorSource([1.0, 2.0])),
                         ("truth", ConstantVectorSource([3.0]))]:
        builder.Connect(builder.AddSystem(source).get_output_port(),
                        writer.GetInputPort(name))
    builder.Connect(builder.AddSystem(FrameClock()).get_output_port(),
                    writer.GetInputPort("frame_time"))
    Simulator(builder.Build()).AdvanceTo(0.35)
    writer.close()

    assert writer.frames_written == 4  # frames at 0, 0.1, 0.2, 0.3 s
    back = cv2.cvtColor(cv2.imread(str(tmp_path / "Frames" / "FrameBuffer_0002.png")),
                        cv2.COLOR_BGR2RGB)
    np.testing.assert_array_equal(back, rgb.data[:, :, :3])
    raw = cv2.imread(str(tmp_path / "Frames" / "Depth_0003.png"), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint16
    assert raw[0, 5] == 65535 and raw[5, 5] == 0 and not raw[:, :3].any()
    np.testing.assert_array_equal(cv2.imread(str(tmp_path / "mask.png"), cv2.IMREAD_GRAYSCALE),
                                  np.where(mask, 255, 0))
    d = read_depth_png(tmp_path / "Frames" / "Depth_0003.png", 0.2)
    assert np.isinf(d[0, 5]) and np.isnan(d[5, 5]) and np.isnan(d[:, :3]).all()
    measured = np.isfinite(d)
    # 16 bits over 0.2 m: 3 micrometre steps.
    np.testing.assert_allclose(d[measured], depth.data[:, :, 0][measured], atol=2e-6)
    position = np.loadtxt(tmp_path / "SavedPosition.txt")
    np.testing.assert_allclose(position[0], X_WC.translation(), atol=1e-8)
    qx, qy, qz, qw = np.loadtxt(tmp_path / "SavedRotationQuaternion.txt")[1]
    R = RotationMatrix(Quaternion(qw, qx, qy, qz)).matrix()
    np.testing.assert_allclose(R, X_WC.rotation().matrix(), atol=1e-8)
    # The lumen truth was asked of the frame's own pose and depth.
    assert len(seen) == 4 and seen[0][0].IsExactlyEqualTo(X_WC)
    np.testing.assert_array_equal(np.isinf(seen[0][1]), np.isinf(depth.data[:, :, 0]))
    lumen_rows = np.loadtxt(tmp_path / "lumen_truth.csv", delimiter=",", skiprows=1)
    assert lumen_rows.shape == (4, 12)
    np.testing.assert_allclose(lumen_rows[0, 2:9], [100.5, 80.25, 1, 0.1, 0.2, 0.3, 0.4])
    # The image-side truth of the frame's own range inside the lens's field.
    far = far_region(depth.data[:, :, 0], mask, 0.2)
    np.testing.assert_allclose(lumen_rows[0, 9:11], far.pixel, atol=1e-3, equal_nan=True)
    assert lumen_rows[0, 11] == int(far.visible)
    imu = np.loadtxt(tmp_path / "imu.csv", delimiter=",", skiprows=1)
    np.testing.assert_allclose(imu[:, 0], 0.01 * np.arange(len(imu)), atol=1e-9)
    assert len(imu) == 35  # samples at 0, 0.01, ..., 0.34 s
    np.testing.assert_allclose(imu[:, 1:], [[0.1, -9.81, 0.5]] * len(imu))
    late = np.genfromtxt(tmp_path / "late.csv", delimiter=",", names=True)
    assert late.dtype.names == ("time_s", "b", "a")
    np.testing.assert_allclose(late["time_s"], 0.052 + 0.01 * np.arange(30), atol=1e-9)
    assert (late["b"] == 2.0).all() and (late["a"] == 1.0).all()
    truth = np.loadtxt(tmp_path / "truth.csv", delimiter=",", skiprows=1)
    np.testing.assert_allclose(truth[:, 0], 0.05 * np.arange(7), atol=1e-9)
    assert (tmp_path / "camera.yaml").read_text() == "model: test\n"


def test_depth_encoding_keeps_no_measurement_apart_from_beyond_range():
    depth = np.array([[np.nan, 0.0, 1e-7, 0.05, 0.2 - 1e-7, np.inf, 0.1]])
    mask = np.array([[True, True, True, True, True, True, False]])
    raw = encode_depth(depth, mask, 0.2)
    # NaN and 0 (nearer than the near clip) and outside the mask: 0; a tiny range is still
    # a measurement (1); a range just short of full scale is not "beyond" (65534).
    np.testing.assert_array_equal(raw, [[0, 0, 1, 16384, 65534, 65535, 0]])
