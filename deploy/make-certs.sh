#!/usr/bin/env bash
# Makes what a multi-machine run needs in DIR (default deploy/secrets): a CA, a server
# certificate for the given host names / IPs, and a bearer token.
#   deploy/make-certs.sh DIR learner.example.org 10.0.0.5 ...
set -euo pipefail
dir=${1:-deploy/secrets}; shift || true
names=("$@")
[ ${#names[@]} -gt 0 ] || names=(taskctl learner localhost 127.0.0.1)
mkdir -p "$dir" && cd "$dir"
san=""
for n in "${names[@]}"; do
    if [[ $n =~ ^[0-9.]+$ ]]; then san+="IP:$n,"; else san+="DNS:$n,"; fi
done
printf 'subjectAltName=%s\nbasicConstraints=CA:FALSE\n' "${san%,}" > san.ext
openssl req -x509 -newkey ec -pkeyopt ec_paramgen_curve:prime256v1 -nodes -subj "/CN=dronerace CA" -days 365 -keyout ca.key -out ca.pem
openssl req -newkey ec -pkeyopt ec_paramgen_curve:prime256v1 -nodes -subj "/CN=dronerace" -keyout server.key -out server.csr
openssl x509 -req -in server.csr -CA ca.pem -CAkey ca.key -CAcreateserial -days 365 -extfile san.ext -out server.pem
head -c 32 /dev/urandom | od -An -tx1 | tr -d ' \n' > token
echo "wrote $dir: ca.pem server.pem server.key token (keep ca.key and token secret)"
