#!/usr/bin/env bash
# Make the TLS certificates of one robot: a thin wrapper around `kgadapt certs`
# (docs/security.md), kept for the command line it always had.
#
#   deploy/tls/make-certs.sh OUT_DIR [ROBOT [ROUTER_NAME...]]
#   e.g. deploy/tls/make-certs.sh ./tls quad1 knowledge.quad1.local 10.0.0.2
#
# writes ca.pem, ca-key.pem and <robot>-{knowledge,onboard,remote,operator}.pem
# with their -key.pem into OUT_DIR, named as deploy/zenoh/*.json5 expect them
# under /etc/kgadapt/tls/. ROUTER_NAMEs go into the knowledge certificate's SAN
# (default knowledge.ROBOT.local, localhost, 127.0.0.1). A CA already in
# OUT_DIR is reused, as this script always did; `kgadapt certs` itself refuses
# to touch an existing CA unless told --use-ca or --force.
#
# Which kgadapt: $KGADAPT if set, else `kgadapt` on the PATH, else this
# checkout's .venv, else `python3 -m kgadapt`.
set -euo pipefail
out=${1:?usage: $0 OUT_DIR [ROBOT [ROUTER_NAME...]]}
robot=${2:-quad1}
shift $(( $# >= 2 ? 2 : $# ))

args=(certs "$out" --robot "$robot")
for name in "$@"; do args+=(--router-address "$name"); done
[ -f "$out/ca.pem" ] && args+=(--use-ca)

here=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
if [ -n "${KGADAPT:-}" ]; then
    exec $KGADAPT "${args[@]}"
elif command -v kgadapt >/dev/null 2>&1; then
    exec kgadapt "${args[@]}"
elif [ -x "$here/../../.venv/bin/kgadapt" ]; then
    exec "$here/../../.venv/bin/kgadapt" "${args[@]}"
else
    exec python3 -m kgadapt "${args[@]}"
fi
