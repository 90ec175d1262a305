"""The README's "Running the parts" block, typed line by line as a newcomer would, each output checked.

The lines come from README.md itself (between the ``newcomer-test`` markers),
so the README cannot drift from the code: a changed command, flag or output
breaks this test. A line starting with ``.`` or ``export`` changes the shell,
so it is kept for every later line, as in one terminal.
"""

from __future__ import annotations

import json
import re

import pytest

from kgadapt.shared.readiness import READY_TOKEN
from tests.support import REPO, wait_for

# What each command's output must show, by the line's start (every line must be covered).
EXPECTED = {
    ". .venv/bin/activate": None,
    "kgadapt knowledge load": r"loaded \d+ model files",
    "kgadapt perception calibrate": r"recorded \d+ CALIBRATED relations in embedded:",
    "kgadapt knowledge serve": r"knowledge service ready: robot quad1",
    "kgadapt remote": r"remote agent ready: robot quad1, host remote",
    "kgadapt flight fake-fc": re.escape(READY_TOKEN),
    "kgadapt onboard": r"onboard agent ready: robot quad1, host onboard",
    "kgadapt status": r"(?s)onboard +up since .*remote +up since .*marker_detection_\w+@onboard +ready.*"
                      r"band (day|dusk|dark).*calibrated \d+%.*in the air.*-> marker_detection_\w+@onboard.*"
                      r"no problems seen",
    "kgadapt why": r"runs configuration marker_detection_\w+ on onboard",
    "kgadapt ask placement": r"marker_detection_dark +detector_dark +(onboard|remote)",
    "kgadapt deploy list": r"onboard +marker_detection_\w+-onboard-\w+ +ready",
    "kgadapt squeeze": r"onboard: reserved 0 MiB, free \d+ of 700 MiB",
}


def readme_lines() -> list[str]:
    text = (REPO / "README.md").read_text()
    block = re.search(r"<!-- newcomer-test: begin -->\s*```sh\n(.*?)```\s*<!-- newcomer-test: end -->", text, re.S)
    assert block, "README.md lost its newcomer-test block"
    lines = []
    for raw in block.group(1).splitlines():
        line = re.sub(r"\s+#.*$", "", raw).strip()  # comments are for people
        if line:
            lines.append(line)
    return lines


@pytest.mark.timeout(300)  # several robots' processes on a shared 2-core machine
def test_the_readme_commands_run_in_order_and_say_what_the_readme_says(terminal):
    lines = readme_lines()
    uncovered = [line for line in lines if not any(line.startswith(k) for k in EXPECTED)]
    assert not uncovered, f"README lines this test does not check: {uncovered}"
    shell_state: list[str] = []
    for line in lines:
        expected = next(v for k, v in EXPECTED.items() if line.startswith(k))
        typed = " && ".join([*shell_state, line.rstrip("& ").rstrip()])
        if line.startswith((". ", "source ", "export ")):
            assert terminal.run(typed).returncode == 0, line
            shell_state.append(line)
            continue
        if line.endswith("&"):
            job = terminal.start(line.rstrip("& ").rstrip(), prelude="".join(f"{s}; " for s in shell_state))
            assert re.search(expected, job.text()), f"{line!r} printed:\n{job.text()[-2000:]}"
            continue
        if line.startswith("kgadapt status"):
            # The first decision comes a moment after the onboard agent is ready: look again, as a person would.
            def settled():
                result = terminal.run(typed, timeout=60)
                return result if result.returncode == 0 and re.search(expected, result.stdout) else None

            try:
                result = wait_for(settled, 45, "kgadapt status to show the running robot with no problem", interval=1)
            except AssertionError:
                last = terminal.run(typed, timeout=60)
                raise AssertionError(f"{line!r} exit {last.returncode}:\n{last.stdout}\n{last.stderr}") from None
            json_out = json.loads(terminal.run(typed.replace("--once", "--json"), timeout=60).stdout)
            assert {h["host"] for h in json_out["hosts"] if h["up"]} == {"onboard", "remote"}
            continue
        result = terminal.run(typed)
        assert result.returncode == 0, f"{line!r} exit {result.returncode}:\n{result.stdout}\n{result.stderr}"
        if expected is not None:
            assert re.search(expected, result.stdout), f"{line!r} printed:\n{result.stdout}\n{result.stderr}"
    # Ctrl-C stops each long-running command, and it says what it stopped.
    terminal.interrupt_all()
    for job in terminal.background:
        assert job.stopped_in_s is not None, f"{job.line!r} did not stop on Ctrl-C"
        assert job.process.returncode in (0, 130), f"{job.line!r} exit {job.process.returncode}:\n{job.text()[-1500:]}"
    print({job.line.split(" &&")[-1][:40]: round(job.stopped_in_s or -1, 2) for job in terminal.background})
