"""Trains a small navigation policy with PPO (skrl, JAX backend) in the Gymnasium environment,
and scores it against the lumen follower on colons it never saw.

    pip install -e '.[learn]'        # skrl, JAX (CPU), flax, optax
    .venv/bin/python examples/gym_train_ppo.py --residual --control-period 0.5 --rollouts 64 \
        --minutes 25 --envs 2 --out runs/ppo
    .venv/bin/python examples/gym_train_ppo.py --evaluate runs/ppo --plot runs/ppo/curve.png

The task is the environment's own (capsule_drake/ColonNavigation-v0: its reward is 1 per cm
advanced along the centreline, less the time in contact with the wall and the contact load
above 0.5 N), in episodes of `--episode-seconds` simulated seconds (default 30) on the
benchmark's colons 0-9, one action every `--control-period` s (the environment's step,
default 0.1). The policy is privileged, as the follower it is scored against
("autonomy-truth", which steers by the lumen's truth on the capsule's true pose): it observes
the capsule's true pose and the EPM's, both in the capsule's frame (`Egocentric`), and its
action is the EPM's move in the capsule's frame too (`EgocentricAction`; with `--turn`, the
turn of its moment as well), so that what it learns does not depend on where in the abdomen
the colon runs. With `--residual` the action, times RESIDUAL_SCALE, corrects a scripted move
(FORWARD: the EPM carried along the capsule's axis at full speed) rather than being the
move itself (residual reinforcement learning, Johannink et al. 2019). PPO (Schulman et al.
2017) as skrl implements it, 2 x 64 tanh networks; nothing of it was tuned on the held-out
colons.

What it writes in `--out`: `curve.csv` (each finished training episode: the environment
steps taken by then over all workers, wall time, colon, return, advance in cm),
`policy.npz` (the trained mean-action network's weights and the observation scaler, enough
to act without skrl), `config.json` (the command's settings). `--evaluate DIR` runs the
trained policy (its mean action), the scripted move alone and the follower on the held-out
colons (`--held-out`, default 10-19) for the same simulated seconds and writes
`evaluation.csv` beside it: per colon and driver, the furthest advance (cm), the time in
contact (s) and the peak contact load (N); `--plot PNG` draws the curve and those advances.

Training runs `--envs` worker processes (gymnasium's AsyncVectorEnv, spawned), each keeping
its colons' diagrams built across resets (the environment's cache). `--steps N` stops after N
environment steps instead of `--minutes` (the test runs a few hundred).
"""

import argparse
import csv
import json
import math
import os
import sys
import time

import gymnasium
import numpy as np

from capsule_drake.capsule.model import rotation_from_quaternion

ENV_ID = "capsule_drake:capsule_drake/ColonNavigation-v0"
# Scales of the egocentric observation: the EPM's offset (m), the capsule's speed (m/s) and
# turn rate (rad/s), so that each feature is of order 1 (the observation scaler does the rest).
OFFSET_SCALE = 0.1
SPEED_SCALE = 0.01
TURN_SCALE = 1.0


class Egocentric(gymnasium.ObservationWrapper):
    """The capsule's and the EPM's poses seen from the capsule (B: +z its axis, forward):
    the EPM's centre relative to the capsule's (/ OFFSET_SCALE), its moment's direction, the
    capsule's velocity (/ SPEED_SCALE) and turn rate (/ TURN_SCALE), and the direction of
    gravity, all in B: 15 numbers. Needs the observations "truth" and "epm"."""

    def __init__(self, env):
        super().__init__(env)
        self.observation_space = gymnasium.spaces.Box(-np.inf, np.inf, (15,), np.float32)

    def observation(self, observation):
        truth = observation["truth"].astype(float)
        epm = observation["epm"].astype(float)
        R_WB = rotation_from_quaternion(truth[:4])
        to_B = R_WB.T
        return np.concatenate([
            to_B @ (epm[:3] - truth[4:7]) / OFFSET_SCALE,
            to_B @ epm[3:6],
            to_B @ truth[10:13] / SPEED_SCALE,
            to_B @ truth[7:10] / TURN_SCALE,
            to_B @ np.array([0.0, 0.0, -1.0]),
        ]).astype(np.float32)


