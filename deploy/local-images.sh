#!/usr/bin/env bash
# Makes the two base images docker/Dockerfile builds on, for a machine that cannot pull public
# images but has podman, debootstrap and Debian's package mirror (these machines):
#   localhost/debian:bookworm-slim  the runtime base: Debian bookworm, minbase, docs removed
#   localhost/rust:1.95-bookworm    the build base: the same plus gcc and libc6-dev, and this
#                                   machine's Rust toolchain (rustc and cargo, docs left out)
# Then build with them as the Dockerfile's build arguments:
#   export CONTAINERS_CONF=$PWD/deploy/podman/containers.conf
#   podman build -f docker/Dockerfile -t dronerace \
#     --build-arg BUILD_IMAGE=localhost/rust:1.95-bookworm \
#     --build-arg RUNTIME_IMAGE=localhost/debian:bookworm-slim .
# `local-images.sh runtime` makes the runtime base only (enough for `--target prebuilt`).
# Images that exist already are kept (FORCE=1 remakes them). Needs root: debootstrap and chroot.
set -euo pipefail
export CONTAINERS_CONF=${CONTAINERS_CONF:-$(cd "$(dirname "$0")" && pwd)/podman/containers.conf}
mirror=${DEBIAN_MIRROR:-http://deb.debian.org/debian}
runtime_image=localhost/debian:bookworm-slim
build_image=localhost/rust:1.95-bookworm
for tool in podman debootstrap; do
    command -v "$tool" >/dev/null || { echo "$tool is missing: apt-get install podman runc debootstrap" >&2; exit 1; }
done
exists() { [ "${FORCE:-0}" != 1 ] && podman image exists "$1"; }
# Whether to make the build base: not with `runtime` (prebuilt images need none), nor when it exists.
wanted_build() { [ "${1:-}" != runtime ] && ! exists "$build_image"; }
work=$(mktemp -d /var/tmp/dronerace-images.XXXXXX)
trap 'rm -rf "$work"' EXIT

# Strips what an image never needs, as Debian's -slim images do.
slim() {
    rm -rf "$1"/var/cache/apt/archives/*.deb "$1"/var/lib/apt/lists/* \
        "$1"/usr/share/doc/* "$1"/usr/share/man/* "$1"/usr/share/info/*
}

if exists "$runtime_image" && ! wanted_build "$@"; then
    echo "the base images wanted exist (FORCE=1 remakes them)"
    exit 0
fi
echo "debootstrap bookworm (minbase) from $mirror"
debootstrap --variant=minbase bookworm "$work/rootfs" "$mirror" >"$work/debootstrap.log" ||
    { tail -20 "$work/debootstrap.log" >&2; exit 1; }

if wanted_build "$@"; then
    # The build base starts as a copy of the runtime base, so both are the same Debian.
    cp -a "$work/rootfs" "$work/build"
    cp /etc/resolv.conf "$work/build/etc/resolv.conf"
    chroot "$work/build" sh -c 'apt-get update -qq && DEBIAN_FRONTEND=noninteractive \
        apt-get install -y -qq --no-install-recommends gcc libc6-dev ca-certificates >/dev/null'
    # Certificate authorities this machine trusts beyond Debian's (a proxy's, say), so that cargo
    # in the build base reaches crates.io as cargo on this machine does.
    if compgen -G "/usr/local/share/ca-certificates/*.crt" >/dev/null; then
        cp /usr/local/share/ca-certificates/*.crt "$work/build/usr/local/share/ca-certificates/"
        chroot "$work/build" update-ca-certificates >/dev/null
    fi
    toolchain=$(rustc --print sysroot)
    mkdir -p "$work/build/usr/local/rust"
    tar -C "$toolchain" --exclude=./share/doc -c . | tar -C "$work/build/usr/local/rust" -x
    for tool in cargo rustc rustdoc; do ln -s "/usr/local/rust/bin/$tool" "$work/build/usr/local/bin/$tool"; done
    slim "$work/build"
    tar -C "$work/build" -c . | podman import -q --change 'ENV CARGO_HOME=/usr/local/cargo' - "$build_image" >/dev/null
    echo "made $build_image ($(podman run --rm "$build_image" cargo --version))"
fi
if ! exists "$runtime_image"; then
    slim "$work/rootfs"
    tar -C "$work/rootfs" -c . | podman import -q - "$runtime_image" >/dev/null
    echo "made $runtime_image"
fi
