"""Validate deploy/k8s/*.yaml against the Kubernetes schemas and the project's deployment rules.

    pip install kubernetes-validate
    python3 deploy/check-k8s.py [--kubernetes-version 1.34] [FILE ...]

Schema: every resource, strictly (unknown fields refused), for the given Kubernetes version.
Rules: every pod runs as non-root; every container has CPU and memory requests and limits; a
container that serves gRPC (declares a containerPort) has native gRPC readiness and liveness
probes, each naming its service and asking the plaintext port given to --health-listen (native
probes cannot speak TLS, which the servers speak beyond loopback); the learner's run directory and the task controller's snapshot are on
PersistentVolumeClaims; the token and certificates come from a Secret; actors spread across
nodes. Exits non-zero naming every failure.
"""
import argparse, sys
from pathlib import Path

import kubernetes_validate
import yaml


def rules(doc):
    """The project's rules for one resource: a list of failures."""
    kind, name = doc.get("kind"), doc.get("metadata", {}).get("name")
    if kind not in ("Deployment", "StatefulSet"):
        return []
    where = f"{kind}/{name}"
    pod = doc["spec"]["template"]["spec"]
    failures = []
    if not pod.get("securityContext", {}).get("runAsNonRoot"):
        failures.append(f"{where}: pod does not set securityContext.runAsNonRoot")
    volumes = {v["name"]: v for v in pod.get("volumes", [])}
    if not any("secret" in v for v in volumes.values()):
        failures.append(f"{where}: no Secret volume for the token and certificates")
    for c in pod["containers"]:
        at = f"{where} container {c['name']}"
        resources = c.get("resources", {})
        for part in ("requests", "limits"):
            for what in ("cpu", "memory"):
                if what not in resources.get(part, {}):
                    failures.append(f"{at}: no resources.{part}.{what}")
        if c.get("ports"):
            # Native gRPC probes speak plaintext only; the servers speak TLS beyond loopback, so a
            # probe must ask the plaintext health port given to --health-listen.
            args = [str(a) for a in c.get("args", [])]
            health = {int(args[i + 1].rsplit(":", 1)[1]) for i, a in enumerate(args[:-1]) if a == "--health-listen"}
            for probe in ("readinessProbe", "livenessProbe"):
                grpc = c.get(probe, {}).get("grpc")
                if grpc is None:
                    failures.append(f"{at}: serves gRPC but has no native gRPC {probe}")
                elif grpc.get("port") not in health:
                    failures.append(f"{c['name']}: {probe} asks port {grpc.get('port')}, not the plaintext --health-listen port {sorted(health)}")
                elif not grpc.get("service"):
                    failures.append(f"{at}: {probe} names no service (it would pass whatever the server serves)")
        for mount in c.get("volumeMounts", []):
            if mount["mountPath"] in ("/runs", "/state") and "persistentVolumeClaim" not in volumes[mount["name"]]:
                failures.append(f"{at}: {mount['mountPath']} is not on a PersistentVolumeClaim")
    if name == "actor" and not pod.get("topologySpreadConstraints") and not pod.get("affinity"):
        failures.append(f"{where}: actors are not spread across nodes")
    return failures


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--kubernetes-version", default="1.34")
    p.add_argument("files", nargs="*", default=sorted(str(f) for f in Path(__file__).parent.glob("k8s/*.yaml")))
    a = p.parse_args()
    failures, count = [], 0
    for file in a.files:
        for doc in yaml.safe_load_all(open(file)):
            if not doc:
                continue
            count += 1
            try:
                kubernetes_validate.validate(doc, a.kubernetes_version, strict=True)
            except kubernetes_validate.ValidationError as e:
                failures.append(f"{file}: {doc.get('kind')}/{doc.get('metadata', {}).get('name')}: {e.message} at {list(e.path)}")
            failures += [f"{file}: {f}" for f in rules(doc)]
    for f in failures:
        print(f, file=sys.stderr)
    print(f"{count} resources checked against Kubernetes {a.kubernetes_version}: {len(failures)} failures")
    sys.exit(1 if failures else 0)


if __name__ == "__main__":
    main()
