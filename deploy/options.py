"""The deployer's command-line flags, importable without Zenoh or psutil.

Agent commands register their flags at ``kgadapt`` start-up, where heavy
imports are not wanted (kgadapt/cli.py); the settings are built later by
:func:`kgadapt.deploy.deployer.settings_from_args`.
"""

from __future__ import annotations

import argparse

# Idle detectors per kind of start an agent's launcher keeps by default: one, so the first start of a kind
# (a failover's) is a hand-over, not a fork. It costs the host an idle member (RSS 63 MiB, of which 9 MiB
# its own) and the launcher's fork above it (RSS 31 MiB, 2 MiB its own), both yielded to any start.
DEFAULT_POOL = 1


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The deployer's flags for agent commands (``kgadapt onboard``, ``kgadapt remote``, ``kgadapt deploy serve``)."""
    group = parser.add_argument_group("deployer")
    group.add_argument("--ready-timeout", type=float, default=15.0, metavar="S",
                       help="seconds a started process has to announce it is ready (default 15)")
    group.add_argument("--max-restarts", type=int, default=3, metavar="N",
                       help="restarts of a crashed process before it is reported failed (default 3)")
    group.add_argument("--stop-timeout", type=float, default=3.0, metavar="S",
                       help="seconds after SIGINT, and again after SIGTERM, before escalating (default 3)")
    group.add_argument("--detector-zenoh-config", metavar="FILE",
                       help="Zenoh configuration of the processes this deployer starts (the shipped "
                       "<host>-detector.json5: the host's detector certificate); default: the agent's own")
    group.add_argument("--profile-interval", type=float, default=1.0, metavar="S",
                       help="seconds between memory/CPU samples of each process (default 1)")
    group.add_argument("--no-launcher", action="store_true",
                       help="start every detector as a new interpreter instead of forking it from the host's "
                            "launcher (a process with the detector's code already imported)")
    group.add_argument("--pool", type=int, default=DEFAULT_POOL, metavar="N",
                       help="idle detectors the launcher keeps, with their Zenoh session open, for each kind of "
                            "start the graph says may run on this host (a start, a failover's too, then takes "
                            "one); within the memory budget, each counted at the least declared memory of its "
                            f"kind's configurations (default {DEFAULT_POOL}; 0: none)")
