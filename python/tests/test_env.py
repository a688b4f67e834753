"""RaceVecEnv and RaceEnv: gymnasium's API, next-step autoreset, seeding, switching and the
errors a wrong call gets."""

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import dronerace


def random_actions(rng, n):
    return rng.uniform(-1.0, 1.0, size=(n, 4)).astype(np.float32)


@pytest.mark.filterwarnings("ignore:.*infinity.*")
@pytest.mark.parametrize("observation", ["state", "vision"])
def test_the_registered_environment_passes_gymnasiums_checker(observation):
    env = gymnasium.make("dronerace/Race-v0", track="Figure8", observation=observation)
    check_env(env.unwrapped)


def test_vector_api_shapes_dtypes_and_spaces():
    envs = dronerace.RaceVecEnv(6, tracks=["Figure8", "BigS"], seed=3)
    assert envs.metadata["autoreset_mode"] == gymnasium.vector.AutoresetMode.NEXT_STEP
    assert envs.single_observation_space.shape == (52,) and envs.single_action_space.shape == (4,)
    obs, infos = envs.reset(seed=3)
    assert obs.shape == (6, 52) and obs.dtype == np.float32 and envs.observation_space.contains(obs)
    assert [t.name for t in envs.tracks()] == ["Figure8", "BigS"] * 3
    obs, rewards, terminations, truncations, infos = envs.step(envs.action_space.sample())
    assert (rewards.shape, rewards.dtype) == ((6,), np.float32)
    assert terminations.dtype == np.bool_ and truncations.dtype == np.bool_
    assert infos["laps"].tolist() == [0] * 6 and infos["_laps"].all()
    assert infos["target_gate"].shape == (6,)


def test_the_same_seed_and_actions_fly_the_same_and_another_seed_does_not():
    def fly(seed):
        envs = dronerace.RaceVecEnv(4, tracks="Kidney", seed=seed)
        rng = np.random.default_rng(0)
        obs, _ = envs.reset(seed=seed)
        observations, rewards = [obs.copy()], []
        for _ in range(200):
            obs, reward, *_ = envs.step(random_actions(rng, 4))
            observations.append(obs.copy())
            rewards.append(reward.copy())
        return np.stack(observations), np.stack(rewards)

    (obs_a, rew_a), (obs_b, rew_b), (obs_c, _) = fly(7), fly(7), fly(8)
    assert np.array_equal(obs_a, obs_b) and np.array_equal(rew_a, rew_b)
    assert not np.array_equal(obs_a, obs_c)


def test_a_noisy_estimate_changes_what_is_observed_not_the_flight_and_bad_disturbances_are_named():
    def fly(disturbance):
        envs = dronerace.RaceVecEnv(2, tracks="Figure8", seed=5, randomize=False, disturbance=disturbance)
        obs, _ = envs.reset(seed=5)
        hover = np.zeros((2, 4), dtype=np.float32)
        seen, rewards = [obs.copy()], []
        for _ in range(20):
            obs, reward, *_ = envs.step(hover)
            seen.append(obs.copy())
            rewards.append(reward.copy())
        return np.stack(seen), np.stack(rewards)

    (nominal, r0), (noisy, r1) = fly(None), fly({"noise": 4.0})
    assert not np.allclose(nominal, noisy), "the estimate has noise"
    # The same actions fly the same states: progress rewards depend on the true state only.
    assert np.allclose(r0, r1, atol=1e-6)
    for bad, name in [({"wind": 3.0}, "wind"), ({"thrust_loss": 1.5}, "thrust_loss"), ({"noise": "x"}, "noise")]:
        with pytest.raises(ValueError, match=name):
            dronerace.RaceVecEnv(1, tracks="Figure8", disturbance=bad)


def test_an_ended_episode_is_reported_then_restarts_at_the_next_step_ignoring_its_action():
    envs = dronerace.RaceVecEnv(8, tracks="Figure8", seed=1)
    obs, _ = envs.reset(seed=1)
    rng = np.random.default_rng(1)
    for _ in range(500):
        obs, rewards, terminations, truncations, infos = envs.step(random_actions(rng, 8))
        if "episode" in infos:
            break
    else:
        pytest.fail("no episode ended in 500 steps of random actions")
    ended = np.flatnonzero(infos["_episode"])
    assert (terminations | truncations)[ended].all()
    episode = infos["episode"]
    assert set(episode["outcome"][ended]) <= {"crash_ground", "crash_ceiling", "crash_wall", "crash_gate", "time_limit"}
    assert (episode["l"][ended] > 0).all()
    last = obs[ended].copy()
    obs, rewards, terminations, truncations, infos = envs.step(np.full((8, 4), 5.0, dtype=np.float32))
    assert (rewards[ended] == 0).all() and not (terminations | truncations)[ended].any()
    assert (infos["laps"][ended] == 0).all() and (infos["target_gate"][ended] == 0).all()
    assert not np.array_equal(obs[ended], last), "a new episode began"


