"""A recorded dataset folder, read as a user would: by running the example code of its
README.md (numpy and OpenCV only), then checked against independent routes: the camera's
pose against the ground truth composed with the camera's mounting, the back-projected
depth against the colon's wall mesh, the README's rays against the lens model, the IMU
against the ground truth's motion. And `record --seeds`: one folder per seed, splits that
partition the seeds."""

import ast
import json

import numpy as np
import pytest
import trimesh
import yaml

from capsule_drake.app import record as record_module
from capsule_drake.anatomy import load_colon
from capsule_drake.app.cli import main as cli_main
from capsule_drake.app.dataset_docs import load_example_code, split_of_seed
from capsule_drake.perception import Lens, LensConfig
from capsule_drake.scenario import load_scenario

SEED = 1  # the colon the benchmark's tests build too (cached once)
# Ground truth at the plant's step, so that every sensor sample has its truth row.
TEXT = "{outputs: {log_period: 0.002}}"
GRAVITY_W = np.array([0.0, 0.0, -9.81])  # Drake's default gravity (m/s^2)


@pytest.fixture(scope="module")
def batch(tmp_path_factory):
    out = tmp_path_factory.mktemp("record") / "batch"
    code = cli_main(["record", "--seeds", str(SEED), "--duration", "0.55", "--scenario-text",
                     TEXT, "--out", str(out), "--quiet"])
    assert code == 0
    return out


@pytest.fixture(scope="module")
def folder(batch):
    return batch / f"seed_{SEED:04d}"


@pytest.fixture(scope="module")
def loaded(folder):
    """The README's example, run as written from inside the folder."""
    code = load_example_code((folder / "README.md").read_text())
    imported = {alias.name for node in ast.walk(ast.parse(code))
                if isinstance(node, (ast.Import, ast.ImportFrom)) for alias in node.names}
    assert imported == {"cv2", "numpy"}, imported
    namespace = {}
    with pytest.MonkeyPatch.context() as patch:
        patch.chdir(folder)
        exec(compile(code, "README.md", "exec"), namespace)
    return namespace


def _rows(truth, times):
    """Indices of the ground-truth rows at `times` (each must have one)."""
    index = np.searchsorted(truth["time_s"], np.asarray(times) - 1e-7)
    np.testing.assert_allclose(truth["time_s"][index], times, atol=1e-6)
    return index


def _quaternion_rotations(q_xyzw):
    """Rotation matrices of x, y, z, w quaternions, by an independent formula (scipy's)."""
    from scipy.spatial.transform import Rotation
    return Rotation.from_quat(q_xyzw).as_matrix()


@pytest.mark.slow
def test_the_folder_has_what_its_readme_lists(folder):
    frames = sorted((folder / "Frames").glob("FrameBuffer_*.png"))
    depths = sorted((folder / "Frames").glob("Depth_*.png"))
    assert len(frames) == len(depths) == 6  # 10 fps from t = 0
    readme = (folder / "README.md").read_text()
    for name in ("mask.png", "frames.csv", "SavedPosition.txt", "SavedRotationQuaternion.txt",
                 "lumen_truth.csv", "imu.csv", "ahrs.csv", "magnetometer.csv",
                 "ground_truth.csv", "camera.yaml", "sensors.yaml", "wall_pressure.npz",
                 "wall_pressure.png"):
        assert (folder / name).exists() and f"`{name}`" in readme, name
    lumen = np.loadtxt(folder / "lumen_truth.csv", delimiter=",", skiprows=1)
    assert lumen.shape == (6, 12) and lumen[:, 4].all()
    assert json.loads((folder / "metrics.json").read_text())["stopped_early"] is None


@pytest.mark.slow
def test_camera_pose_equals_the_ground_truth_through_the_camera_mounting(folder, loaded):
    truth = loaded["truth"]
    rows = _rows(truth, loaded["frames"]["time_s"])
    mounting = yaml.safe_load((folder / "camera.yaml").read_text())["T_body_camera"]
    R_BC = _quaternion_rotations(mounting["quaternion_xyzw"])
    p_BC = np.array(mounting["position_m"])
    R_WB = _quaternion_rotations(loaded["q_WB"][rows])
    p_WB = loaded["p_WB"][rows]
    # X_WC = X_WB X_BC, from the body's truth; the files hold the pose the frame was drawn
    # from, at the same instant.
    np.testing.assert_allclose(loaded["p_WC"], p_WB + R_WB @ p_BC, atol=1e-8)
    R_WC = _quaternion_rotations(loaded["q_WC"])
    np.testing.assert_allclose(R_WC, R_WB @ R_BC, atol=1e-8)
    np.testing.assert_allclose(loaded["R_WC"], R_WC[0], atol=1e-12)  # the README's formula


