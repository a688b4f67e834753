"""Tracks, policies, the flight-stack racer and evaluation from Python."""

import pathlib

import numpy as np
import pytest

import dronerace

ROOT = pathlib.Path(__file__).resolve().parents[2]
GENERALIST = ROOT / "policies" / "generalist.bin"


def test_tracks_load_parse_generate_and_round_trip(tmp_path):
    library = dronerace.tracks.library()
    assert [t.name for t in library] == dronerace.tracks.library_names() and len(library) >= 9
    figure8 = library[0]
    assert dronerace.tracks.parse(figure8.to_toml()) == figure8
    figure8.save(tmp_path / "mine.toml")
    assert dronerace.tracks.load(tmp_path / "mine.toml") == figure8
    csv = tmp_path / "poses.csv"
    csv.write_text("x,y,z,yaw_deg\n" + "\n".join(f"{x},{y},{z},{np.degrees(yaw)}" for x, y, z, yaw in figure8.gates))
    assert np.allclose(dronerace.tracks.load(csv).gates, figure8.gates)
    a, b = dronerace.tracks.generate(5), dronerace.tracks.generate(5)
    assert a == b and a != dronerace.tracks.generate(6) and len(a) == 6
    assert len(dronerace.tracks.test_set()) == 40
    assert [t.name for t in dronerace.tracks.validation_set(2)] == ["val-8000000", "val-8000001"]
    fit = dronerace.tracks.fit([(0, 0, 1), (5, 0, 1), (5, 5, 2), (0, 5, 1)], smoothing=0.0)
    assert len(fit["coefficients"]) == 3 and fit["residual"] < 1e-9
    with pytest.raises(OSError, match="missing.toml"):
        dronerace.tracks.load(tmp_path / "missing.toml")
    (tmp_path / "broken").mkdir()
    (tmp_path / "broken" / "bad.toml").write_text('name = "Bad"\n')
    with pytest.raises(ValueError, match="bad.toml: gate: a track needs at least 2 gates"):
        dronerace.tracks.load(tmp_path / "broken" / "bad.toml")
    envs = dronerace.RaceVecEnv(2, tracks=[tmp_path])
    envs.reset()
    assert {t.name for t in envs.tracks()} == {"Figure8"}
    # Beyond the limits (python/README.md, "Limits"), each named.
    with pytest.raises(ValueError, match=r"gates: 65 is outside 2\.\.=64"):
        dronerace.tracks.generate(0, gates=65)
    with pytest.raises(ValueError, match=r"gates_max: 1 is outside 2\.\.=64"):
        dronerace.tracks.generate(0, gates_max=1)
    with pytest.raises(ValueError, match=r"count: 10000000 is outside 0\.\.=4096"):
        dronerace.tracks.validation_set(10**7)
    with pytest.raises(ValueError, match=r"seed: 18446744073709551615 is outside 0\.\.=18446744073709551575"):
        dronerace.tracks.test_set(2**64 - 1)
    with pytest.raises(ValueError, match=r"points\[1\]\[2\] is 1e4; coordinates lie within ±1000 m"):
        dronerace.tracks.fit([(0, 0, 1), (5, 0, 1e4), (5, 5, 2), (0, 5, 1)])


def test_policy_acts_deterministically_within_bounds_and_refuses_wrong_input():
    policy = dronerace.Policy.load(GENERALIST)
    assert policy.agent == "state" and policy.observation_dim == 52
    envs = dronerace.RaceVecEnv(5, tracks="Figure8")
    obs, _ = envs.reset(seed=0)
    actions = policy.act(obs)
    assert actions.shape == (5, 4) and actions.dtype == np.float32 and np.abs(actions).max() <= 1.0
    assert np.array_equal(actions, policy.act(obs.copy()))
    # The same numbers laid out column-major (what `obs[:, columns]` or a transpose gives) or
    # strided are the same observations (the rows differ, so a misread would show).
    assert not np.array_equal(actions[0], actions[1])
    assert np.array_equal(actions, policy.act(np.asfortranarray(obs)))
    assert np.array_equal(actions[::2], policy.act(obs[::2]))
    with pytest.raises(ValueError, match=r"observations: expected shape \(n, 52\)"):
        policy.act(np.zeros((2, 40), dtype=np.float32))
    with pytest.raises(OSError, match="nothing.bin"):
        dronerace.Policy.load("nothing.bin")
    with pytest.raises(ValueError, match="path: .*policies: not a regular file"):
        dronerace.Policy.load(ROOT / "policies")


