"""A Gymnasium environment: an agent drives the EPM to take the capsule to the cecum.

    env = gymnasium.make("capsule_drake/ColonNavigation-v0",
                         observations=("camera", "imu", "magnetometer", "epm"))

Registered when `capsule_drake` is imported (or with gymnasium's "module:id" form,
`gymnasium.make("capsule_drake:capsule_drake/ColonNavigation-v0")`). The task is the
navigation benchmark's (app/benchmark/): the capsule starts in the rectum of a
seeded procedural colon (the scenario `Navigation` of diagrams/default.yaml, its
`capsule.start_s`), and the episode ends at the cecum. The agent takes the place of the
benchmark's navigators: the station's EPM driver is `!External`, and every step the
agent's action moves the EPM's command.

Episodes and seeds. `reset(seed=k)` runs colon `colons[k % len(colons)]` (the scenario's
`colon.seed`; `colons` defaults to 0-9, the benchmark's ten colons; pass e.g.
`colons=range(10, 20)` for held-out colons, or `reset(options={"colon": 12})` for one
colon), and seeds the sensors' noise with k (as a run seeds it with the scenario's
`random_seed`: `diagram.SetRandomContext(context, RandomGenerator(k))`; the scenario's own
random_seed is not used). `reset()` without a seed draws k from the environment's
generator, so a sequence of episodes is reproducible from the first seed. A colon's
diagram is built once and kept (the last `max_cached_colons` colons): a reset
re-initialises its context (state, noise, time 0).

Action: `Box(-1, 1, (6,), float32)`, a bounded change of the EPM's command per step:
    [dx, dy, dz] * max_epm_speed * control_period    move of the EPM's centre (world, m)
    [wx, wy, wz] * max_turn_rate * control_period    rotation vector (world, rad) turning
                                                     its moment direction
Moves, not poses: every action, random or learnt, is a small change from where the EPM
is, so no action can fling the magnet across the patient (at the defaults, 3 mm and 5
degrees per 0.1 s step: the lumen follower's 3 cm/s), and "hold still" is the zero action.
A rotation vector rather than yaw and pitch, so the action has no singularity at the
vertical moment (where yaw is undefined); its component along the moment does nothing. The
components are clipped to [-1, 1] (an out-of-bound action is clipped, reported in
`info["action_clipped"]`); a non-finite action or one of the wrong shape is a ValueError.
Within a step the command ramps from the old to the new pose in sub-steps of
`COMMAND_PERIOD` (the follower's 20 Hz), and each sub-step's command is made safe: its
centre is kept in the box `workspace` (over the patient) and then raised, if need be, so
that the magnet is at least the scenario's `epm.clearance` above the skin under it (the
station's EPM guard, epm/guard.py; `info["epm_raised"]`). The action changes the
commanded pose, which the EPM's carrier follows (the kinematic stage at once).

Observations (`observations=` at make time; a `spaces.Dict` of these, float32 but the
camera):
    camera        (S, S, 3) uint8: the capsule camera's latest delivered frame (the
                  scenario's camera with an S x S lens, S = `image_size`, default 64, one
                  frame per step, and the scenario's radio latency)
    imu           (6,) [accel (m/s^2), gyro (rad/s)] in the IMU's frame, its latest sample
    magnetometer  (3,) the magnetometer's field (T), its latest sample
    hall          (3n,) the Hall array's fields (T; capsule.magnetic_array)
    epm           (6,) the EPM's pose [p_WE (m), m_hat_W], which the robot knows
    truth         (13,) the capsule's true state [q_WB wxyz, p_WB, w_WB, v_WB]
Sensor values are clipped to the sensor's full-scale range (as it saturates) and the rest
to the space's bounds. The default, ("imu", "magnetometer", "epm"), renders nothing and
steps fastest; navigating needs the camera (or the truth, for privileged learning).

Reward per step, with the weights of `RewardWeights` (`reward=` at make time):
    progress * ds                     ds: change of the capsule's centreline station (m;
                                      the benchmark's: its centre's closest centreline point)
  - wall_contact * contact_fraction   share of the step with the contact load above the
                                      benchmark's CONTACT_THRESHOLD (0.05 N)
  - force * max(0, peak - force_threshold)   peak contact load in the step (N)
  + cecum                             once, on reaching the cecum
  - guard_stop                        once, when the run guard stops the episode
`info["reward_terms"]` holds the terms, which sum to the reward. The contact load is
sampled every CONTACT_SAMPLE_PERIOD.

Episode end: terminated at the cecum (centreline station within the benchmark's
CECUM_MARGIN of the end), on a run guard stop (io/guard.py: the state stopped being
physical: not finite, too fast, through the wall, out of the colon; the progress term of
the stopping step is 0 when the state diverged, kept when the compliant wall tore), or on an
error of the simulation;
truncated at `max_episode_seconds` of simulated time (default 600 s, the benchmark's).
`info`: t, colon_seed, noise_seed, s, progress (s - s at the start, m), progress_fraction
(the benchmark's "progress": furthest station reached, as a share of the colon from the
start), contact_load (N, now), peak_contact_load (N, in the step), wall_contact_time (s, in
the step), reward_terms, epm_raised, action_clipped, ended ("", "cecum", "guard", "error"
or "time_limit") and reason (one line).

Control period: `control_period` s of simulated time per step (default 0.1 s).
render_mode "rgb_array": `render()` returns the camera's latest frame (the camera is
added if not observed).
"""

