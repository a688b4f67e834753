"""The race environment under gymnasium's API: `RaceVecEnv`, many environments stepped in
parallel by the Rust core (the interpreter's lock released while they step), and `RaceEnv`,
one environment for `gymnasium.make("dronerace/Race-v0", track=...)`.
"""

import numpy as np
import gymnasium
from gymnasium import spaces
from gymnasium.vector import AutoresetMode
from gymnasium.vector.utils import batch_space

from dronerace import _core

def _spaces(core, observation):
    """The single environment's observation and action spaces."""
    state = spaces.Box(-np.inf, np.inf, shape=(core.observation_dim,), dtype=np.float32)
    if observation == "vision":
        side = _core.IMAGE_SIDE
        image = spaces.Box(0, 255, shape=(1, side, side), dtype=np.uint8)
        observation_space = spaces.Dict({"image": image, "state": state})
    else:
        observation_space = state
    action_space = spaces.Box(-1.0, 1.0, shape=(_core.ACTION_DIM,), dtype=np.float32)
    return observation_space, action_space


def _track_list(tracks):
    if tracks is None or isinstance(tracks, list):
        return tracks
    if isinstance(tracks, (str, _core.Track)) or hasattr(tracks, "__fspath__"):
        return [tracks]
    return list(tracks)


def _actions(actions, num_envs):
    """Actions as the core reads them: C-contiguous float32, one row per environment."""
    array = np.ascontiguousarray(actions, dtype=np.float32)
    if array.ndim == 1 and num_envs == 1:
        array = array.reshape(1, -1)
    return array


class RaceVecEnv(gymnasium.vector.VectorEnv):
    """`num_envs` drone-racing environments, stepped in parallel in Rust.

    Args:
        num_envs: environments.
        tracks: a track or a list (each a `dronerace.Track`, a library name such as "Figure8",
            or a track file or directory), cycled over the environments; `None` (the default):
            tracks of the informed generator, drawn and switched by the task controller, as the
            thesis' generalist trains.
        seed: seed of the first `reset()` (tracks, randomisation, start perturbations).
        switching: "adaptive" (the thesis' switching by reward flatness), "random" or "none";
            default adaptive for generated tracks, none for given ones.
        observation: "state" (the state-based agent's numbers, what `policies/generalist.bin`
            reads) or "vision" (a dict of the 84x84 camera image and the 40 state numbers).
        rollout_steps: steps between the task controller's switching decisions (training's
            rollout length).
        randomize: False flies the nominal vehicle from SPEC §9's perturbed starts (evaluation,
            with SPEC's 0.15 m collision sphere; training's is 0.25 m).
        max_episode_steps: episode length (default 1,500 steps = 30 s at 50 Hz).
        switch_window, switch_alpha, switch_probability: SPEC §8's window l (rollouts), sensitivity
            α of the adaptive policy, and the random policy's switch probability per rollout.
        disturbance: SPEC §13's disturbances as a dict, e.g. {"wind_speed": 3.0} (mean wind with
            gusts), {"noise": 2.0, "dropout": 0.05}, {"latency_ms": 20}, {"thrust_loss": 0.1,
            "thrust_loss_motor": 0}; None: the nominal world.

    Autoreset is gymnasium's default (next step): the step that ends an episode returns its last
    observation; the next step ignores that environment's action and returns the first
    observation of a new episode, with reward 0. A task switch ends an episode as `truncated`
    (outcome "track_switch"). The returned observation, reward, termination and truncation
    arrays are filled in place by every step: copy what you keep. An array you make read-only
    (or resize) is left as it is, and the next step returns a fresh one in its place.

    `infos` holds `laps` and `target_gate` for every environment and, where an episode ended,
    `episode` with its return `r`, length `l`, `laps`, `gates_passed`, `fastest_lap` (s, NaN
    without a lap), `outcome` (crash_ground, crash_ceiling, crash_wall, crash_gate, time_limit or
    track_switch) and `crash_gate` (-1 unless a gate's frame), masked by `_episode`.
    """

    metadata = {"autoreset_mode": AutoresetMode.NEXT_STEP, "render_modes": []}

    def __init__(self, num_envs, tracks=None, seed=0, switching=None, observation="state", rollout_steps=250,
                 randomize=True, max_episode_steps=None, switch_window=600, switch_alpha=1000.0, switch_probability=1.616e-3,
                 disturbance=None):
        self._core = _core.VecEnv(num_envs, _track_list(tracks), seed=seed, switching=switching, observation=observation,
                                  rollout_steps=rollout_steps, randomize=randomize, max_episode_steps=max_episode_steps,
                                  switch_window=switch_window, switch_alpha=switch_alpha, switch_probability=switch_probability,
                                  disturbance=disturbance)
        self.num_envs = num_envs
        self.single_observation_space, self.single_action_space = _spaces(self._core, observation)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self.render_mode = None
        self._vision = observation == "vision"

    def reset(self, *, seed=None, options=None):
        """Starts every environment afresh; with `seed`, exactly as a new environment of that
        seed (an int; a list of seeds is not supported: environment i runs on stream i of one
        seed)."""
        if seed is not None and not isinstance(seed, (int, np.integer)):
            raise TypeError(f"seed: one int for all environments (environment i uses stream i), not {seed!r}")
        # The core first: it refuses a seed outside 0..2**64 - 1 with a ValueError naming it.
        infos = self._core.reset(None if seed is None else int(seed))
        if seed is not None:
            super().reset(seed=int(seed))
        return self._observations(), infos

    def step(self, actions):
        """Steps every environment with its row of `actions` (num_envs x 4, in [-1, 1])."""
        rewards, terminations, truncations, infos = self._core.step(_actions(actions, self.num_envs))
        return self._observations(), rewards, terminations, truncations, infos

    def _observations(self):
        """The core's observation arrays, filled in place at every step (asked for each time:
        the core replaces one the user made read-only or resized)."""
        if self._vision:
            return {"image": self._core.images, "state": self._core.observations}
        return self._core.observations

    def tracks(self):
        """The track each environment flies now."""
        return self._core.tracks()

    def states(self):
        """Each environment's body state now, num_envs x 13 float64: position, velocity (world),
        orientation (w, x, y, z; body to world), angular velocity (body): what `Racer` takes."""
        return self._core.states()

    @property
    def switches(self):
        """Task switches since the last seeded reset."""
        return self._core.switches