class EgocentricAction(gymnasium.Wrapper):
    """The action's move [0:3] and turn [3:6] given in the capsule's frame, turned into the
    world's for the environment (the bounds per component are the environment's: a full
    action along a diagonal of B is clipped component by component in W). With
    `turn=False` the action is the move alone (3,), and the EPM's moment keeps its direction
    (the Default drag's way: the magnet carried, not turned)."""

    def __init__(self, env, turn: bool = True, base=None, residual_scale: float = 1.0):
        super().__init__(env)
        self._R_WB = np.eye(3)
        self._turn = turn
        # Residual learning: the policy's action, times residual_scale, is added to a
        # scripted action `base` (in B) before it is clipped to the bounds.
        self._base = None if base is None else np.asarray(base, dtype=float)
        self._scale = float(residual_scale)
        if not turn:
            self.action_space = gymnasium.spaces.Box(-1.0, 1.0, (3,), np.float32)

    def _remember(self, observation):
        self._R_WB = rotation_from_quaternion(observation["truth"][:4])

    def reset(self, **kwargs):
        observation, info = self.env.reset(**kwargs)
        self._remember(observation)
        return observation, info

    def step(self, action):
        action = np.asarray(action, dtype=float)
        if self._base is not None:
            action = np.clip(self._base + self._scale * action, -1.0, 1.0)
        turn = self._R_WB @ action[3:6] if self._turn else np.zeros(3)
        world = np.concatenate([self._R_WB @ action[:3], turn])
        observation, reward, terminated, truncated, info = self.env.step(
            np.clip(world, -1.0, 1.0).astype(np.float32))
        self._remember(observation)
        return observation, reward, terminated, truncated, info