import collections
import dataclasses
import gc
import math

import gymnasium
import numpy as np
from gymnasium import spaces

from capsule_drake.epm.guard import floor_guard
from capsule_drake.epm.paths import epm_start
from capsule_drake.epm.poses import stage_to_pose
from capsule_drake.app.run import Run, add_contact_monitor
from capsule_drake.app.benchmark import CECUM_MARGIN, CONTACT_THRESHOLD
from capsule_drake.perception import Lens
from capsule_drake.scenario import load_scenario
from capsule_drake.schema import need_range
from capsule_drake.app.gym_parts import (_ANGULAR_SPEED_BOUND, _POSITION_BOUND, _SPEED_BOUND,
                                         COMMAND_PERIOD, CONTACT_SAMPLE_PERIOD, CONTACT_STATS,
                                         DEFAULT_OBSERVATIONS, DEFAULT_WORKSPACE, ENV_ID,
                                         OBSERVATIONS, ContactStats, RewardWeights,
                                         _colon_seeds, _number, _observation_names,
                                         _workspace, action_toward, check_reward_weights,
                                         rotate)

__all__ = ["ColonNavigationEnv", "ENV_ID", "OBSERVATIONS", "DEFAULT_OBSERVATIONS",
           "RewardWeights", "action_toward", "rotate"]


@dataclasses.dataclass
class _Colon:
    """One colon's run (its built diagram, stepped by the run loop) and what the episode
    needs of it."""

    colon_seed: int
    run: Run
    guard: object            # EpmGuard: the clearance floor
    start_command: np.ndarray
    start_s: float
    monitor: object = None   # the episode's contact monitor and statistics (added to the run)
    stats: object = None

    @property
    def station(self):
        return self.run.station

    @property
    def colon(self):
        return self.run.colon


