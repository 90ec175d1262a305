"""What a ``--zenoh-config`` file says wins over our defaults; flags win over the file.

Our defaults (``shared/session.py``): multicast scouting off, a 1 s lease on hosts and 4 s on routers,
4 keep-alives a lease, no scouting delay, shared memory off. Each applies only where the file is silent.
"""

from __future__ import annotations

import json

import pytest

from kgadapt.shared.errors import ConfigError
from kgadapt.shared.session import HOST_LEASE_MS, ROUTER_LEASE_MS, ZenohSettings, build_config


def _value(config, key):
    return json.loads(config.get_json(key))


def test_a_files_lease_keep_alive_and_scouting_win_over_our_defaults(tmp_path):
    path = tmp_path / "own.json5"
    path.write_text("""{
      // an operator's choices, each one that our defaults would otherwise replace
      scouting: { delay: 200, multicast: { enabled: true } },
      transport: { link: { tx: { lease: 2500, keep_alive: 5 } } },
    }""")
    config = build_config(ZenohSettings(config_file=str(path)))
    assert _value(config, "transport/link/tx/lease") == 2500
    assert _value(config, "transport/link/tx/keep_alive") == 5
    assert _value(config, "scouting/multicast/enabled") is True
    assert _value(config, "scouting/delay") == 200


def test_where_a_file_is_silent_our_defaults_hold_by_the_files_mode(tmp_path):
    host, router = tmp_path / "host.json5", tmp_path / "router.json5"
    host.write_text('{ mode: "client", transport: { link: { tx: { keep_alive: 4 } } } }')
    router.write_text("{ mode: 'router' }")
    for path, lease in ((host, HOST_LEASE_MS), (router, ROUTER_LEASE_MS)):
        config = build_config(ZenohSettings(config_file=str(path)))
        assert _value(config, "transport/link/tx/lease") == lease, path.name
        assert _value(config, "scouting/multicast/enabled") is False
        assert _value(config, "scouting/delay") == 0
        assert _value(config, "transport/shared_memory/enabled") is False


def test_flags_still_win_over_the_file(tmp_path):
    path = tmp_path / "own.json5"
    path.write_text('{ mode: "peer", connect: { endpoints: ["tcp/127.0.0.1:9"] } }')
    config = build_config(ZenohSettings(config_file=str(path), mode="router", connect=("tcp/127.0.0.1:7",)))
    assert _value(config, "mode") == "router"
    assert _value(config, "connect/endpoints") == ["tcp/127.0.0.1:7"]
    assert _value(config, "transport/link/tx/lease") == ROUTER_LEASE_MS  # the flag's mode decides our default


def test_a_yaml_file_which_zenoh_would_take_is_refused_by_name(tmp_path):
    # We could not tell which keys it sets, so our defaults would silently replace the file's.
    path = tmp_path / "own.yaml"
    path.write_text("transport:\n  link:\n    tx:\n      lease: 2500\n")
    with pytest.raises(ConfigError) as caught:
        build_config(ZenohSettings(config_file=str(path)))
    assert str(path) in str(caught.value) and "give a JSON5 file" in str(caught.value)