RESIDUAL_SCALE = 0.5
"""With --residual: the policy's share of the action, beside the scripted forward move."""
FORWARD = np.array([0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
"""The scripted move, an egocentric action: the EPM carried along the capsule's axis at full
speed, its moment left as it is."""


def make_env(colons=tuple(range(10)), episode_seconds: float = 30.0, turn: bool = False,
             residual: bool = False, control_period: float = 0.1):
    """The training environment: the navigation task on `colons`, `episode_seconds` long,
    observed and driven from the capsule's frame (the EPM moved only, unless `turn`); with
    `residual`, the policy's action is a correction (x RESIDUAL_SCALE) to FORWARD."""
    env = gymnasium.make(ENV_ID, observations=("epm", "truth"), colons=tuple(colons),
                         max_episode_seconds=float(episode_seconds),
                         control_period=float(control_period))
    base = None
    if residual:
        base = FORWARD if turn else FORWARD[:3]
    return Egocentric(EgocentricAction(env, turn, base, RESIDUAL_SCALE))


class _Factory:
    """A picklable environment factory for the spawned workers."""

    def __init__(self, colons, episode_seconds, turn, residual, control_period):
        self.colons, self.episode_seconds = tuple(colons), episode_seconds
        self.turn, self.residual, self.control_period = turn, residual, control_period

    def __call__(self):
        return make_env(self.colons, self.episode_seconds, self.turn, self.residual,
                        self.control_period)


class LearningCurve(gymnasium.vector.VectorWrapper):
    """Records each finished episode of a vector environment (autoreset in the same step):
    the steps taken so far over all its environments, the wall time, the colon, the return
    and the advance (cm); appended to `path` as it goes (a stopped run keeps its curve)."""

    FIELDS = ("env_steps", "wall_s", "colon", "return", "advance_cm", "ended")

    def __init__(self, env, path):
        super().__init__(env)
        self.steps = 0
        self.start = time.perf_counter()
        self.returns = np.zeros(env.num_envs)
        self.rows = []
        self._file = open(path, "w", newline="")
        self._writer = csv.DictWriter(self._file, self.FIELDS)
        self._writer.writeheader()

    def step(self, actions):
        observation, reward, terminated, truncated, info = self.env.step(actions)
        self.steps += self.num_envs
        self.returns += reward
        for i in np.flatnonzero(np.logical_or(terminated, truncated)):
            final = info["final_info"]
            row = {"env_steps": self.steps,
                   "wall_s": round(time.perf_counter() - self.start, 1),
                   "colon": int(final["colon_seed"][i]),
                   "return": round(float(self.returns[i]), 3),
                   "advance_cm": round(100.0 * float(final["progress"][i]), 2),
                   "ended": str(final["ended"][i])}
            self.rows.append(row)
            self._writer.writerow(row)
            self._file.flush()
            self.returns[i] = 0.0
        return observation, reward, terminated, truncated, info

    def close(self, **kwargs):
        self._file.close()
        return super().close(**kwargs)


def _ppo(env, seed: int, rollouts: int):
    """skrl's PPO for `env` (a skrl-wrapped environment): a Gaussian policy and a value
    network, each 2 x 64 tanh, observations and values standardised as they run."""
    from skrl.agents.jax.ppo import PPO, PPO_CFG
    from skrl.memories.jax import RandomMemory
    from skrl.resources.preprocessors.jax import RunningStandardScaler
    from skrl.utils import set_seed
    from skrl.utils.model_instantiators.jax import deterministic_model, gaussian_model

    set_seed(seed)
    layers = [{"name": "net", "input": "OBSERVATIONS", "layers": [64, 64],
               "activations": "tanh"}]
    models = {
        "policy": gaussian_model(observation_space=env.observation_space,
                                 action_space=env.action_space, device=env.device,
                                 clip_actions=True, initial_log_std=-0.5,
                                 network=layers, output="ACTIONS"),
        "value": deterministic_model(observation_space=env.observation_space,
                                     action_space=env.action_space, device=env.device,
                                     network=layers, output="ONE"),
    }
    for model in models.values():
        model.init_state_dict(role="")
    cfg = PPO_CFG(rollouts=rollouts, learning_epochs=8, mini_batches=4,
                  discount_factor=0.99, gae_lambda=0.95, learning_rate=3e-4,
                  ratio_clip=0.2, value_clip=0.2, entropy_loss_scale=0.0,
                  value_loss_scale=0.5, grad_norm_clip=0.5, time_limit_bootstrap=True,
                  observation_preprocessor=RunningStandardScaler,
                  observation_preprocessor_kwargs={"size": env.observation_space,
                                                   "device": env.device},
                  value_preprocessor=RunningStandardScaler,
                  value_preprocessor_kwargs={"size": 1, "device": env.device})
    cfg.experiment.write_interval = 0
    cfg.experiment.checkpoint_interval = 0
    memory = RandomMemory(memory_size=rollouts, num_envs=env.num_envs, device=env.device)
    return PPO(models=models, memory=memory, observation_space=env.observation_space,
               action_space=env.action_space, device=env.device, cfg=cfg)


def _flat_params(tree, prefix=""):
    """A flax parameter tree as {"a/b/kernel": array}."""
    out = {}
    for key, value in tree.items():
        name = f"{prefix}/{key}" if prefix else str(key)
        if isinstance(value, dict) or hasattr(value, "items"):
            out.update(_flat_params(value, name))
        else:
            out[name] = np.asarray(value)
    return out


class MeanPolicy:
    """The trained policy's mean action from its saved weights (policy.npz), in NumPy: the
    observation standardised by the scaler's running mean and standard deviation (clipped to
    +-5, as skrl's scaler does), two tanh layers, the linear output clipped to the action's
    bounds."""

    def __init__(self, path):
        data = np.load(path)
        self.mean, self.var = data["obs_mean"], data["obs_var"]
        self.layers = [(data[f"w{i}"], data[f"b{i}"]) for i in range(3)]

    def __call__(self, observation):
        x = np.clip((np.asarray(observation, float) - self.mean)
                    / (np.sqrt(self.var) + 1e-8), -5.0, 5.0)
        for i, (w, b) in enumerate(self.layers):
            x = x @ w + b
            if i < len(self.layers) - 1:
                x = np.tanh(x)
        return np.clip(x, -1.0, 1.0)


def _export(agent, path):
    """The policy network's weights and the observation scaler's statistics to `path`."""
    params = _flat_params(agent.models["policy"].state_dict.params)
    kernels = sorted(k for k in params if k.endswith("kernel"))
    if len(kernels) != 3:
        raise RuntimeError(f"expected 3 dense layers in the policy, found {kernels}")
    arrays = {}
    for i, name in enumerate(kernels):
        arrays[f"w{i}"] = params[name]
        arrays[f"b{i}"] = params[name[:-len("kernel")] + "bias"]
    scaler = agent._observation_preprocessor   # (skrl keeps it on the agent, unexported)
    arrays["obs_mean"] = np.asarray(scaler.running_mean)
    arrays["obs_var"] = np.asarray(scaler.running_variance)
    np.savez(path, **arrays)
    # The NumPy policy acts as skrl's mean action does (checked on scaled random inputs).
    rng = np.random.default_rng(0)
    x = rng.normal(size=(8, len(arrays["obs_mean"]))).astype(np.float32) * 3.0
    _, outputs = agent.models["policy"].act({"observations": scaler(x)}, role="policy")
    skrl_mean = np.clip(np.asarray(outputs["mean_actions"]), -1.0, 1.0)
    ours = np.stack([MeanPolicy(path)(row) for row in x])
    if not np.allclose(ours, skrl_mean, atol=1e-4):
        raise RuntimeError(f"the exported policy differs from skrl's by "
                           f"{np.abs(ours - skrl_mean).max():.2g}")


def train(out, envs: int, minutes: float, steps: int | None, episode_seconds: float,
          seed: int, rollouts: int, turn: bool = False, residual: bool = False,
          control_period: float = 0.1):
    """Trains for `minutes` of wall time (or `steps` environment steps over all workers) and
    writes out/curve.csv, out/policy.npz and out/config.json."""
    from skrl.envs.wrappers.jax import wrap_env
    from skrl.trainers.jax import SequentialTrainer

    os.makedirs(out, exist_ok=True)
    with open(os.path.join(out, "config.json"), "w") as f:
        json.dump({"algorithm": "ppo", "turn": turn, "residual": residual,
                   "control_period": control_period, "envs": envs, "minutes": minutes,
                   "steps": steps, "episode_seconds": episode_seconds, "seed": seed,
                   "rollouts": rollouts,
                   "colons": list(range(10))}, f, indent=1)
    factory = _Factory(range(10), episode_seconds, turn, residual, control_period)
    vector = gymnasium.vector.AsyncVectorEnv(
        [factory] * envs, context="spawn",
        autoreset_mode=gymnasium.vector.AutoresetMode.SAME_STEP)
    curve = LearningCurve(vector, os.path.join(out, "curve.csv"))
    env = wrap_env(curve, wrapper="gymnasium", verbose=False)
    env._seed = seed   # (skrl's wrapper seeds the vector's first reset from this)
    agent = _ppo(env, seed, rollouts)
    # The trainer counts its own steps (one per vector step); with a time budget it is given
    # more than can fit and stopped at the deadline, after the agent's step that passes it.
    total = steps // envs if steps else 10**9
    deadline = time.perf_counter() + 60.0 * minutes if not steps else math.inf
    trainer = SequentialTrainer(env=env, agents=agent,
                                cfg={"timesteps": total, "headless": True,
                                     "disable_progressbar": True,
                                     "close_environment_at_exit": False})
    original = agent.post_interaction

    def post_interaction(*args, **kwargs):
        original(*args, **kwargs)
        if time.perf_counter() > deadline:
            raise _Deadline

    agent.post_interaction = post_interaction
    try:
        trainer.train()
    except _Deadline:
        pass
    finally:
        _export(agent, os.path.join(out, "policy.npz"))
        curve.close()
    return curve.rows


class _Deadline(Exception):
    """Training's time budget is spent."""


def _episode(env, act, seed: int):
    """One episode of `env` (an Egocentric environment) driven by `act`; (the furthest advance
    in cm, as the benchmark's progress_cm, time in contact in s, peak contact load in N, how
    it ended)."""
    observation, info = env.reset(seed=seed)
    contact, peak, furthest = 0.0, 0.0, 0.0
    while True:
        observation, _, terminated, truncated, info = env.step(act(observation))
        contact += info["wall_contact_time"]
        peak = max(peak, info["peak_contact_load"])
        furthest = max(furthest, info["progress"])
        if terminated or truncated:
            return 100.0 * furthest, contact, peak, info["ended"]


def evaluate(out, held_out, episode_seconds: float):
    """The trained policy, the scripted FORWARD move and the follower ("autonomy-truth") on the
    held-out colons, each for `episode_seconds`; writes out/evaluation.csv and returns its
    rows."""
    from capsule_drake.app.benchmark import Task, run_task

    policy = MeanPolicy(os.path.join(out, "policy.npz"))
    with open(os.path.join(out, "config.json")) as f:
        config = json.load(f)
    turn, residual = config.get("turn", False), config.get("residual", False)
    period = config.get("control_period", 0.1)
    size = 6 if turn else 3
    # in the residual form, the scripted move is the environment's own: its policy acts 0
    scripted = np.zeros(size) if residual else FORWARD[:size]
    rows = []
    for colon in held_out:
        env = make_env((colon,), episode_seconds, turn, residual, period)
        for driver, act in (("trained", policy), ("forward", lambda o: scripted)):
            advance, contact, peak, ended = _episode(env, act, seed=0)
            rows.append({"colon": colon, "driver": driver, "advance_cm": round(advance, 2),
                         "contact_s": round(contact, 2), "peak_load_N": round(peak, 3),
                         "ended": ended})
        env.close()
        follower = run_task(Task("autonomy-truth", colon, duration=episode_seconds))["row"]
        rows.append({"colon": colon, "driver": "follower",
                     "advance_cm": follower["progress_cm"],
                     "contact_s": follower["wall_contact_s"],
                     "peak_load_N": follower["peak_contact_force_N"],
                     "ended": follower["status"]})
        for row in rows[-3:]:
            print(", ".join(f"{k} {v}" for k, v in row.items()), flush=True)
    with open(os.path.join(out, "evaluation.csv"), "w", newline="") as f:
        writer = csv.DictWriter(f, list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    return rows


def plot(out, path):
    """The learning curve (out/curve.csv: each episode's return and advance against the
    environment steps, with their running median over 15 episodes) and, when out/evaluation.csv
    exists, the held-out colons' advance for the policy and the follower; saved to `path`."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    with open(os.path.join(out, "curve.csv")) as f:
        rows = list(csv.DictReader(f))
    steps = np.array([int(r["env_steps"]) for r in rows])
    evaluation = os.path.join(out, "evaluation.csv")
    panels = 3 if os.path.exists(evaluation) else 2
    fig, axes = plt.subplots(1, panels, figsize=(4.2 * panels, 3.4))
    for ax, key, label in ((axes[0], "return", "episode return"),
                           (axes[1], "advance_cm", "advance in the episode (cm)")):
        values = np.array([float(r[key]) for r in rows])
        ax.plot(steps, values, ".", color="0.65", ms=3, label="episodes")
        window = 15
        if len(values) >= window:
            median = [np.median(values[max(0, i - window + 1):i + 1])
                      for i in range(len(values))]
            ax.plot(steps, median, color="C0", label=f"running median ({window})")
        ax.set_xlabel("environment steps (all workers)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    if panels == 3:
        with open(evaluation) as f:
            scored = list(csv.DictReader(f))
        colons = sorted({int(r["colon"]) for r in scored})
        labels = {"trained": "trained policy", "forward": "scripted: EPM along the axis",
                  "follower": "lumen follower"}
        for k, driver in enumerate(labels):
            advance = [next(float(r["advance_cm"]) for r in scored
                            if int(r["colon"]) == c and r["driver"] == driver)
                       for c in colons]
            axes[2].bar(np.arange(len(colons)) + 0.27 * (k - 1), advance, 0.27,
                        label=labels[driver])
        axes[2].set_xticks(range(len(colons)), [str(c) for c in colons])
        axes[2].set_xlabel("held-out colon")
        axes[2].set_ylabel("advance (cm)")
        axes[2].set_ylim(0, 1.45 * max(float(r["advance_cm"]) for r in scored))
        axes[2].legend(fontsize=8, loc="upper left")
        axes[2].grid(alpha=0.3, axis="y")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def _colons(text):
    if "-" in text:
        lo, hi = text.split("-")
        return list(range(int(lo), int(hi) + 1))
    return [int(c) for c in text.split(",")]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="runs/ppo", help="directory for the curve and policy")
    parser.add_argument("--envs", type=int, default=2, help="worker processes")
    parser.add_argument("--minutes", type=float, default=25.0, help="training's wall time")
    parser.add_argument("--steps", type=int, default=None,
                        help="environment steps (over all workers) instead of --minutes")
    parser.add_argument("--episode-seconds", type=float, default=30.0)
    parser.add_argument("--rollouts", type=int, default=128,
                        help="steps per worker between PPO updates")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--turn", action="store_true",
                        help="the policy turns the EPM's moment too (6 actions, not 3)")
    parser.add_argument("--control-period", type=float, default=0.1,
                        help="simulated seconds per action (the environment's step)")
    parser.add_argument("--residual", action="store_true",
                        help="the policy learns a correction to the scripted forward move")
    parser.add_argument("--evaluate", metavar="DIR", default=None,
                        help="evaluate the policy trained in DIR instead of training")
    parser.add_argument("--held-out", default="10-19", help="colons to evaluate on")
    parser.add_argument("--plot", metavar="PNG", default=None,
                        help="with --evaluate (or after training): draw the curve to PNG")
    args = parser.parse_args(argv)
    try:
        import skrl  # noqa: F401
        import jax  # noqa: F401
    except ImportError as error:
        sys.exit(f"gym_train_ppo: {error.name} is missing: pip install -e '.[learn]'")
    if args.evaluate:
        if not (args.plot and os.path.exists(os.path.join(args.evaluate, "evaluation.csv"))):
            evaluate(args.evaluate, _colons(args.held_out), args.episode_seconds)
        if args.plot:
            plot(args.evaluate, args.plot)
        return
    try:
        rows = train(args.out, args.envs, args.minutes, args.steps, args.episode_seconds,
                     args.seed, args.rollouts, args.turn, args.residual, args.control_period)
    except KeyboardInterrupt:   # train() has written the curve so far and the policy
        sys.exit(f"gym_train_ppo: interrupted; the curve and the policy so far are in "
                 f"{args.out}")
    print(f"{len(rows)} episodes; curve in {os.path.join(args.out, 'curve.csv')}")
    if args.plot:
        plot(args.out, args.plot)


if __name__ == "__main__":
    main()
