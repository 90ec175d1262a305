"""The reliability and soak benches' orphan check knows the launchers' idle pool members (issue 32).

An idle member is the launcher's grandchild (its intermediate process is the launcher's child), not
the agent's child, so the check asks the deployers which pids are idle members and holds a detector
program to be one only where a live agent's deployer names it and it sits below that agent's launcher.
"""

from __future__ import annotations

from kgadapt.bench.reliability_bench import DetectorProcess, held_pool_members

AGENT, LAUNCHER, MIDDLE, MEMBER = 100, 200, 300, 301
TREE = {MEMBER: [MIDDLE, LAUNCHER, AGENT, 1], 400: [AGENT, 1], 500: [1], 600: [MIDDLE, LAUNCHER, 1]}


def ancestors(pid: int) -> list[int]:
    return TREE.get(pid, [])


def test_an_idle_member_a_live_agent_holds_is_no_orphan_and_anything_else_still_is():
    member = DetectorProcess(MEMBER, MIDDLE, "onboard", "?")
    adopted = DetectorProcess(500, 1, "onboard", "gone-agent-detector")  # re-parented to init: an orphan
    named = {MEMBER: LAUNCHER, 500: LAUNCHER}
    assert held_pool_members([member, adopted], named, agents={AGENT}, ancestors=ancestors) == {MEMBER}
    # Not named by a deployer: not held, whatever its place in the tree.
    assert held_pool_members([member], {}, agents={AGENT}, ancestors=ancestors) == set()
    # Named, but its agent is gone (the launcher's parent is no live agent): an orphan.
    assert held_pool_members([member], named, agents={999}, ancestors=ancestors) == set()
    # Named with another launcher than the one above it: not held.
    assert held_pool_members([member], {MEMBER: 777}, agents={AGENT}, ancestors=ancestors) == set()
    # Below a launcher whose parent is no agent (a launcher left behind): not held.
    stray = DetectorProcess(600, MIDDLE, "onboard", "?")
    assert held_pool_members([stray], {600: LAUNCHER}, agents={AGENT}, ancestors=ancestors) == set()
