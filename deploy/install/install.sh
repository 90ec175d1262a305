#!/bin/sh
# Install kgadapt from this archive's wheelhouse, with no network.
#
# Makes a virtualenv (default /opt/kgadapt/venv) with `pip --no-index`, the
# `kgadapt` system user, /etc/kgadapt (configuration, TLS, Zenoh configs) and
# /var/lib/kgadapt (the store), and installs the systemd units pointed at the
# virtualenv. Run it again to upgrade: the virtualenv is replaced, existing
# configuration is kept.
set -eu

here=$(cd "$(dirname "$0")" && pwd)
prefix=/opt/kgadapt
extras=""
python=python3
etc=/etc/kgadapt
state=/var/lib/kgadapt
unit_dir=/etc/systemd/system
user=kgadapt
make_user=yes
units=yes

usage() {
    cat <<USAGE
usage: install.sh [options]
  --prefix DIR      where the virtualenv goes: DIR/venv (default $prefix)
  --extras LIST     extras to install, comma-separated: store, memgraph, certs
                    (default none: the onboard and remote agents; the knowledge
                    service's host needs --extras store)
  --python PATH     the Python 3.11+ to build the virtualenv with (default $python)
  --etc DIR         configuration directory (default $etc)
  --state DIR       state directory, the store's data (default $state)
  --unit-dir DIR    where the systemd units go (default $unit_dir)
  --no-units        do not install systemd units
  --no-user         do not create the '$user' system user (e.g. in a test)
USAGE
}

while [ $# -gt 0 ]; do
    case "$1" in
        --prefix) prefix=$2; shift 2 ;;
        --extras) extras=$2; shift 2 ;;
        --python) python=$2; shift 2 ;;
        --etc) etc=$2; shift 2 ;;
        --state) state=$2; shift 2 ;;
        --unit-dir) unit_dir=$2; shift 2 ;;
        --no-units) units=no; shift ;;
        --no-user) make_user=no; shift ;;
        -h|--help) usage; exit 0 ;;
        *) echo "install.sh: unknown option $1" >&2; usage >&2; exit 2 ;;
    esac
done

case ",$extras," in
    *[!a-z,]*) echo "install.sh: --extras $extras: use names from store, memgraph, certs" >&2; exit 2 ;;
esac
for extra in $(echo "$extras" | tr ',' ' '); do
    case "$extra" in
        store|memgraph|certs) ;;
        *) echo "install.sh: extra '$extra' is not in this archive (it has store, memgraph, certs)" >&2; exit 2 ;;
    esac
done

if ! "$python" -c 'import sys; sys.exit(sys.version_info < (3, 11))' 2>/dev/null; then
    echo "install.sh: $python is not Python 3.11 or newer (use --python PATH)" >&2
    exit 2
fi

venv="$prefix/venv"
echo "kgadapt: virtualenv $venv (offline, from $here/wheelhouse)"
mkdir -p "$prefix"
# A virtualenv names its own path inside, so it is built where it will live;
# the previous one is kept aside and put back if the install fails.
rm -rf "$venv.old"
[ -d "$venv" ] && mv "$venv" "$venv.old"
restore() {
    rm -rf "$venv"
    [ -d "$venv.old" ] && mv "$venv.old" "$venv"
    echo "install.sh: the install failed; the previous virtualenv (if any) is back" >&2
    exit 1
}
spec=kgadapt
[ -n "$extras" ] && spec="kgadapt[$extras]"
"$python" -m venv "$venv" || restore
"$venv/bin/python" -m pip install --quiet --no-index --find-links "$here/wheelhouse" \
    --disable-pip-version-check "$spec" || restore
rm -rf "$venv.old"

if [ "$make_user" = yes ] && ! getent passwd "$user" >/dev/null; then
    echo "kgadapt: system user $user"
    useradd --system --home-dir "$state" --no-create-home --shell /usr/sbin/nologin "$user"
fi

echo "kgadapt: configuration in $etc, state in $state"
mkdir -p "$etc/zenoh" "$etc/tls" "$state"
chmod 0750 "$etc/tls"
for f in "$here"/zenoh/*.json5; do
    [ -e "$etc/zenoh/$(basename "$f")" ] || cp "$f" "$etc/zenoh/"
done
if [ ! -e "$etc/kgadapt.env" ]; then
    cat > "$etc/kgadapt.env" <<ENV
# Read by the kgadapt units (EnvironmentFile); a value here wins over the unit's.
# The store of the knowledge service (default embedded:$state/store):
# KGADAPT_STORE=memgraph+s://127.0.0.1:7687?ca=$etc/tls/ca.pem
# What the onboard agent runs (the unit's default: adapt, camera 0, flight controller on USB):
# KGADAPT_ONBOARD_ARGS=--adapt --camera-source device:0 --fc /dev/ttyACM0:921600
# Extra arguments of the remote agent and of the knowledge service:
# KGADAPT_REMOTE_ARGS=--memory-budget 2G
# KGADAPT_KNOWLEDGE_ARGS=--workers 3
ENV
fi
if [ "$make_user" = yes ]; then
    chown "$user:$user" "$state"
    chgrp "$user" "$etc/tls"
fi

if [ "$units" = yes ]; then
    echo "kgadapt: systemd units in $unit_dir"
    mkdir -p "$unit_dir"
    for unit in "$here"/systemd/*.service; do
        sed -e "s|/opt/kgadapt/venv|$venv|g" -e "s|/etc/kgadapt|$etc|g" -e "s|/var/lib/kgadapt|$state|g" \
            "$unit" > "$unit_dir/$(basename "$unit")"
    done
    if [ -d /run/systemd/system ] && [ "$unit_dir" = /etc/systemd/system ]; then
        systemctl daemon-reload
    fi
fi

echo "kgadapt: $("$venv/bin/kgadapt" --version) in $venv"
echo "next: certificates and units, see docs/deploy.md (\"Running on a quadcopter and a remote host\")"