def test_the_generalist_laps_figure8_through_a_python_callable_as_through_its_policy_file():
    policy = dronerace.Policy.load(GENERALIST)
    by_file = dronerace.evaluate(policy, ["Figure8"], runs=4)
    by_callable = dronerace.evaluate(policy.act, "Figure8", runs=4)
    laps = [[d["lap_times"] for d in r["tracks"][0]["deployments"]] for r in (by_file, by_callable)]
    assert laps[0] == laps[1] and all(len(l) >= 2 for l in laps[0]), laps
    assert by_file["success_rate"] == by_callable["success_rate"] == 1.0
    hover = dronerace.evaluate(lambda obs: np.zeros((len(obs), 4)), "Figure8", runs=2, steps=100)
    assert hover["success_rate"] == 0.0
    with pytest.raises(ValueError, match=r"the callable's actions\[0, 0\] is NaN"):
        dronerace.evaluate(lambda obs: np.full((len(obs), 4), np.nan), "Figure8", runs=1, steps=5)
    with pytest.raises(ValueError, match=r"expected shape \(1, 4\)"):
        dronerace.evaluate(lambda obs: np.zeros((len(obs), 3)), "Figure8", runs=1, steps=5)
    with pytest.raises(ValueError, match=r"runs: 0 is outside 1\.\.=1000"):
        dronerace.evaluate(policy, "Figure8", runs=0)
    with pytest.raises(TypeError, match="steps: an int, not float"):
        dronerace.evaluate(policy, "Figure8", steps=1e3)


def test_a_racer_fed_the_simulators_states_observes_as_the_environment_and_flies_the_policy():
    policy = dronerace.Policy.load(GENERALIST)
    envs = dronerace.RaceVecEnv(1, tracks="Figure8", randomize=False, max_episode_steps=1000)
    obs, infos = envs.reset(seed=4)
    racer = dronerace.Racer(envs.tracks()[0], policy=policy)
    for step in range(600):
        state = envs.states()[0]
        observed = racer.observe(state[0:3], state[3:6], state[6:10], state[10:13])
        assert np.array_equal(observed, obs[0]), f"step {step}"
        assert (racer.target_gate, racer.laps) == (infos["target_gate"][0], infos["laps"][0]), f"step {step}"
        action = policy.act(obs)[0]
        racer.acted(action)
        obs, _, terminations, truncations, infos = envs.step(action[None, :])
        assert not (terminations[0] or truncations[0]), f"the generalist crashed on Figure8 at step {step}"
    laps = infos["laps"][0]
    assert laps >= 1
    with pytest.raises(ValueError, match="orientation has norm 2"):
        racer.observe([0, 0, 1], [0, 0, 0], [2, 0, 0, 0], [0, 0, 0])
    with pytest.raises(ValueError, match="position has 2 numbers; it needs 3"):
        racer.observe([0, 0], [0, 0, 0], [1, 0, 0, 0], [0, 0, 0])
    with pytest.raises(ValueError, match=r"velocity\[1\] is NaN"):
        racer.observe([0, 0, 1], [0, np.nan, 0], [1, 0, 0, 0], [0, 0, 0])
    # Finite but beyond any drone: 1e308 m made every observation -inf.
    with pytest.raises(ValueError, match=r"position\[0\] is 10{308}, beyond the ±1000"):
        racer.observe([1e308, 0, 1], [0, 0, 0], [1, 0, 0, 0], [0, 0, 0])
    with pytest.raises(ValueError, match=r"velocity\[2\] is -150, beyond the ±100"):
        racer.observe([0, 0, 1], [0, 0, -150], [1, 0, 0, 0], [0, 0, 0])
    with pytest.raises(ValueError, match=r"angular_velocity\[1\] is 1000, beyond the ±100"):
        racer.observe([0, 0, 1], [0, 0, 0], [1, 0, 0, 0], [0, 1000, 0])