def test_adaptive_switching_gives_new_tracks_and_cuts_the_episode():
    envs = dronerace.RaceVecEnv(4, seed=2, switching="adaptive", rollout_steps=5, switch_window=2, switch_alpha=0.0)
    envs.reset(seed=2)
    before = [t.name for t in envs.tracks()]
    assert all(name.startswith("informed-") for name in before), before
    outcomes = []
    for _ in range(10):
        _, _, _, truncations, infos = envs.step(np.zeros((4, 4), dtype=np.float32))
        if "episode" in infos:
            outcomes += list(infos["episode"]["outcome"][infos["_episode"]])
    assert envs.switches > 0 and "track_switch" in outcomes
    envs.step(np.zeros((4, 4), dtype=np.float32))
    assert [t.name for t in envs.tracks()] != before
    fixed = dronerace.RaceVecEnv(2, tracks="Twist", rollout_steps=1, switch_window=2, switch_alpha=0.0)
    fixed.reset()
    for _ in range(5):
        fixed.step(np.zeros((2, 4), dtype=np.float32))
    assert fixed.switches == 0 and [t.name for t in fixed.tracks()] == ["Twist", "Twist"], "a user's tracks stay"


def test_vision_observations_hold_the_camera_image_and_the_state():
    envs = dronerace.RaceVecEnv(3, tracks="Figure8", observation="vision")
    obs, _ = envs.reset(seed=0)
    assert obs["image"].shape == (3, 1, 84, 84) and obs["image"].dtype == np.uint8
    assert obs["state"].shape == (3, 40) and obs["image"].max() > obs["image"].min()
    assert envs.observation_space.contains(obs)


def test_wrong_calls_raise_exceptions_that_name_the_argument():
    envs = dronerace.RaceVecEnv(3, tracks="Figure8")
    with pytest.raises(RuntimeError, match="reset"):
        envs.step(np.zeros((3, 4), dtype=np.float32))
    envs.reset()
    with pytest.raises(ValueError, match=r"actions: expected shape \(3, 4\), got \[3, 3\]"):
        envs.step(np.zeros((3, 3), dtype=np.float32))
    nan = np.zeros((3, 4), dtype=np.float32)
    nan[1, 2] = np.nan
    with pytest.raises(ValueError, match=r"actions\[1, 2\] is NaN"):
        envs.step(nan)
    with pytest.raises(ValueError, match=r'tracks\[0\]: "Nowhere" is neither a library track \(Figure8'):
        dronerace.RaceVecEnv(2, tracks="Nowhere")
    with pytest.raises(ValueError, match="observation"):
        dronerace.RaceVecEnv(2, observation="lidar")
    with pytest.raises(ValueError, match="switching"):
        dronerace.RaceVecEnv(2, switching="sometimes")
    with pytest.raises(ValueError, match="switch_window"):
        dronerace.RaceVecEnv(2, switch_window=1)
    # Counts and seeds beyond their documented limits (python/README.md, "Limits"), however
    # large, and numbers of the wrong type: each named (`test_hostile_inputs.py`
    # runs the calls that could abort the interpreter).
    with pytest.raises(ValueError, match=r"num_envs: 4097 is outside 1\.\.=4096"):
        dronerace.RaceVecEnv(4097)
    with pytest.raises(ValueError, match=r"num_envs: 0 is outside 1\.\.=4096"):
        dronerace.RaceVecEnv(0)
    with pytest.raises(TypeError, match="num_envs: an int, not float"):
        dronerace.RaceVecEnv(2.5)
    with pytest.raises(ValueError, match=r"rollout_steps: 4294967296 is outside 1\.\.=1000000"):
        dronerace.RaceVecEnv(2, rollout_steps=2**32)
    with pytest.raises(ValueError, match=r"max_episode_steps: 0 is outside 1\.\.=1000000"):
        dronerace.RaceVecEnv(2, max_episode_steps=0)
    with pytest.raises(ValueError, match=r"switch_window: 10001 is outside 2\.\.=10000"):
        dronerace.RaceVecEnv(2, switch_window=10_001)
    with pytest.raises(ValueError, match=r"seed: -1 is outside 0\.\.=18446744073709551615"):
        dronerace.RaceVecEnv(2, seed=-1)
    with pytest.raises(ValueError, match=r"seed: 18446744073709551616 is outside"):
        envs.reset(seed=2**64)
