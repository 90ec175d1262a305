"""The router keeps nothing of a client killed with kill -9 (Zenoh's shared memory stays off).

With Zenoh 1.x defaults, a client on the same machine puts every message above
3 KiB into a 16 MiB shared-memory pool that the router maps; a client killed
-9 leaves that mapping in the router for good (19 MiB per onboard agent
restart in the soak). A router and clients opened through kgadapt.shared.session must
not do that.
"""

from __future__ import annotations

import os
import signal
import sys
import threading

from kgadapt.shared.session import ZenohSettings, build_config, open_session
from tests.conftest import free_port
from tests.support import Child

KILLS = 3
# A client that publishes messages above Zenoh's shared-memory threshold (3 KiB),
# opened as the agents open theirs (kgadapt.shared.session's defaults, client mode).
CLIENT = """
import sys, time
from kgadapt.shared.readiness import announce_ready
from kgadapt.shared.session import ZenohSettings, open_session
session = open_session(ZenohSettings(mode="client", connect=(sys.argv[1],)))
publisher = session.declare_publisher(sys.argv[2])
announce_ready()
while True:
    publisher.put(b"x" * 20000)
    time.sleep(0.01)
"""


def shm_mappings() -> int:
    with open("/proc/self/maps") as maps:
        return sum(1 for line in maps if "/dev/shm/" in line)


def rss_mib() -> float:
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    raise AssertionError("no VmRSS in /proc/self/status")


def test_shared_memory_is_off_by_default_and_a_file_can_set_it(tmp_path):
    assert build_config(ZenohSettings()).get_json("transport/shared_memory/enabled") == "false"
    own = tmp_path / "shm.json5"
    own.write_text('{ transport: { shared_memory: { enabled: true } } }')
    assert build_config(ZenohSettings(config_file=str(own))).get_json("transport/shared_memory/enabled") == "true"


def test_router_maps_nothing_of_clients_killed_by_sigkill(tmp_path):
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    key = f"kgadapt/shm{os.getpid()}/status"
    router = open_session(ZenohSettings(mode="router", listen=(endpoint,)))
    received = threading.Semaphore(0)
    subscriber = router.declare_subscriber(key, lambda sample: received.release())
    try:
        mapped_before, rss_before = shm_mappings(), rss_mib()
        for n in range(KILLS):
            child = Child([sys.executable, "-c", CLIENT, endpoint, key], f"client{n}", tmp_path)
            try:
                child.wait_ready()
                for _ in range(20):  # large messages have reached the router
                    assert received.acquire(timeout=30), f"client {n}: no messages reached the router"
            finally:
                child.process.send_signal(signal.SIGKILL)
                child.process.wait(timeout=30)
        mapped, grown = shm_mappings() - mapped_before, rss_mib() - rss_before
        assert mapped == 0, f"the router mapped {mapped} shared-memory segments of {KILLS} dead clients"
        # With shared memory on, each dead client leaves about 19 MiB in the router.
        assert grown < 10 * KILLS, f"router RSS grew {grown:.0f} MiB over {KILLS} killed clients"
    finally:
        subscriber.undeclare()
        router.close()