@pytest.mark.slow
def test_depth_with_the_mask_back_projects_onto_the_colon_wall(folder, loaded):
    mask, raw, depth = loaded["mask"], loaded["raw"], loaded["depth"]
    assert mask.any() and not mask.all()  # the fisheye's circle inside the square image
    assert not raw[~mask].any()           # outside the lens: 0, no measurement
    assert not loaded["rgb"][~mask].any()  # and black
    assert (raw[mask] > 0).mean() > 0.99  # inside it: a range, or 65535 beyond 0.2 m
    assert np.isfinite(depth[mask]).mean() > 0.5
    # The README's rays (numpy's inversion of the lens's radius) against the lens model.
    camera = yaml.safe_load((folder / "camera.yaml").read_text())
    assert camera["model"] == "equidistant"
    lens = Lens(LensConfig(model="equidistant", width=camera["width"], height=camera["height"],
                           fov_deg=camera["fov_deg"]))
    pixels = np.column_stack([loaded["u"], loaded["v"]]).astype(float)
    np.testing.assert_allclose(loaded["rays_C"], lens.unproject(pixels), atol=1e-7)
    # Every measured point lies on the wall the camera sees (the visual mesh, a finer
    # tessellation of the same surface): measured, median 0.04 mm, largest 0.2 mm.
    colon, _ = load_colon(load_scenario(override=f"{{colon: {{seed: {SEED}}}}}").colon)
    points = loaded["points_W"]
    chosen = points[np.random.default_rng(0).choice(len(points), 300, replace=False)]
    _, distance, _ = trimesh.proximity.closest_point(colon.visual_mesh(), chosen)
    assert np.median(distance) < 2e-4 and distance.max() < 1e-3, np.percentile(distance, 90)


@pytest.mark.slow
def test_imu_columns_are_si_in_the_sensor_frame(folder, loaded):
    imu, truth = loaded["imu"], loaded["truth"]
    sensors = yaml.safe_load((folder / "sensors.yaml").read_text())
    R_BS = _quaternion_rotations(sensors["imu"]["T_body_sensor"]["quaternion_xyzw"])
    rows = _rows(truth, imu["time_s"])
    R_WB = _quaternion_rotations(loaded["q_WB"][rows])
    R_SW = np.einsum("ji,njk->nik", R_BS, np.transpose(R_WB, (0, 2, 1)))
    w_W = np.column_stack([truth["wx_rad_s"], truth["wy_rad_s"], truth["wz_rad_s"]])[rows]
    gyro_true = np.column_stack([imu["gx_true_rad_s"], imu["gy_true_rad_s"],
                                 imu["gz_true_rad_s"]])
    # rad/s, in S: the body's angular velocity from the ground truth, turned into S.
    np.testing.assert_allclose(gyro_true, np.einsum("nij,nj->ni", R_SW, w_W), atol=1e-6)
    # m/s^2, in S: specific force = acceleration - gravity; the acceleration over the plant
    # step that ends at the sample (the ground truth's velocities, differenced).
    v_W = np.column_stack([truth["vx_m_s"], truth["vy_m_s"], truth["vz_m_s"]])
    dt = truth["time_s"][rows] - truth["time_s"][rows - 1]
    a_W = (v_W[rows] - v_W[rows - 1]) / dt[:, None]
    accel_true = np.column_stack([imu["ax_true_m_s2"], imu["ay_true_m_s2"],
                                  imu["az_true_m_s2"]])
    np.testing.assert_allclose(accel_true, np.einsum("nij,nj->ni", R_SW, a_W - GRAVITY_W),
                               atol=1e-4)
    # The measured gyro clips at its range, given in sensors.yaml in rad/s.
    assert np.abs(loaded["gyro"]).max() <= sensors["imu"]["gyro_range_rad_s"] + 1e-9
    magnetometer = loaded["magnetometer"]
    field = np.linalg.norm([magnetometer["bx_true_T"], magnetometer["by_true_T"],
                            magnetometer["bz_true_T"]], axis=0)
    assert (1e-4 < field).all() and (field < 0.05).all()  # millitesla, written in tesla


@pytest.mark.slow
def test_every_stream_starts_at_its_first_real_sample(loaded):
    imu, ahrs, magnetometer, truth = (loaded[k] for k in ("imu", "ahrs", "magnetometer",
                                                          "truth"))
    # The sensors sample at 0, 0.01, ... s and measure the state one plant step (2 ms) later.
    assert imu["time_s"][0] == pytest.approx(0.002) and magnetometer["time_s"][0] == \
        pytest.approx(0.002)
    assert np.linalg.norm(loaded["accel"][0]) > 5.0  # gravity, not a zero placeholder
    assert np.linalg.norm([magnetometer[k][0] for k in ("bx_T", "by_T", "bz_T")]) > 1e-4
    # The AHRS's first estimate (of the attitude one IMU period in), near the truth there,
    # not the identity it holds before.
    assert ahrs["time_s"][0] == pytest.approx(0.012)
    row = _rows(truth, ahrs["time_s"][:1])
    R_est = _quaternion_rotations(np.array([[ahrs[k][0] for k in ("qx", "qy", "qz", "qw")]]))
    R_true = _quaternion_rotations(loaded["q_WB"][row])
    angle = np.degrees(np.arccos(np.clip((np.trace(R_est[0].T @ R_true[0]) - 1) / 2, -1, 1)))
    assert angle < 10.0 and abs(ahrs["qw"][0]) < 0.5  # the truth here is far from identity
    assert truth["time_s"][0] == 0.0


