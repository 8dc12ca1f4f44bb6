"""The Gymnasium environment (app/gym_env.py): Gymnasium's own checker, the spaces,
the reward's progress against the centreline found independently, the action's bounds
and the EPM's clearance from the skin, the seeding, the reuse of built diagrams, a vector
of two environments, and the example script."""

import os
import subprocess
import sys
import warnings
from pathlib import Path

import gymnasium
from gymnasium.utils.env_checker import check_env
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import capsule_drake  # noqa: F401  (registers the environment)
from capsule_drake.app.gym_env import (ENV_ID, OBSERVATIONS, ColonNavigationEnv,
                                              action_toward, rotate)

REPO = Path(__file__).resolve().parents[1]
COLON = 3   # one colon for every test: built once per environment


@pytest.fixture(scope="module")
def env():
    """Every observation, on one colon (colons=(3,): every reset seed runs colon 3)."""
    environment = gymnasium.make(ENV_ID, observations=OBSERVATIONS, colons=(COLON,),
                                 image_size=32, render_mode="rgb_array")
    yield environment
    environment.close()


def centreline_station(colon, p, spacing=5e-4):
    """Arc length of the centreline point closest to p, by brute force: the closest of
    samples every `spacing`, then the closest point on the chords either side of it."""
    s = np.arange(0.0, colon.centerline.length, spacing)
    points = colon.centerline.point_at(s)
    i = int(np.argmin(np.linalg.norm(points - p, axis=1)))
    best_s, best_d = s[i], np.linalg.norm(points[i] - p)
    for j in (i - 1, i):
        if 0 <= j < len(s) - 1:
            a, b = points[j], points[j + 1]
            f = float(np.clip((p - a) @ (b - a) / ((b - a) @ (b - a)), 0.0, 1.0))
            d = np.linalg.norm(a + f * (b - a) - p)
            if d < best_d:
                best_s, best_d = s[j] + f * (s[j + 1] - s[j]), d
    return best_s


