#!/usr/bin/env bash
# Make the TLS certificates of one robot: a CA, and one certificate per identity
# the Zenoh access control knows (deploy/zenoh/router.json5):
#
#   <robot>-knowledge   the knowledge service's router (SAN: the names hosts dial)
#   <robot>-onboard     the onboard agent and the detectors it starts
#   <robot>-remote      the remote agent and the detectors it starts
#   <robot>-operator    people's tools (kgadapt deploy / ask / why)
#
# Usage: deploy/tls/make-certs.sh OUT_DIR [ROBOT [ROUTER_NAME...]]
#   e.g. deploy/tls/make-certs.sh ./tls quad1 knowledge.quad1.local 10.0.0.2
# Then copy ca.pem and each host's <name>.pem / <name>-key.pem to /etc/kgadapt/tls/
# on that host (the key readable by the kgadapt user only). Keep ca-key.pem offline.
set -euo pipefail
out=${1:?usage: $0 OUT_DIR [ROBOT [ROUTER_NAME...]]}
robot=${2:-quad1}
shift $(( $# >= 2 ? 2 : $# ))
routers=("$@")
[ ${#routers[@]} -gt 0 ] || routers=("knowledge.$robot.local" localhost 127.0.0.1)

mkdir -p "$out"
cd "$out"
umask 077
if [ ! -f ca.pem ]; then
    openssl req -x509 -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes -days 3650 \
        -subj "/CN=$robot CA" -keyout ca-key.pem -out ca.pem 2>/dev/null
fi

issue() {  # issue CN NAME... : a certificate for CN, valid for the given DNS names / IP addresses
    local cn=$1; shift
    local san="" name
    for name in "$@"; do
        if [[ $name =~ ^[0-9.]+$ || $name == *:* ]]; then san+="IP:$name,"; else san+="DNS:$name,"; fi
    done
    openssl req -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes -subj "/CN=$cn" \
        -keyout "$cn-key.pem" -out "$cn.csr" 2>/dev/null
    # serverAuth and clientAuth: with mutual TLS every process is a client, the router also a server.
    printf 'subjectAltName=%s\nextendedKeyUsage=serverAuth,clientAuth\nbasicConstraints=CA:FALSE\n' "${san%,}" > "$cn.ext"
    openssl x509 -req -in "$cn.csr" -CA ca.pem -CAkey ca-key.pem -CAcreateserial -days 825 \
        -extfile "$cn.ext" -out "$cn.pem" 2>/dev/null
    rm -f "$cn.csr" "$cn.ext"
    echo "$out/$cn.pem (SAN ${san%,})"
}

issue "$robot-knowledge" "${routers[@]}"
issue "$robot-onboard" "onboard.$robot.local"
issue "$robot-remote" "remote.$robot.local"
issue "$robot-operator" "operator.$robot.local"
for cert in ca.pem "$robot"-{knowledge,onboard,remote,operator}.pem; do chmod 644 "$cert"; done