@pytest.mark.slow
def test_camera_yaml_has_no_nulls_and_only_its_models_fields(folder):
    camera = yaml.safe_load((folder / "camera.yaml").read_text())

    def values(node):
        if isinstance(node, dict):
            for v in node.values():
                yield from values(v)
        elif isinstance(node, list):
            for v in node:
                yield from values(v)
        else:
            yield node

    assert None not in list(values(camera))
    assert not {"kb_coefficients", "radtan_coefficients", "lens"} & set(camera)
    assert camera["K"] == [[camera["fx"], 0.0, camera["cx"]], [0.0, camera["fy"], camera["cy"]],
                           [0.0, 0.0, 1.0]]
    assert None not in list(values(yaml.safe_load((folder / "sensors.yaml").read_text())))


@pytest.mark.slow
def test_the_batch_lists_its_seed_in_splits(batch):
    rows = np.genfromtxt(batch / "splits.csv", delimiter=",", names=True, dtype=None,
                         encoding="utf-8", ndmin=1)
    assert [int(r["seed"]) for r in rows] == [SEED]
    assert rows["split"][0] == split_of_seed(SEED, (0.7, 0.15, 0.15))
    assert "Rule:" in (batch / "README.md").read_text()


def test_record_seeds_partitions_the_seeds_into_splits(tmp_path, monkeypatch, capsys):
    recorded = []

    def fake_record(scenario, out_dir, progress=True, scenario_name=""):
        out_dir.mkdir(parents=True)
        recorded.append((scenario.colon.seed, scenario.random_seed, out_dir.name))
        return type("Result", (), {"status": "completed", "metrics": {}})()

    monkeypatch.setattr(record_module, "record", fake_record)   # record_seeds's
    out = tmp_path / "batch"
    assert cli_main(["record", "--seeds", "10-29,40", "--split", "0.5,0.25,0.25", "--out",
                     str(out), "--quiet"]) == 0
    seeds = list(range(10, 30)) + [40]
    # Each seed its own colon and noise, in its own folder.
    assert recorded == [(s, s, f"seed_{s:04d}") for s in seeds]
    with open(out / "splits.csv") as f:
        header, *lines = f.read().split()
    assert header == "seed,split,folder"
    split = {int(seed): name for seed, name, _ in (line.split(",") for line in lines)}
    # A partition: every seed once, in one of the three splits.
    assert sorted(split) == seeds and set(split.values()) <= {"train", "val", "test"}
    # Consecutive seeds spread evenly (the golden-ratio sequence): each split's count is
    # within 1.5 of its share of the 21 seeds even in so small a batch.
    counts = {name: list(split.values()).count(name) for name in ("train", "val", "test")}
    for name, share in zip(counts, (0.5, 0.25, 0.25)):
        assert abs(counts[name] - share * len(seeds)) <= 1.5, counts
    # The rule depends on the seed alone: the same seeds in another batch, the same splits.
    assert all(split_of_seed(s, (0.5, 0.25, 0.25)) == split[s] for s in seeds)
    # Over many seeds the shares are the fractions.
    shares = [split_of_seed(s, (0.7, 0.15, 0.15)) for s in range(1000)]
    assert abs(shares.count("train") - 700) <= 3 and abs(shares.count("val") - 150) <= 3


def test_record_seeds_errors_are_one_line(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(record_module, "record",
                        lambda *a, **k: pytest.fail("nothing may be recorded"))
    for argv, message in ((["--seeds", "5-3"], "each range from low to high"),
                          (["--seeds", "a-b"], "expected e.g."),
                          (["--seeds", "1,1"], "a seed is given twice"),
                          (["--seeds", "0-3", "--split", "0.5,0.6,0.1"], "add up to 1"),
                          (["--split", "0.7,0.15,0.15"], "only with --seeds"),
                          (["--seeds", "0-3", "--scenario-text", "{colon: {seed: 3}}"],
                           "sets colon.seed")):
        out = tmp_path / "never"
        assert cli_main(["record", *argv, "--out", str(out)]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and message in err, err
        assert not out.exists()
