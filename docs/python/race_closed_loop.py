"""A closed loop from Python through `Pilot/Race`: the simulator (the `dronerace` package) plays
the drone and a flight stack's part — it reports the drone's state every control step — and a
served policy (`dronerace serve`) answers each state with the action, the target gate and the
laps, keeping the race itself.

    pip install ./python grpcio grpcio-tools
    dronerace serve --policy policies/generalist.bin --listen 127.0.0.1:50060 &
    python docs/python/race_closed_loop.py --addr 127.0.0.1:50060 --track Figure8

The drone starts as `dronerace eval`'s deployment 0 of seed `--seed` does (nominal vehicle,
SPEC §9's start perturbation), so with the same policy it flies the same laps as that
deployment. Prints one JSON line: laps, fastest lap, how the flight ended, steps, and the
round-trip latency per step (p50/p99, ms) on the open stream.
"""
import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import grpc
import numpy as np

import dronerace

sys.path.insert(0, str(Path(__file__).resolve().parent))
from pilot_client import stubs  # noqa: E402  (the generated dronerace.v1 modules)


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--addr", default="127.0.0.1:50060")
    p.add_argument("--track", default="Figure8", help="library name or track file")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--steps", type=int, default=1000)
    p.add_argument("--token-file")
    a = p.parse_args()
    pb, pb_grpc = stubs()
    metadata = [("authorization", "Bearer " + Path(a.token_file).read_text().strip())] if a.token_file else []
    pilot = pb_grpc.PilotStub(grpc.insecure_channel(a.addr))

    envs = dronerace.RaceVecEnv(1, tracks=a.track, seed=a.seed, switching="none", randomize=False, max_episode_steps=a.steps)
    envs.reset(seed=a.seed)
    track = envs.tracks()[0]
    # The stream is driven by replies: the next state is sent only once the last action is flown.
    replies, sent, latencies = [], [], []
    ended = {"outcome": None}

    def requests():
        yield pb.RaceRequest(start=pb.RaceStart(track_toml=track.to_toml()))
        for _ in range(a.steps):
            s = envs.states()[0]
            sent.append(time.perf_counter())
            yield pb.RaceRequest(state=pb.DroneState(position=s[0:3], velocity=s[3:6], orientation=s[6:10],
                                                     angular_velocity=s[10:13]))
            while len(replies) < len(sent):
                time.sleep(0)
            _, _, terminated, truncated, infos = envs.step(np.asarray(replies[-1].action, dtype=np.float32)[None, :])
            if terminated[0] or truncated[0]:
                episode = infos["episode"]
                ended.update(outcome=str(episode["outcome"][0]), laps=int(episode["laps"][0]),
                             fastest_lap=float(episode["fastest_lap"][0]), steps=int(episode["l"][0]))
                return

    for reply in pilot.Race(requests(), metadata=metadata):
        latencies.append(time.perf_counter() - sent[len(replies)])
        replies.append(reply)
    q = statistics.quantiles(latencies, n=100)
    result = dict(ended, served_laps=replies[-1].laps, target_gate=replies[-1].target_gate,
                  latency_p50_ms=round(q[49] * 1e3, 3), latency_p99_ms=round(q[98] * 1e3, 3))
    if result.get("fastest_lap") is not None and np.isnan(result["fastest_lap"]):
        result["fastest_lap"] = None
    print(json.dumps(result))


if __name__ == "__main__":
    main()
