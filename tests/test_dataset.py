"""DatasetWriter: what it writes can be read back exactly (images, depth scale, poses)."""

import cv2
import numpy as np
import pytest
from pydrake.common.eigen_geometry import Quaternion
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform, RollPitchYaw, RotationMatrix
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder, LeafSystem
from pydrake.systems.primitives import ConstantValueSource, ConstantVectorSource
from pydrake.systems.sensors import ImageDepth32F, ImageRgba8U

from capsule_drake.io.dataset import DatasetWriter, read_depth_png


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
    depth.mutable_data[0, 0, 0] = np.inf  # nothing hit: stored as full scale
    X_WB = RigidTransform(RotationMatrix(RollPitchYaw(0.3, -0.2, 1.0)), [0.1, -0.2, 0.08])
    X_BC = RigidTransform([0.0, 0.0, 0.01575])
    q = X_WB.rotation().ToQuaternion()
    state = np.concatenate([[q.w(), q.x(), q.y(), q.z()], X_WB.translation(), np.zeros(6)])
    lumen = np.array([100.5, 80.25, 1.0, 0.1, 0.2, 0.3, 0.4])

    builder = DiagramBuilder()
    writer = builder.AddSystem(DatasetWriter(
        tmp_path, X_BC, frame_check_period=0.02,
        streams=[("imu", ["ax", "ay", "az"], 0.01)], depth_full_scale=0.2,
        camera_yaml="model: test\n"))
    for name, source in [("rgb", ConstantValueSource(AbstractValue.Make(rgb))),
                         ("depth", ConstantValueSource(AbstractValue.Make(depth))),
                         ("capsule_state", ConstantVectorSource(state)),
                         ("lumen", ConstantVectorSource(lumen)),
                         ("imu", ConstantVectorSource([0.1, -9.81, 0.5]))]:
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
    d = read_depth_png(tmp_path / "Frames" / "Depth_0003.png", 0.2)
    # 16 bits over 0.2 m: 3 micrometre steps.
    expected = np.where(np.isfinite(depth.data[:, :, 0]), depth.data[:, :, 0], 0.2)
    np.testing.assert_allclose(d, expected, atol=2e-6)
    X_WC = X_WB.multiply(X_BC)
    position = np.loadtxt(tmp_path / "SavedPosition.txt")
    np.testing.assert_allclose(position[0], X_WC.translation(), atol=1e-8)
    qx, qy, qz, qw = np.loadtxt(tmp_path / "SavedRotationQuaternion.txt")[1]
    R = RotationMatrix(Quaternion(qw, qx, qy, qz)).matrix()
    np.testing.assert_allclose(R, X_WC.rotation().matrix(), atol=1e-8)
    lumen_rows = np.loadtxt(tmp_path / "lumen_truth.csv", delimiter=",", skiprows=1)
    assert lumen_rows.shape == (4, 9)
    np.testing.assert_allclose(lumen_rows[0, 2:], lumen, atol=1e-6)
    imu = np.loadtxt(tmp_path / "imu.csv", delimiter=",", skiprows=1)
    assert len(imu) == pytest.approx(36, abs=1)
    np.testing.assert_allclose(imu[:, 1:], [[0.1, -9.81, 0.5]] * len(imu))
    assert "depth_png_full_scale_m: 0.2" in (tmp_path / "camera.yaml").read_text()
    assert "FrameBuffer" in (tmp_path / "README.txt").read_text()
