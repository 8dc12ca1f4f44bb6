"""Evaluates two policies in the Gymnasium environment capsule_drake/ColonNavigation-v0.

    python examples/gym_evaluate.py --episodes 3 --steps 600

- random: actions drawn uniformly from the action space;
- heuristic: the lumen seen in the camera (the centroid of the darkest pixels, the lumen
  being the dark region the capsule's light does not reach) turned into a world direction
  with the capsule's pose, and the EPM sent, within the step's bounds, where its pull plus
  the capsule's weight is a small force along that direction (above and ahead of the
  capsule; `epm_pose_for_force`), its moment turning the capsule toward it. It uses the
  true pose (the "truth" observation): a privileged baseline.

Prints each episode's return, centreline progress and how it ended, and per policy the
means. Episode k of each policy runs with reset seed `--seed` + k (colon `colons[seed %
len(colons)]`, see the environment's docstring), so both policies meet the same colons.
"""

import argparse
import time

import gymnasium
import numpy as np

import capsule_drake  # noqa: F401  (registers the environment)
from capsule_drake.capsule.model import capsule_model, rotation_from_quaternion
from capsule_drake.control.analysis import epm_pose_for_force
from capsule_drake.app.gym_env import action_toward

# The heuristic's drive force along the lumen (N): the lumen follower's cruise range.
DRIVE_FORCE = 0.03
# Share of the image's in-field pixels taken as the dark region.
DARK_FRACTION = 0.05


class LumenHeuristic:
    """The hand-written policy (module docstring), for an environment observing "camera",
    "epm" and "truth"."""

    def __init__(self, env):
        env = env.unwrapped
        self.env = env
        model = capsule_model()
        self.R_BC = model.X_BC.rotation().matrix()
        self.p_BM = model.X_BM.translation()
        self.weight = model.mass * 9.81
        self.moments = (env.scenario.epm.magnet.moment(), env.scenario.capsule.ipm.moment())
        rays, in_field = env.lens.pixel_rays()
        self.rays, self.in_field = rays, in_field

    def lumen_ray(self, image):
        """Unit ray (camera frame) to the centroid of the darkest in-field pixels."""
        gray = image.astype(float).mean(axis=2)
        values = gray[self.in_field]
        dark = self.in_field & (gray <= np.quantile(values, DARK_FRACTION))
        ray = self.rays[dark].mean(axis=0)
        return ray / np.linalg.norm(ray)

    def __call__(self, obs):
        state = obs["truth"].astype(float)
        R_WB = rotation_from_quaternion(state[:4])
        R_WC = R_WB @ self.R_BC
        heading = R_WC @ self.lumen_ray(obs["camera"])
        p_WM = state[4:7] + R_WB @ self.p_BM
        force = DRIVE_FORCE * heading + np.array([0.0, 0.0, self.weight])
        p, m, _ = epm_pose_for_force(p_WM, heading, force, *self.moments)
        return action_toward(self.env.epm_command, np.concatenate([p, m]),
                             self.env.max_move, self.env.max_turn)


def evaluate(env, policy, episodes: int, steps: int, seed: int, label: str) -> dict:
    returns, progress = [], []
    for k in range(episodes):
        obs, info = env.reset(seed=seed + k)
        total, start = 0.0, time.perf_counter()
        for _ in range(steps):
            obs, reward, terminated, truncated, info = env.step(policy(obs))
            total += reward
            if terminated or truncated:
                break
        returns.append(total)
        progress.append(info["progress"])
        print(f"{label:9s} episode {k}: colon {info['colon_seed']}, return {total:8.2f}, "
              f"progress {100 * info['progress']:6.1f} cm ({info['progress_fraction']:.3f} "
              f"of the colon), {info['t']:.1f} s simulated in "
              f"{time.perf_counter() - start:.1f} s, ended: {info['ended'] or 'step limit'}"
              + (f" ({info['reason']})" if info["reason"] else ""), flush=True)
    return {"policy": label, "mean_return": float(np.mean(returns)),
            "mean_progress_cm": float(100 * np.mean(progress))}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=3, help="episodes per policy")
    parser.add_argument("--steps", type=int, default=600,
                        help="most steps per episode (0.1 s each)")
    parser.add_argument("--seed", type=int, default=0, help="reset seed of the first episode")
    parser.add_argument("--image-size", type=int, default=64, help="camera image side (px)")
    args = parser.parse_args(argv)
    if args.episodes < 1 or args.steps < 1:
        parser.error("--episodes and --steps must be at least 1")
    env = gymnasium.make("capsule_drake/ColonNavigation-v0",
                         observations=("camera", "epm", "truth"),
                         image_size=args.image_size)
    heuristic = LumenHeuristic(env)
    random_policy = env.action_space
    random_policy.seed(args.seed)
    results = [evaluate(env, lambda obs: random_policy.sample(), args.episodes, args.steps,
                        args.seed, "random"),
               evaluate(env, heuristic, args.episodes, args.steps, args.seed, "heuristic")]
    env.close()
    for r in results:
        print(f"{r['policy']:9s} mean return {r['mean_return']:8.2f}   mean progress "
              f"{r['mean_progress_cm']:6.1f} cm")


if __name__ == "__main__":
    main()
