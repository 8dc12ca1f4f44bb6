"""The PPO training example (examples/gym_train_ppo.py): its egocentric wrappers against the
world's geometry, and a short training run that writes its curve and a policy acting as
skrl's does."""

import csv
import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import gymnasium
import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]


def _example():
    spec = importlib.util.spec_from_file_location("gym_train_ppo",
                                                  REPO / "examples" / "gym_train_ppo.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _quaternion(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * axis])


class _Stub(gymnasium.Env):
    """The least of an environment the wrappers need: fixed spaces and one observation."""

    def __init__(self, observation):
        self.observation = observation
        self.observation_space = gymnasium.spaces.Dict(
            {"truth": gymnasium.spaces.Box(-np.inf, np.inf, (13,)),
             "epm": gymnasium.spaces.Box(-np.inf, np.inf, (6,))})
        self.action_space = gymnasium.spaces.Box(-1.0, 1.0, (6,), np.float32)
        self.actions = []

    def reset(self, **kwargs):
        return self.observation, {}

    def step(self, action):
        self.actions.append(np.asarray(action))
        return self.observation, 0.0, False, False, {}


def test_the_egocentric_observation_is_the_world_seen_from_the_capsule():
    example = _example()
    q = _quaternion([1.0, -2.0, 0.5], 1.1)
    R_WB = example.rotation_from_quaternion(q)
    # an independent rotation: Rodrigues' formula
    k = np.array([1.0, -2.0, 0.5]) / np.linalg.norm([1.0, -2.0, 0.5])
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    assert np.allclose(R_WB, np.eye(3) + np.sin(1.1) * K + (1 - np.cos(1.1)) * K @ K)
    p_WB, v_WB, w_WB = np.array([0.1, 0.2, 0.05]), np.array([0.004, -0.002, 0.001]), \
        np.array([0.3, 0.0, -0.2])
    p_WE, m_W = np.array([0.12, 0.25, 0.2]), np.array([0.0, 0.6, 0.8])
    truth = np.concatenate([q, p_WB, w_WB, v_WB]).astype(np.float32)
    stub = _Stub({"truth": truth, "epm": np.concatenate([p_WE, m_W]).astype(np.float32)})
    env = example.Egocentric(gymnasium.Wrapper(stub))
    observation, _ = env.reset()
    assert observation.shape == (15,) and env.observation_space.shape == (15,)
    # back to the world: each block, turned by R_WB, is what it describes
    assert np.allclose(R_WB @ observation[0:3] * example.OFFSET_SCALE, p_WE - p_WB, atol=1e-6)
    assert np.allclose(R_WB @ observation[3:6], m_W, atol=1e-6)
    assert np.allclose(R_WB @ observation[6:9] * example.SPEED_SCALE, v_WB, atol=1e-8)
    assert np.allclose(R_WB @ observation[9:12] * example.TURN_SCALE, w_WB, atol=1e-6)
    assert np.allclose(R_WB @ observation[12:15], [0, 0, -1], atol=1e-6)


def test_the_egocentric_action_moves_the_epm_along_the_capsule():
    example = _example()
    q = _quaternion([0.0, 1.0, 0.0], np.pi / 2)     # the capsule's axis (B z) along world +x
    truth = np.concatenate([q, np.zeros(9)]).astype(np.float32)
    stub = _Stub({"truth": truth, "epm": np.zeros(6, np.float32)})
    env = example.EgocentricAction(stub)
    env.reset()
    env.step(np.array([0.0, 0.0, 1.0, 0.0, 0.5, 0.0]))
    assert np.allclose(stub.actions[-1], [1.0, 0.0, 0.0, 0.0, 0.5, 0.0], atol=1e-6)


@pytest.mark.slow
def test_a_short_training_writes_its_curve_and_a_policy_that_acts_as_skrl_s(tmp_path):
    pytest.importorskip("skrl", reason="the learn extra (pip install -e '.[learn]')")
    out = tmp_path / "ppo"
    result = subprocess.run(
        [sys.executable, str(REPO / "examples" / "gym_train_ppo.py"), "--steps", "300",
         "--envs", "1", "--rollouts", "100", "--episode-seconds", "5", "--out", str(out)],
        capture_output=True, text=True, timeout=600, cwd=REPO,
        env=dict(os.environ, PYTHONPATH=str(REPO)))
    assert result.returncode == 0, result.stderr[-3000:]
    with open(out / "curve.csv") as f:
        rows = list(csv.DictReader(f))
    # 300 steps of 50-step episodes: six episodes, the steps counted as they went
    assert len(rows) >= 5
    assert [int(r["env_steps"]) for r in rows] == sorted(int(r["env_steps"]) for r in rows)
    assert all(np.isfinite(float(r["return"])) for r in rows)
    # the export checked the NumPy policy against skrl's mean action (it raises otherwise);
    # here, that it loads and acts within the action's bounds
    policy = _example().MeanPolicy(out / "policy.npz")
    action = policy(np.zeros(15))
    assert action.shape == (3,) and np.all(np.abs(action) <= 1.0)


def test_without_turning_the_action_is_the_move_alone():
    example = _example()
    q = _quaternion([1.0, 0.0, 0.0], -np.pi / 2)    # the capsule's axis (B z) along world +y
    truth = np.concatenate([q, np.zeros(9)]).astype(np.float32)
    stub = _Stub({"truth": truth, "epm": np.zeros(6, np.float32)})
    env = example.EgocentricAction(stub, turn=False)
    assert env.action_space.shape == (3,)
    env.reset()
    env.step(np.array([0.0, 0.0, 1.0]))
    assert np.allclose(stub.actions[-1], [0.0, 1.0, 0.0, 0.0, 0.0, 0.0], atol=1e-6)
