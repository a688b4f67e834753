#!/usr/bin/env bash
# Builds the dronerace image with podman on the local bases of local-images.sh (made if missing)
# and prints the build's seconds and the image's size in bytes.
#   deploy/build-image.sh TAG            compiled from source (docker/Dockerfile)
#   deploy/build-image.sh TAG BINARY     around a binary already built (`--target prebuilt`)
set -euo pipefail
deploy=$(cd "$(dirname "$0")" && pwd)
root=$(dirname "$deploy")
export CONTAINERS_CONF=${CONTAINERS_CONF:-$deploy/podman/containers.conf}
tag=$1
# Around a prebuilt binary only the runtime base is needed.
"$deploy/local-images.sh" $([ $# -ge 2 ] && echo runtime) >&2
bases=(--build-arg BUILD_IMAGE=localhost/rust:1.95-bookworm --build-arg RUNTIME_IMAGE=localhost/debian:bookworm-slim)
start=$(date +%s)
if [ $# -ge 2 ]; then
    # Only the binary goes into the build context, stripped of debug information.
    context=$(mktemp -d)
    trap 'rm -rf "$context"' EXIT
    strip -o "$context/dronerace" "$2"
    podman build -q -f "$root/docker/Dockerfile" --target prebuilt "${bases[@]}" -t "$tag" "$context" >/dev/null
else
    podman build -q -f "$root/docker/Dockerfile" "${bases[@]}" -t "$tag" "$root" >/dev/null
fi
echo "image $tag built in $(( $(date +%s) - start )) s, $(podman image inspect "$tag" --format '{{.Size}}') bytes"
