"""An independent implementation of the state-based environment — the numpy port of
docs/bench/numpy_env.py, written from the Rust sources for the speed baseline — flies step for
step as RaceVecEnv does: the same body states, observations, rewards, target gates, laps and
episode ends, bit for bit (glibc's atan2 for the heading, as Rust)."""

import importlib.util
import pathlib

import dronerace

ROOT = pathlib.Path(__file__).resolve().parents[2]


def load_port():
    spec = importlib.util.spec_from_file_location("numpy_env", ROOT / "docs" / "bench" / "numpy_env.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_numpy_port_flies_as_racevecenv_bit_for_bit():
    port = load_port()
    assert port._chacha_known_answer()
    policy = dronerace.Policy.load(str(ROOT / "policies" / "generalist.bin"))
    names = dronerace.tracks.library_names()
    # Random actions (crashes of every kind), the generalist's actions (gates passed; it may
    # fly all 200 steps without a crash), and the evaluation environment with short episodes
    # (truncations and resets). Each flight must show what it is there to compare.
    for randomize, max_steps, source in [(True, None, "random"), (True, None, "policy"), (False, 60, "policy")]:
        r = port.fly_both(names, 18, 7, 200, randomize, max_steps, source, True, policy)
        if source == "random" or max_steps:
            assert r["ends_rust"], "some episodes end within the horizon"
        else:
            assert r["passes"] > 0, "the policy passes gates"
        assert r["ends_rust"] == r["ends_port"]
        assert r["start"] == 0 and r["state"] == 0 and r["reward"] == 0
        assert r["not_identical"] == 0, f"observation columns {sorted(r['differing'])} differ"
        assert r["infos_agree"]