class ColonNavigationEnv(gymnasium.Env):
    """The capsule's navigation to the cecum as a Gymnasium environment (module docstring).

    Args:
        observations: names from OBSERVATIONS (default DEFAULT_OBSERVATIONS).
        colons: the colon seeds episodes run on (reset seed k -> colons[k % len(colons)]).
        control_period: simulated seconds per step.
        max_episode_seconds: simulated seconds after which an episode is truncated.
        max_epm_speed: largest move of the EPM's centre (m/s; per step: times the period).
        max_turn_rate_deg: largest turn of its moment (deg/s; per step: times the period).
        image_size: side of the camera image (px).
        reward: RewardWeights, or a dict of its fields.
        workspace: ((x, y, z) low, (x, y, z) high), the box (m) the EPM's centre stays in.
        scenario: the named scenario the episodes start from (default "Navigation").
        scenario_file: the file it is in (default diagrams/default.yaml).
        scenario_text: YAML laid over it (e.g. "{contact: {friction: 0.3}}"); the driver
            is always `!External` and the colon's seed the episode's.
        max_cached_colons: colons whose diagrams are kept built.
        render_mode: None or "rgb_array" (the camera's latest frame).

    Attributes (for scripted policies; see examples/gym_evaluate.py): scenario (the
    first colon's Scenario: magnets, capsule, camera), lens (the camera's Lens, or None),
    max_move (m) and max_turn (rad), a full action's move and turn per step; colon (the
    episode's colon), epm_command (the commanded EPM pose [p_WE, m_hat_W]),
    floor_height(x, y, m_hat) (the lowest EPM centre the clearance allows), build_count
    (diagrams built so far), reward_weights.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, observations=DEFAULT_OBSERVATIONS, *, colons=tuple(range(10)),
                 control_period: float = 0.1, max_episode_seconds: float = 600.0,
                 max_epm_speed: float = 0.03, max_turn_rate_deg: float = 50.0,
                 image_size: int = 64, reward=None, workspace=DEFAULT_WORKSPACE,
                 scenario: str = "Navigation", scenario_file=None, scenario_text: str = "",
                 max_cached_colons: int = 4, render_mode: str | None = None):
        super().__init__()
        self._observed = _observation_names(observations)
        self._colons = _colon_seeds(colons)
        need_range(_number(control_period, "control_period"), "control_period",
                   "[0.01, 10]", "s")
        need_range(_number(max_episode_seconds, "max_episode_seconds"),
                   "max_episode_seconds", f"[{control_period}, 1e6]", "s")
        need_range(_number(max_epm_speed, "max_epm_speed"), "max_epm_speed", "(0, 1]", "m/s")
        need_range(_number(max_turn_rate_deg, "max_turn_rate_deg"), "max_turn_rate_deg",
                   "(0, 360]", "deg/s")
        need_range(image_size, "image_size", "[16, 1024]", "px")
        need_range(max_cached_colons, "max_cached_colons", "[1, 64]", "",
                   "each built colon holds its meshes and renderers")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        if isinstance(reward, dict):
            try:
                reward = RewardWeights(**reward)
            except TypeError:
                names = [f.name for f in dataclasses.fields(RewardWeights)]
                unknown = sorted(set(reward) - set(names))
                raise ValueError(f"reward: unknown weight(s) {', '.join(map(str, unknown))}; "
                                 f"the weights are {', '.join(names)}") from None
        self.reward_weights = reward if reward is not None else RewardWeights()
        check_reward_weights(self.reward_weights)
        self._workspace = _workspace(workspace)
        self.render_mode = render_mode
        self.control_period = float(control_period)
        self.max_episode_seconds = float(max_episode_seconds)
        self.max_move = float(max_epm_speed) * self.control_period
        self.max_turn = math.radians(float(max_turn_rate_deg)) * self.control_period
        self._substeps = max(1, int(round(self.control_period / COMMAND_PERIOD)))
        self._steps_per_episode = int(round(self.max_episode_seconds / self.control_period))
        self._image_size = int(image_size)
        self._max_cached = int(max_cached_colons)
        self._camera = "camera" in self._observed or render_mode == "rgb_array"
        self._scenario_source = (scenario_file, scenario)
        self._texts = [self._env_text(scenario_file, scenario), scenario_text]
        # The scenario of the first colon: checks the settings now, and gives the sensors'
        # ranges (the same for every colon).
        self.scenario = self._scenario_for(self._colons[0])
        self.lens = Lens(self.scenario.capsule.camera.lens) if self._camera else None
        self.metadata = dict(self.metadata, render_fps=1.0 / self.control_period)
        self.observation_space = self._observation_space(self.scenario)
        self.action_space = spaces.Box(-1.0, 1.0, shape=(6,), dtype=np.float32)
        self.build_count = 0   # diagrams built (a colon's first episode, or after eviction)
        self._runs: collections.OrderedDict[int, _Colon] = collections.OrderedDict()
        self._run = None
        self._ended = True

    # -- configuration ------------------------------------------------------------------

    def _env_text(self, scenario_file, name) -> str:
        """The YAML the environment lays over the named scenario: the External driver, the
        observed sensors switched on, the camera as observed."""
        base = load_scenario(scenario_file, name)
        capsule = []
        if "imu" in self._observed and base.capsule.imu is None:
            capsule.append("imu: {}")
        if "magnetometer" in self._observed and base.capsule.magnetometer is None:
            capsule.append("magnetometer: {}")
        if "hall" in self._observed and base.capsule.magnetic_array is None:
            capsule.append("magnetic_array: {}")
        if self._camera:
            size = self._image_size
            capsule.append(f"camera: {{fps_mode: fixed, fps: {1.0 / self.control_period!r}, "
                           f"render_depth: false, lens: {{width: {size}, height: {size}}}}}")
        else:  # nothing renders: the camera and what watches it go
            capsule += ["camera: null", "lumen_tracker: null"]
        return f"{{epm: {{driver: !External {{}}}}, capsule: {{{', '.join(capsule)}}}}}"

    def _scenario_for(self, colon_seed: int):
        file, name = self._scenario_source
        return load_scenario(file, name, self._texts + [f"{{colon: {{seed: {colon_seed}}}}}"])

    def _observation_space(self, scenario) -> spaces.Dict:
        capsule = scenario.capsule
        boxes = {}
        for name in self._observed:
            if name == "camera":
                size = self._image_size
                boxes[name] = spaces.Box(0, 255, shape=(size, size, 3), dtype=np.uint8)
                continue
            if name == "imu":
                high = [capsule.imu.accel_range] * 3 + [capsule.imu.gyro_range] * 3
            elif name == "magnetometer":
                high = [capsule.magnetometer.range] * 3
            elif name == "hall":
                high = [capsule.magnetic_array.range] * (3 * len(capsule.magnetic_array.positions))
            elif name == "epm":
                high = [_POSITION_BOUND] * 3 + [1.0] * 3
            else:  # truth
                high = ([1.0] * 4 + [_POSITION_BOUND] * 3 + [_ANGULAR_SPEED_BOUND] * 3
                        + [_SPEED_BOUND] * 3)
            high = np.asarray(high, dtype=np.float32)
            boxes[name] = spaces.Box(-high, high, dtype=np.float32)
        return spaces.Dict(boxes)

    # -- building -----------------------------------------------------------------------

    def _run_for(self, colon_seed: int) -> _Colon:
        """The built diagram of a colon: kept from an earlier episode, or built now."""
        if colon_seed in self._runs:
            self._runs.move_to_end(colon_seed)
            return self._runs[colon_seed]
        if len(self._runs) >= self._max_cached:
            while len(self._runs) >= self._max_cached:
                _, old = self._runs.popitem(last=False)
                old.run.close()
            del old
            # A diagram lives in reference cycles (builder, systems) that only the garbage
            # collector frees: free the evicted one before building the next (a training
            # loop would otherwise hold up to ~20 built colons, GBs with the camera, until
            # Python's own collection came round).
            gc.collect()
        scenario = self._scenario_for(colon_seed)

        added = {}

        def add_contact_stats(builder, station):
            # The environment's own monitor: the run's is not evaluated without its loggers.
            monitor = add_contact_monitor(builder, station, "gym.contact_monitor")
            stats = builder.AddNamedSystem(CONTACT_STATS, ContactStats(CONTACT_SAMPLE_PERIOD,
                                                                       CONTACT_THRESHOLD))
            builder.Connect(monitor.GetOutputPort("contact_load"), stats.get_input_port())
            added.update(monitor=monitor, stats=stats)

        run = Run(scenario, extend=add_contact_stats, log=False)
        epm = scenario.epm
        start = stage_to_pose(epm_start(epm, run.colon, scenario.capsule.start_s))
        entry = _Colon(colon_seed, run, floor_guard(run.colon.abdomen, epm.magnet,
                                                    epm.clearance),
                       start, scenario.capsule.start_s, **added)
        self._runs[colon_seed] = entry
        self.build_count += 1
        return entry

    # -- the Gymnasium interface --------------------------------------------------------

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        episode = int(seed) if seed is not None else int(self.np_random.integers(0, 2**32))
        colon_seed = self._colons[episode % len(self._colons)]
        if options and "colon" in options:
            colon_seed = _colon_seeds([options["colon"]])[0]
        # Let go of the last episode's run first: an evicted colon must have no holder left.
        self._run = self._station_context = self._stats_context = None
        run = self._run_for(colon_seed)
        self._run = run
        self._noise_seed = episode % 2**32
        run.run.reset(self._noise_seed)
        context = run.run.context
        self._station_context = run.station.GetMyMutableContextFromRoot(context)
        self._stats_context = run.stats.GetMyMutableContextFromRoot(context)
        self._command = self._safe(run.start_command[:3], run.start_command[3:])[:2]
        self._set_command(np.concatenate(self._command))
        run.run.initialize()
        ending = run.run.advance_to(0.0)   # the sensors' first samples (events at t = 0)
        if ending is not None and ending.status == "error":
            raise RuntimeError(f"colon {colon_seed}: {ending.text}")
        self._steps = 0
        self._s = float(run.start_s)
        self._s = self._station_of(self._capsule_state())
        self._furthest = self._s
        self._s0 = self._s
        self._ended = False
        return self._observe(), self._info(self._zero_terms(), 0.0, 0.0, False, False, "", "")

    def step(self, action):
        if self._run is None:
            raise RuntimeError("call reset() before step()")
        if self._ended:
            raise RuntimeError("the episode has ended: call reset() before step()")
        a = np.asarray(action, dtype=float)
        if a.shape != (6,):
            raise ValueError(f"action must have shape (6,), got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"action must be finite, got {a.tolist()}")
        clipped = bool(np.any(np.abs(a) > 1.0))
        a = np.clip(a, -1.0, 1.0)
        p0, m0 = self._command
        move, turn = self.max_move * a[:3], self.max_turn * a[3:]
        self._stats_context.SetDiscreteState(np.zeros(2))
        run = self._run.run
        raised, ended, reason, diverged = False, "", "", False
        for j in range(1, self._substeps + 1):
            f = j / self._substeps
            p, m, up = self._safe(p0 + f * move, rotate(m0, f * turn))
            raised = raised or up
            self._set_command(np.concatenate([p, m]))
            self._command = (p, m)
            t = (self._steps * self._substeps + j) * self.control_period / self._substeps
            ending = run.advance_to(t)
            if ending is not None:
                ended = "error" if ending.status == "error" else "guard"
                reason, diverged = ending.text, ending.status == "diverged"
                break
        self._steps += 1
        w = self.reward_weights
        state = self._capsule_state()
        s = self._s
        if ended == "error" or (ended == "guard" and diverged):
            progress = 0.0   # nothing measured in a diverged state means anything
        else:
            s = self._station_of(state)
            progress = s - self._s
        self._s = s
        self._furthest = max(self._furthest, s)
        peak, contact_time = self._stats_context.get_discrete_state().get_vector().value()
        terms = self._zero_terms()
        terms["progress"] = w.progress * progress
        peak, contact_time = float(peak), float(contact_time)
        terms["wall_contact"] = -w.wall_contact * min(1.0, contact_time / self.control_period)
        terms["force"] = -w.force * max(0.0, peak - w.force_threshold)
        if ended:
            terms["guard_stop"] = -w.guard_stop
        elif s >= self._run.colon.centerline.length - CECUM_MARGIN:
            ended, reason = "cecum", f"reached the cecum at t = {run.time:.3f} s"
            terms["cecum"] = w.cecum
        terminated = bool(ended)
        truncated = not terminated and self._steps >= self._steps_per_episode
        if truncated:
            ended, reason = "time_limit", f"{self.max_episode_seconds:g} s of simulated time"
        self._ended = terminated or truncated
        reward = float(sum(terms.values()))
        info = self._info(terms, peak, contact_time, raised, clipped, ended, reason)
        return self._observe(), reward, terminated, truncated, info

    def render(self):
        if self.render_mode != "rgb_array" or self._run is None:
            return None
        image = self._run.station.GetOutputPort("capsule.camera.rgb_image").Eval(
            self._station_context)
        return np.array(image.data[:, :, :3], dtype=np.uint8)

    def close(self):
        while self._runs:   # (no loop variable left holding a run at the collection)
            self._runs.popitem()[1].run.close()
        self._run = None
        self._station_context = self._stats_context = None
        self._ended = True
        gc.collect()   # the diagrams go now, not at Python's next collection
        super().close()

    # -- the episode: command, outputs, observations, info --------------------------------

    @property
    def colon(self):
        """The current episode's colon (its centreline, wall and abdomen), or None."""
        return self._run.colon if self._run is not None else None

    @property
    def epm_command(self) -> np.ndarray:
        """The EPM's commanded pose [p_WE, m_hat_W] (the actions move it)."""
        return np.concatenate(self._command)

    def floor_height(self, x: float, y: float, m_hat) -> float:
        """The lowest EPM centre height the clearance allows at (x, y) with moment m_hat."""
        return self._run.guard.lowest_centre_height(x, y, np.asarray(m_hat, dtype=float))

    def _safe(self, p, m):
        """(p, m, raised): the command's centre kept in the workspace box, then raised to
        the clearance floor (the station's EPM guard); its moment made unit."""
        low, high = self._workspace
        p = np.clip(np.asarray(p, dtype=float), low, high)
        m = np.asarray(m, dtype=float)
        m = m / np.linalg.norm(m)
        floor = self._run.guard.lowest_centre_height(p[0], p[1], m)
        raised = bool(p[2] < floor)
        if raised:
            p[2] = floor
        return p, m, raised

    def _set_command(self, command):
        self._run.station.GetInputPort("epm.command").FixValue(self._station_context, command)

    def _output(self, name):
        return self._run.station.GetOutputPort(name).Eval(self._station_context)

    def _capsule_state(self) -> np.ndarray:
        return np.array(self._output("capsule.state"), dtype=float)

    def _station_of(self, state) -> float:
        if not np.all(np.isfinite(state[4:7])):
            return self._s
        return float(self._run.colon.centerline.closest(state[4:7])[0])

    def _observe(self) -> dict:
        obs = {}
        for name, box in self.observation_space.spaces.items():
            if name == "camera":
                image = self._output("capsule.camera.rgb_image")
                obs[name] = np.array(image.data[:, :, :3], dtype=np.uint8)
                continue
            if name == "imu":
                value = np.concatenate([self._output("capsule.imu.accel"),
                                        self._output("capsule.imu.gyro")])
            elif name == "magnetometer":
                value = self._output("capsule.magnetometer.B_S")
            elif name == "hall":
                value = self._output("capsule.magnetic_array.B")
            elif name == "epm":
                value = self._output("epm.pose")
            else:
                value = self._output("capsule.state")
            value = np.nan_to_num(np.asarray(value, dtype=np.float32), nan=0.0)
            obs[name] = np.clip(value, box.low, box.high)
        return obs

    @staticmethod
    def _zero_terms() -> dict:
        return {"progress": 0.0, "wall_contact": 0.0, "force": 0.0, "cecum": 0.0,
                "guard_stop": 0.0}

    def _info(self, terms, peak, contact_time, raised, clipped, ended, reason) -> dict:
        run = self._run
        length = run.colon.centerline.length
        load = float(self._output_load())
        return {"t": float(run.run.time),
                "colon_seed": int(run.colon_seed), "noise_seed": int(self._noise_seed),
                "s": float(self._s), "progress": float(self._s - self._s0),
                "progress_fraction": float((self._furthest - self._s0)
                                           / max(length - self._s0, 1e-9)),
                "contact_load": load, "peak_contact_load": max(peak, 0.0),
                "wall_contact_time": contact_time, "reward_terms": dict(terms),
                "epm_raised": bool(raised), "action_clipped": bool(clipped),
                "ended": ended, "reason": reason}

    def _output_load(self) -> float:
        monitor = self._run.monitor
        context = monitor.GetMyContextFromRoot(self._run.run.context)
        load = float(monitor.GetOutputPort("contact_load").Eval(context)[0])
        return load if math.isfinite(load) else 0.0
