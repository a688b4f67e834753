#!/usr/bin/env bash
# deploy/k8s/dronerace.yaml under `podman kube play` (podman 4.3, Debian bookworm's), as far as
# podman runs it: the task controller and learner Deployments with their PersistentVolumeClaims
# and the ConfigMap. What podman 4.3 cannot do is stood in for, and said here:
#   - a Secret volume is written still base64-encoded (the TLS key does not parse), so the
#     secrets directory is mounted with a hostPath instead;
#   - Services give no names, so the actors get the pods' addresses with --add-host;
#   - a StatefulSet is ignored, so the two actors run as plain containers (same image, args);
#   - native gRPC probes are not run (podman makes health checks of exec probes only).
# Trains until the learner reports iteration 3, then tears everything down.
#
#   deploy/kube-play-test.sh [BINARY]   (image from source, or around BINARY; see build-image.sh)
set -euo pipefail
deploy=$(cd "$(dirname "$0")" && pwd)
export CONTAINERS_CONF=${CONTAINERS_CONF:-$deploy/podman/containers.conf}
image=localhost/dronerace:kube-$$
network=dronerace-kube-$$
work=$(mktemp -d /var/tmp/dronerace-kube.XXXXXX)
say() { echo "kube-play-test: $*"; }
cleanup() {
    podman rm -f actor-0 actor-1 >/dev/null 2>&1 || true
    [ -f "$work/manifest.yaml" ] && podman kube down "$work/manifest.yaml" >/dev/null 2>&1 || true
    podman volume rm -f dronerace-runs dronerace-taskctl dronerace-config >/dev/null 2>&1 || true
    podman network rm -f "$network" >/dev/null 2>&1 || true
    podman image rm -f "$image" >/dev/null 2>&1 || true
    rm -rf "$work"
}
trap cleanup EXIT

say "$("$deploy/build-image.sh" "$image" "$@")"
"$deploy/make-certs.sh" "$work/secrets" taskctl learner >/dev/null 2>&1
chown -R 10001:10001 "$work/secrets"
# The ConfigMap as `kubectl create configmap dronerace-config --from-file=cluster.toml=...` makes it.
{
    printf 'apiVersion: v1\nkind: ConfigMap\nmetadata: { name: dronerace-config }\ndata:\n  cluster.toml: |\n'
    sed 's/^/    /' "$deploy/cluster.toml"
} >"$work/configmap.yaml"
sed -e "s#secret: { secretName: dronerace-secrets, optional: false }#hostPath: { path: $work/secrets }#" \
    -e "s#image: dronerace#image: $image#" "$deploy/k8s/dronerace.yaml" >"$work/manifest.yaml"
grep -q "hostPath: { path: $work/secrets }" "$work/manifest.yaml" || { say "the manifest's secret volume changed; update this script"; exit 1; }

podman network create "$network" >/dev/null
podman kube play --network "$network" --configmap "$work/configmap.yaml" "$work/manifest.yaml" >/dev/null
address() { podman inspect "$1" --format '{{range .NetworkSettings.Networks}}{{.IPAddress}}{{end}}'; }
hosts=(--add-host "taskctl:$(address taskctl-pod-0-taskctl)" --add-host "learner:$(address learner-pod-0-learner)")
for i in 0 1; do
    podman run -d --name "actor-$i" --network "$network" "${hosts[@]}" -v "$work/secrets:/secrets:ro" \
        -v dronerace-config:/config:ro "$image" actor --config /config/cluster.toml --name "actor-$i" \
        --envs 24 --transport grpc --taskctl https://taskctl:50051 --learner https://learner:50052 >/dev/null
done
status() {
    podman run --rm --network "$network" "${hosts[@]}" -v "$work/secrets:/secrets:ro" -v dronerace-config:/config:ro \
        "$image" status --learner https://learner:50052 --config /config/cluster.toml 2>/dev/null
}
deadline=$(( $(date +%s) + 600 ))
until [ "$(status | sed -n 's/^iteration //p')" -ge 3 ] 2>/dev/null; do
    [ "$(date +%s)" -lt "$deadline" ] || { say "no iteration 3 within 600 s"; podman logs learner-pod-0-learner | tail -20; exit 1; }
    sleep 3
done
status | sed 's/^/  status: /'
say "pods: $(podman pod ps --format '{{.Name}}={{.Status}}' | tr '\n' ' ')"
say "passed"