class RaceEnv(gymnasium.Env):
    """One drone-racing environment on one track: `gymnasium.make("dronerace/Race-v0",
    track="Figure8")`. The arguments are `RaceVecEnv`'s for one environment; `track` is one
    track (library name, file or `dronerace.Track`; default Figure8). Observations are copies.
    """

    metadata = {"render_modes": []}

    def __init__(self, track="Figure8", seed=0, switching="none", observation="state", randomize=True,
                 max_episode_steps=None, render_mode=None, disturbance=None):
        if render_mode is not None:
            raise ValueError(f"render_mode: {render_mode!r}; this environment does not render (see `dronerace sim render`)")
        self._envs = RaceVecEnv(1, [track], seed=seed, switching=switching, observation=observation, randomize=randomize,
                                max_episode_steps=max_episode_steps, disturbance=disturbance)
        self.observation_space = self._envs.single_observation_space
        self.action_space = self._envs.single_action_space
        self.render_mode = None

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        obs, infos = self._envs.reset(seed=seed)
        return self._first(obs), self._unbatch(infos)

    def step(self, action):
        obs, rewards, terminations, truncations, infos = self._envs.step(np.asarray(action, dtype=np.float32).reshape(1, -1))
        return self._first(obs), float(rewards[0]), bool(terminations[0]), bool(truncations[0]), self._unbatch(infos)

    @staticmethod
    def _first(obs):
        if isinstance(obs, dict):
            return {key: value[0].copy() for key, value in obs.items()}
        return obs[0].copy()

    @staticmethod
    def _unbatch(infos):
        out = {"laps": int(infos["laps"][0]), "target_gate": int(infos["target_gate"][0])}
        if "episode" in infos and infos["_episode"][0]:
            out["episode"] = {key: value[0] for key, value in infos["episode"].items()}
        return out
