#!/usr/bin/env bash
# The compose stack for real, with podman and podman-compose: task controller, learner and two
# actors over gRPC with TLS and a token; a client container asks Learner/Status and ListTasks
# until three iterations are done; the learner container is stopped and started and must resume
# from its volume; teardown must leave no container or volume of the project behind.
#
#   deploy/compose-test.sh            image compiled from source (docker/Dockerfile; 43 min cold here)
#   deploy/compose-test.sh BINARY     image around a binary already built (`--target prebuilt`;
#                                     CI's short version uses the one its tests built)
#
# Needs root, podman, runc, debootstrap and podman-compose (`apt-get install podman runc
# debootstrap`, `pip install podman-compose`); builds the image with build-image.sh.
# Prints the timings BENCHMARKS.md reports: image build, start to first iteration.
set -euo pipefail
deploy=$(cd "$(dirname "$0")" && pwd)
export CONTAINERS_CONF=${CONTAINERS_CONF:-$deploy/podman/containers.conf}
project=dronerace-test-$$
image=localhost/dronerace:test-$$
secrets=$(mktemp -d /var/tmp/dronerace-secrets.XXXXXX)
compose() { DRONERACE_IMAGE=$image podman-compose -p "$project" -f "$deploy/compose.yaml" "$@"; }
cleanup() {
    compose down -v >/dev/null 2>&1 || true
    podman image rm -f "$image" >/dev/null 2>&1 || true
    rm -rf "$secrets"
}
trap cleanup EXIT
say() { echo "compose-test: $*"; }
elapsed() { echo $(( $(date +%s) - $1 )); }

say "$("$deploy/build-image.sh" "$image" "$@")"

# Certificates for the services' names; readable by the image's user (uid 10001) only.
"$deploy/make-certs.sh" "$secrets" taskctl learner >/dev/null 2>&1
chown -R 10001:10001 "$secrets" && chmod 700 "$secrets"
export DRONERACE_SECRETS=$secrets

# `--profile tools` enables the client service, which `up` leaves out.
status() { compose --profile tools run --rm -T client status --learner https://learner:50052 --config /deploy/cluster.toml 2>/dev/null; }
iteration() { status | sed -n 's/^iteration //p'; }
wait_for_iteration() { # N seconds: until the learner reports iteration >= N
    local deadline=$(( $(date +%s) + $2 )) it
    while [ "$(date +%s)" -lt "$deadline" ]; do
        it=$(iteration || true)
        [ -n "$it" ] && [ "$it" -ge "$1" ] && { echo "$it"; return 0; }
        sleep 2
    done
    say "no iteration $1 within $2 s; learner log:"; compose logs learner | tail -30; return 1
}

start=$(date +%s)
compose up -d >/dev/null 2>&1
wait_for_iteration 1 600 >/dev/null
say "start to first iteration: $(elapsed "$start") s"
wait_for_iteration 3 600 >/dev/null
status | sed 's/^/  status: /'
errors=$(mktemp)
tasks=$(compose --profile tools run --rm -T client tasks --taskctl https://taskctl:50051 --config /deploy/cluster.toml 2>"$errors") ||
    { say "the client's ListTasks failed:"; tail -20 "$errors"; exit 1; }
rm -f "$errors"
[ "$(echo "$tasks" | grep -c 'actor-')" -eq 96 ] || { say "ListTasks does not show 96 environments on the two actors:"; echo "$tasks"; exit 1; }
say "ListTasks: 96 environments on actor-0 and actor-1"

# The learner stops (SIGTERM, then checkpoint) and starts again from the volume.
before=$(iteration)
compose stop learner >/dev/null 2>&1
compose start learner >/dev/null 2>&1
after=$(wait_for_iteration $(( before + 1 )) 600)
compose logs learner 2>&1 | grep -q "resuming the run" || { say "the learner did not resume:"; compose logs learner | tail -20; exit 1; }
say "learner stopped at iteration $before, resumed from its volume, now at iteration $after"

compose down -v >/dev/null 2>&1
label=io.podman.compose.project=$project
left=$(podman ps -a -q --filter "label=$label"; podman volume ls -q --filter "label=$label"; podman network ls -q --filter "label=$label")
[ -z "$left" ] || { say "left behind after teardown: $left"; exit 1; }
say "torn down: no containers, volumes or networks left"
say "passed"
