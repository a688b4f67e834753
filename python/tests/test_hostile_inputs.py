"""Regression tests from a security review: calls that aborted the interpreter,
raised `PanicException` (a BaseException that `except Exception` misses), filled memory,
deadlocked, or wrote into arrays the user had made read-only now raise a ValueError or
TypeError naming the argument, finish, or leave the user's array alone.

Each hostile call runs in a fresh interpreter, its address space capped at 4 GiB, so a call
that would abort or fill memory fails that test alone, and one that would hang fails on the
timeout."""

import json
import os
import pathlib
import resource
import subprocess
import sys
import textwrap

import pytest

GENERALIST = pathlib.Path(__file__).resolve().parents[2] / "policies" / "generalist.bin"
MEMORY_CAP = 4 << 30
TIMEOUT_S = 120


def run_python(code, env=None, one_cpu=False):
    """Runs `code` in a fresh interpreter (memory capped; on one CPU if asked): the completed
    process, or a test failure if it outlives the timeout."""

    def limit():
        resource.setrlimit(resource.RLIMIT_AS, (MEMORY_CAP, MEMORY_CAP))
        if one_cpu:
            os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})

    try:
        return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True,
                              timeout=TIMEOUT_S, env=env, preexec_fn=limit)
    except subprocess.TimeoutExpired:
        pytest.fail(f"still running after {TIMEOUT_S} s (deadlocked or working without bound):\n{code}")


def raised(call, setup=""):
    """The exception `call` (one expression) raises in a fresh interpreter, as (type name,
    message); ("nothing", result) if it returns."""
    code = f"""
        import json, numpy as np, dronerace, dronerace._core as core
        {setup}
        try:
            result = {call}
            print(json.dumps(["nothing", repr(result)[:200]]))
        except BaseException as e:
            print(json.dumps([type(e).__name__, str(e)]))
    """
    done = run_python(code)
    assert done.returncode == 0 and done.stdout, f"{call}: exit status {done.returncode}\n{done.stderr[-3000:]}"
    return tuple(json.loads(done.stdout.splitlines()[-1]))


def assert_refused(call, exception, message, setup=""):
    kind, text = raised(call, setup)
    assert kind == exception.__name__, f"{call}: {kind}: {text}"
    assert text.startswith(message), f"{call}: {text!r} does not start with {message!r}"


def test_generate_with_a_trillion_gates_raises_value_error_not_abort():
    assert_refused("dronerace.tracks.generate(0, gates=10**12)", ValueError, "gates: 1000000000000 is outside 2..=64")


@pytest.mark.parametrize("call, exception, message", [
    ("core.generate(0, gates=0)", ValueError, "gates: 0 is outside 2..=64"),
    ("core.generate(0, kind='uniform', gates=2**62)", ValueError, "gates: 4611686018427387904 is outside 2..=64"),
    ("core.generate(0, gates_max=2**63)", ValueError, "gates_max: 9223372036854775808 is outside 2..=64"),
    ("core.generate(0, gates=2**64)", ValueError, "gates: 18446744073709551616 is outside 2..=64"),
    ("core.generate(0, gates=2**200)", ValueError, "gates: an int beyond 128 bits is outside 2..=64"),
    ("core.generate(0, gates=-1)", ValueError, "gates: -1 is outside 2..=64"),
    ("core.generate(0, gates=6.0)", TypeError, "gates: an int, not float"),
    ("core.generate(-1)", ValueError, "seed: -1 is outside 0..=18446744073709551615"),
])
def test_generating_with_counts_or_seeds_out_of_range_raises_naming_the_argument(call, exception, message):
    assert_refused(call, exception, message)


@pytest.mark.parametrize("points, message", [
    ("[(1e300, 0, 0), (0, 1e300, 0), (0, 0, 1), (1, 1, 1)]", "points[0][0] is 1e300; coordinates lie within ±1000 m"),
    ("[(0, 0, 1), (5, 0, 1), (5, 5, float('nan')), (0, 5, 1)]", "points[2][2] is NaN"),
    ("[(0, 0, 1), (5, 0, 1), (5, 5, 2), (-1e4, 5, 1)]", "points[3][0] is -1e4"),
    ("[(np.cos(t), np.sin(t), 1.0) for t in np.linspace(0, 6, 257)]", "points: 257 points; a fit takes at most 256"),
    ("[(0, 0, 1), (10**400, 0, 1), (5, 5, 2), (0, 5, 1)]", "points[1][0]: an int beyond a float's range"),
])
def test_fit_with_huge_nan_or_too_many_points_raises_value_error_not_panic_exception(points, message):
    assert_refused(f"dronerace.tracks.fit({points})", ValueError, message)


@pytest.mark.parametrize("call, message", [
    ("dronerace.RaceVecEnv(2**40)", "num_envs: 1099511627776 is outside 1..=4096"),
    ("core.VecEnv(num_envs=2**40)", "num_envs: 1099511627776 is outside 1..=4096"),
    ("core.VecEnv(2, rollout_steps=2**40)", "rollout_steps: 1099511627776 is outside 1..=1000000"),
    ("core.VecEnv(2, max_episode_steps=2**40)", "max_episode_steps: 1099511627776 is outside 1..=1000000"),
    ("core.VecEnv(2, switch_window=2**40)", "switch_window: 1099511627776 is outside 2..=10000"),
    ("core.VecEnv(2, switch_alpha=10**400)", "switch_alpha: an int beyond a float's range"),
    ("core.VecEnv(2, switch_probability=float('inf'))", "switch_probability is inf, not a finite number"),
])
def test_a_vector_env_of_2_to_the_40_environments_or_steps_raises_value_error_not_panic(call, message):
    assert_refused(call, ValueError, message)