def magnet_skin_gap(colon, pose, magnet):
    """Smallest vertical gap (m) between the EPM cylinder's surface, sampled on its caps and
    side at `pose` [p, m_hat], and the skin straight under each sample."""
    p, m = np.asarray(pose[:3], float), np.asarray(pose[3:], float)
    m = m / np.linalg.norm(m)
    e1 = np.cross(m, [1.0, 0.0, 0.0] if abs(m[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(m, e1)
    radius, half = 0.5 * magnet.dimensions[0], 0.5 * magnet.dimensions[1]
    phi = np.linspace(0.0, 2.0 * np.pi, 180, endpoint=False)
    ring = np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2
    points = [p + t * m + radius * ring for t in np.linspace(-half, half, 21)]
    points += [p + side * half * m + r * ring for side in (-1, 1) for r in
               np.linspace(0.0, radius, 11)]
    points = np.concatenate(points)
    return float(np.min(points[:, 2] - colon.abdomen.skin_height(points[:, 0], points[:, 1])))


@pytest.mark.slow
def test_gymnasium_check_env_passes_and_resets_reuse_the_diagram(env):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        # Its render check would build another environment: render is checked below.
        check_env(env.unwrapped, skip_render_check=True)
    assert not [str(w.message) for w in caught if "gymnasium" in w.filename]
    # check_env reset it with seeds 123, 456 and drawn ones: all colon 3, built once.
    assert env.unwrapped.build_count == 1
    env.reset(seed=3)
    obs, *_ = env.step(env.action_space.sample())
    np.testing.assert_array_equal(env.render(), obs["camera"])


@pytest.mark.slow
def test_random_steps_observations_in_space_and_progress_from_the_truth(env):
    obs, info = env.reset(seed=3)
    assert info["colon_seed"] == COLON and info["noise_seed"] == 3
    assert obs in env.observation_space
    colon = env.unwrapped.colon
    weight = env.unwrapped.reward_weights.progress
    env.action_space.seed(0)
    s_before = centreline_station(colon, obs["truth"][4:7].astype(float))
    progress_terms, independent = [], []
    for _ in range(20):
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        assert obs in env.observation_space
        assert obs["camera"].dtype == np.uint8 and obs["camera"].shape == (32, 32, 3)
        # The terms sum to the reward.
        assert reward == pytest.approx(sum(info["reward_terms"].values()), abs=1e-12)
        s_after = centreline_station(colon, obs["truth"][4:7].astype(float))
        progress_terms.append(info["reward_terms"]["progress"] / weight)
        independent.append(s_after - s_before)
        s_before = s_after
        assert not (terminated or truncated), info["reason"]
    # The reward's progress is the change of the capsule's centreline station (m), as the
    # brute-force closest point gives it (within its chord error, ~0.1 mm).
    np.testing.assert_allclose(progress_terms, independent, atol=2e-4)
    assert max(np.abs(independent)) > 1e-3   # the capsule moved (the check is not vacuous)
    assert info["progress"] == pytest.approx(np.sum(independent), abs=1e-3)


@pytest.mark.slow
def test_seeding_and_reuse_of_the_built_diagram(env):
    builds = env.unwrapped.build_count
    actions = np.random.default_rng(1).uniform(-1.0, 1.0, size=(5, 6))

    def episode(seed):
        obs, _ = env.reset(seed=seed)
        out = [obs]
        for a in actions:
            out.append(env.step(a)[0])
        return out

    first, again, other = episode(5), episode(5), episode(6)
    for a, b in zip(first, again):  # the same seed on the reused diagram: the same run
        for name in a:
            np.testing.assert_array_equal(a[name], b[name])
    # Another seed, the same colon: other sensor noise.
    assert not np.array_equal(first[-1]["imu"], other[-1]["imu"])
    env.reset(options={"colon": COLON})
    assert env.unwrapped.build_count == builds   # no rebuild for the same colon


@pytest.mark.slow
def test_actions_are_clipped_and_the_epm_keeps_its_clearance(env):
    unwrapped = env.unwrapped
    obs, _ = env.reset(seed=3)
    x0 = obs["epm"][:3].astype(float)
    # Beyond the bound: clipped to one full step (the kinematic stage follows at once).
    obs, _, _, _, info = env.step(np.array([4.0, -1.0, 0.0, 0.0, 0.0, 0.0], np.float32))
    assert info["action_clipped"]
    np.testing.assert_allclose(obs["epm"][:2] - x0[:2], [unwrapped.max_move,
                                                          -unwrapped.max_move], atol=1e-6)
    obs, _, _, _, info = env.step(np.array([0.5, 0.0, 0.0, 0.0, 0.0, 0.0], np.float32))
    assert not info["action_clipped"]
    with pytest.raises(ValueError, match="finite"):
        env.step(np.array([np.nan, 0, 0, 0, 0, 0]))
    with pytest.raises(ValueError, match="shape"):
        env.step(np.zeros(5))
    # Driving the magnet down onto the patient, tilting it: it stays `clearance` clear of
    # the skin (its surface sampled against the abdomen's skin, not the guard's formula).
    clearance = unwrapped.scenario.epm.clearance
    magnet = unwrapped.scenario.epm.magnet
    m_start = obs["epm"][3:].astype(float)
    raised = 0
    for k in range(12):
        action = np.array([0.0, 0.3, -1.0, 1.0 if k < 8 else 0.0, 0.0, 0.0], np.float32)
        obs, _, terminated, _, info = env.step(action)
        raised += info["epm_raised"]
        gap = magnet_skin_gap(unwrapped.colon, obs["epm"].astype(float), magnet)
        assert gap >= clearance - 1e-6, (k, gap)
        assert not terminated, info["reason"]
    assert raised >= 10   # it was pushed into the floor, and held there
    # Its moment turned by 8 full steps about world x (the floor moves only its centre).
    turned = Rotation.from_rotvec([8 * unwrapped.max_turn, 0.0, 0.0]).apply(m_start)
    np.testing.assert_allclose(obs["epm"][3:], turned, atol=1e-5)


def test_action_toward_moves_a_command_to_a_target_within_the_bounds():
    rng = np.random.default_rng(4)
    max_move, max_turn = 0.003, np.radians(5.0)
    for _ in range(20):
        command = np.concatenate([rng.uniform(-0.2, 0.2, 3), rng.normal(size=3)])
        command[3:] /= np.linalg.norm(command[3:])
        target = np.concatenate([command[:3] + rng.uniform(-0.02, 0.02, 3), rng.normal(size=3)])
        target[3:] /= np.linalg.norm(target[3:])
        for _ in range(60):
            a = action_toward(command, target, max_move, max_turn)
            assert np.all(np.abs(a) <= 1.0 + 1e-6)
            command = np.concatenate([command[:3] + max_move * a[:3],
                                      rotate(command[3:], max_turn * a[3:])])
        np.testing.assert_allclose(command[:3], target[:3], atol=1e-6)
        np.testing.assert_allclose(command[3:], target[3:], atol=1e-5)


def test_rotate_matches_scipy():
    rng = np.random.default_rng(2)
    for _ in range(10):
        v, w = rng.normal(size=3), rng.normal(size=3)
        np.testing.assert_allclose(rotate(v, w), Rotation.from_rotvec(w).apply(v), atol=1e-12)


@pytest.mark.parametrize("kwargs, key", [
    ({"observations": ("camera", "sonar")}, "'sonar'"),
    ({"observations": ()}, "observations"),
    ({"colons": ()}, "colons"),
    ({"colons": (-1,)}, "colons"),
    ({"control_period": 0.0}, "control_period"),
    ({"max_epm_speed": 5.0}, "max_epm_speed"),
    ({"reward": {"progres": 1.0}}, "progres"),
    ({"reward": {"force": -1.0}}, "reward.force"),
    ({"workspace": ((0, 0, 0), (0, 1, 1))}, "workspace"),
    ({"render_mode": "depth"}, "render_mode"),
])
def test_bad_settings_give_one_line(kwargs, key):
    with pytest.raises(ValueError) as error:
        ColonNavigationEnv(**kwargs)
    message = str(error.value)
    assert key in message and "\n" not in message


def test_a_bad_observation_name_through_make():
    with pytest.raises(ValueError, match=r"^observations: unknown 'sonar'; choose from camera"):
        gymnasium.make(ENV_ID, observations=("imu", "sonar"))


@pytest.mark.slow
def test_a_vector_of_two_environments_steps():
    # Spawned workers (a fork of this multi-threaded process may deadlock), which import
    # the package through the "module:id" form of the name.
    envs = gymnasium.vector.AsyncVectorEnv(
        [lambda: gymnasium.make(f"capsule_drake:{ENV_ID}", colons=(COLON,))] * 2,
        context="spawn")
    try:
        obs, info = envs.reset(seed=[3, 4])
        assert obs in envs.observation_space
        assert list(info["noise_seed"]) == [3, 4]
        envs.action_space.seed(0)
        for _ in range(3):
            obs, reward, terminated, truncated, info = envs.step(envs.action_space.sample())
        assert obs in envs.observation_space and reward.shape == (2,)
        np.testing.assert_allclose(info["t"], [0.3, 0.3])
        assert not np.array_equal(obs["imu"][0], obs["imu"][1])   # their own noise
    finally:
        envs.close()


def test_importing_the_package_registers_the_environment_without_drake():
    code = ("import sys, gymnasium, capsule_drake; "
            f"assert {ENV_ID!r} in gymnasium.registry; "
            "assert not [m for m in sys.modules if m.startswith('pydrake')]")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                            timeout=60, env=dict(os.environ, PYTHONPATH=str(REPO)))
    assert result.returncode == 0, result.stderr[-2000:]


@pytest.mark.slow
def test_the_example_evaluates_both_policies():
    result = subprocess.run(
        [sys.executable, str(REPO / "examples" / "gym_evaluate.py"), "--episodes", "1",
         "--steps", "3", "--image-size", "32"],
        capture_output=True, text=True, timeout=300, cwd=REPO,
        env=dict(os.environ, PYTHONPATH=str(REPO)))
    assert result.returncode == 0, result.stderr[-2000:]
    lines = result.stdout.splitlines()
    assert any(line.startswith("random") and "mean return" in line for line in lines)
    assert any(line.startswith("heuristic") and "mean return" in line for line in lines)
