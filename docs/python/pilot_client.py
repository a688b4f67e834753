"""Fly a served dronerace policy from Python: the client side of `dronerace serve`.

Generates the gRPC stubs from proto/ with grpcio-tools on first use (into a cache directory),
asks the server what it serves, then sends observations one by one (`Act`) and as a control
loop over one stream (`Fly`).

    pip install grpcio grpcio-tools
    dronerace serve --policy policies/generalist.bin --listen 127.0.0.1:50060 &
    python docs/python/pilot_client.py --addr 127.0.0.1:50060

`--observations FILE.json` (a list of observation lists) sends those instead of zeros and
prints the actions as JSON (what the CI test compares with dronerace's own evaluation).
`--token-file F` sends the bearer token the server requires. `--bench N` instead times N
requests each way — unary and streamed, flat out and paced at 50 Hz — and prints latency
percentiles and requests per second (BENCHMARKS.md).
"""
import argparse, json, statistics, sys, tempfile, time
from pathlib import Path

import grpc

ROOT = Path(__file__).resolve().parents[2]


def stubs():
    """The generated dronerace.v1 modules (protoc runs once per proto file version).

    They are generated as the package `dronerace_grpc.v1`, not `dronerace.v1` as the proto
    file's path would name them, so that they never shadow or hide the `dronerace` package
    (python/) in one interpreter."""
    import shutil
    from grpc_tools import protoc
    source = ROOT / "proto" / "proto" / "dronerace" / "v1" / "dronerace.proto"
    out = Path(tempfile.gettempdir()) / f"dronerace-pilot-stubs-{int(source.stat().st_mtime)}"
    if not (out / "dronerace_grpc" / "v1" / "dronerace_pb2_grpc.py").exists():
        (out / "proto" / "dronerace_grpc" / "v1").mkdir(parents=True, exist_ok=True)
        shutil.copy(source, out / "proto" / "dronerace_grpc" / "v1" / "dronerace.proto")
        code = protoc.main(["protoc", f"-I{out / 'proto'}", f"--python_out={out}", f"--grpc_python_out={out}",
                            "dronerace_grpc/v1/dronerace.proto"])
        if code != 0:
            sys.exit(f"protoc failed ({code})")
    sys.path.insert(0, str(out))
    from dronerace_grpc.v1 import dronerace_pb2, dronerace_pb2_grpc
    return dronerace_pb2, dronerace_pb2_grpc


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--addr", default="127.0.0.1:50060")
    p.add_argument("--token-file")
    p.add_argument("--observations", help="JSON file with a list of observations")
    p.add_argument("--bench", type=int, metavar="N", help="time N requests per mode instead")
    a = p.parse_args()
    pb, pb_grpc = stubs()
    metadata = []
    if a.token_file:
        metadata.append(("authorization", "Bearer " + Path(a.token_file).read_text().strip()))
    pilot = pb_grpc.PilotStub(grpc.insecure_channel(a.addr))
    info = pilot.Describe(pb.DescribeRequest(), metadata=metadata)
    print(f"policy v{info.policy_version}: {info.observation_layout or str(info.observation_dim) + ' observations'} "
          f"-> {info.action_dim} actions", file=sys.stderr)
    if a.bench:
        return bench(pilot, pb, metadata, info.observation_dim, a.bench)
    observations = json.load(open(a.observations)) if a.observations else [[0.0] * info.observation_dim] * 3
    unary = [list(pilot.Act(pb.ActRequest(observation=o), metadata=metadata).action) for o in observations]
    loop = [list(r.action) for r in pilot.Fly((pb.ActRequest(observation=o) for o in observations), metadata=metadata)]
    print(json.dumps({"act": unary, "fly": loop}))


def bench(pilot, pb, metadata, dim, n):
    """Latency of one observation → action, unary and streamed, flat out and at 50 Hz."""
    request = pb.ActRequest(observation=[0.1] * dim)

    def report(mode, latencies, seconds):
        q = statistics.quantiles(latencies, n=100)
        print(f"{mode:22s} {len(latencies)} requests: p50 {q[49] * 1e3:.3f} ms  p99 {q[98] * 1e3:.3f} ms  "
              f"{len(latencies) / seconds:.0f} requests/s")

    for period, label in ((0.0, "flat out"), (0.02, "50 Hz")):
        latencies, start = [], time.perf_counter()
        for k in range(n):
            if period:
                time.sleep(max(0.0, start + k * period - time.perf_counter()))
            t = time.perf_counter()
            pilot.Act(request, metadata=metadata)
            latencies.append(time.perf_counter() - t)
        report(f"unary, {label}", latencies, time.perf_counter() - start)
        # Streamed: the generator yields the next observation only once the previous action came
        # back, as a control loop does, so each latency is one round trip on the open stream.
        sent, latencies, start = [], [], time.perf_counter()

        def loop():
            for k in range(n):
                if period:
                    time.sleep(max(0.0, start + k * period - time.perf_counter()))
                sent.append(time.perf_counter())
                yield request
                while len(latencies) < len(sent):
                    time.sleep(0)
        for reply in pilot.Fly(loop(), metadata=metadata):
            latencies.append(time.perf_counter() - sent[len(latencies)])
        report(f"streamed, {label}", latencies, time.perf_counter() - start)


if __name__ == "__main__":
    main()