@pytest.mark.parametrize("call, message", [
    ("dronerace.evaluate(lambda o: np.zeros((len(o), 4)), 'Figure8', runs=10**6)", "runs: 1000000 is outside 1..=1000"),
    ("dronerace.evaluate(policy, 'Figure8', runs=10**6)", "runs: 1000000 is outside 1..=1000"),
    ("dronerace.evaluate(policy, 'Figure8', steps=2**32)", "steps: 4294967296 is outside 1..=1000000"),
    ("dronerace.evaluate(policy, ['Figure8'] * 200, runs=1000)", "runs: 1000 runs on each of 200 tracks make 200000 deployments"),
    ("dronerace.evaluate(policy, ['Figure8'] * 5000, runs=1)", "tracks: 5000 tracks; at most 4096"),
])
def test_an_evaluation_of_a_million_runs_raises_value_error_instead_of_flying_them(call, message):
    assert_refused(call, ValueError, message, setup=f"policy = dronerace.Policy.load({str(GENERALIST)!r})")


def test_loading_dev_zero_as_a_policy_raises_value_error_instead_of_filling_memory():
    assert_refused("dronerace.Policy.load('/dev/zero')", ValueError, "path: /dev/zero: not a regular file")


def test_a_policy_file_over_256_mib_is_refused_unread(tmp_path):
    big = tmp_path / "big.bin"
    with open(big, "wb") as f:
        f.truncate((256 << 20) + 1)  # sparse: no disk used
    assert_refused(f"dronerace.Policy.load({str(big)!r})", ValueError, f"path: {big}: 268435457 bytes, more than the 268435456")


def test_a_csv_track_that_is_a_device_raises_value_error_instead_of_filling_memory(tmp_path):
    zero = tmp_path / "zero.csv"
    zero.symlink_to("/dev/zero")
    assert_refused(f"dronerace.tracks.load({str(zero)!r})", ValueError, f"{zero}: not a regular file")


STEP_FROM_A_SECOND_THREAD = f"""
    import threading, numpy as np, dronerace
    # 96 environments: enough that rayon splits the step (a few would run on the caller alone).
    envs = dronerace.RaceVecEnv(96, tracks="Figure8")
    envs.reset(seed=0)
    policy = dronerace.Policy.load({str(GENERALIST)!r})

    def work():
        for _ in range(20):
            envs.step(np.zeros((96, 4), np.float32))
        dronerace.evaluate(policy, "Figure8", runs=8, steps=20)  # rayon's pool, from this thread

    worker = threading.Thread(target=work)
    worker.start()
    worker.join()  # the main thread waits in Python
    print("done")
"""


@pytest.mark.parametrize("one_cpu", [False, True], ids=["RAYON_NUM_THREADS=1", "one_cpu"])
def test_a_step_from_a_second_thread_while_the_main_thread_joins_does_not_deadlock_on_one_thread(one_cpu):
    env = {k: v for k, v in os.environ.items() if k != "RAYON_NUM_THREADS"}
    if not one_cpu:
        env["RAYON_NUM_THREADS"] = "1"
    done = run_python(STEP_FROM_A_SECOND_THREAD, env=env, one_cpu=one_cpu)
    assert done.returncode == 0 and done.stdout.strip() == "done", done.stderr[-3000:]


def test_step_leaves_output_arrays_made_read_only_alone_and_returns_fresh_ones():
    code = """
        import numpy as np, dronerace
        envs = dronerace.RaceVecEnv(4, tracks="Figure8", observation="vision")
        obs, _ = envs.reset(seed=0)
        _, rewards, terminations, truncations, _ = envs.step(np.zeros((4, 4), np.float32))
        theirs = [obs["state"], obs["image"], rewards, terminations, truncations]
        for array in theirs:
            array.flags.writeable = False
        kept = [array.copy() for array in theirs]
        obs, rewards, terminations, truncations, _ = envs.step(np.ones((4, 4), np.float32))
        ours = [obs["state"], obs["image"], rewards, terminations, truncations]
        assert all(np.array_equal(a, k) for a, k in zip(theirs, kept)), "a read-only array was written"
        assert all(o is not t and o.flags.writeable and o.shape == t.shape and o.dtype == t.dtype for o, t in zip(ours, theirs))
        assert not np.array_equal(ours[0], kept[0]), "the fresh observations are the step's"
        again = envs.step(np.ones((4, 4), np.float32))
        assert again[0]["state"] is ours[0] and again[1] is ours[2], "the fresh arrays are then filled in place"
        print("ok")
    """
    done = run_python(code)
    assert done.returncode == 0 and done.stdout.strip() == "ok", done.stderr[-3000:]


def test_step_after_output_arrays_were_resized_or_retyped_gives_fresh_arrays_not_a_panic():
    code = """
        import numpy as np, dronerace
        envs = dronerace.RaceVecEnv(4, tracks="Figure8")
        obs, _ = envs.reset(seed=0)
        _, rewards, terminations, truncations, _ = envs.step(np.zeros((4, 4), np.float32))
        obs.resize((2, 3), refcheck=False)
        rewards.dtype = np.int32  # same size, other type: written as floats it would read as garbage
        terminations.resize((1,), refcheck=False)
        truncations.shape = (2, 2)
        kept = rewards.copy()
        obs, rewards2, terminations, truncations, _ = envs.step(np.zeros((4, 4), np.float32))
        assert obs.shape == (4, 52) and rewards2.dtype == np.float32 and terminations.shape == truncations.shape == (4,)
        assert np.array_equal(rewards, kept) and np.isfinite(obs).all()
        print("ok")
    """
    done = run_python(code)
    assert done.returncode == 0 and done.stdout.strip() == "ok", done.stderr[-3000:]
