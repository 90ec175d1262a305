"""``/proc/<pid>/stat`` read for a real process whose command name holds what would mislead a naive split."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess

import psutil
import pytest

from kgadapt.shared import proc_stat


@pytest.fixture
def oddly_named(tmp_path):
    # The kernel's command name is the executable's base name (up to 15 bytes): ") S (1 2" puts a space, a
    # closing parenthesis and a fake state inside the parentheses.
    program = tmp_path / ") S (1 2"
    shutil.copy(shutil.which("sleep"), program)
    child = subprocess.Popen([str(program), "30"])
    try:
        yield child
    finally:
        child.kill()
        child.wait()


def test_the_fields_are_split_after_the_last_parenthesis(oddly_named):
    assert psutil.Process(oddly_named.pid).name() == ") S (1 2"
    os.kill(oddly_named.pid, signal.SIGSTOP)
    _, status = os.waitpid(oddly_named.pid, os.WUNTRACED)  # the signal is delivered later; this waits for it
    assert os.WIFSTOPPED(status)
    try:
        assert proc_stat.state_of(oddly_named.pid) == "T"
    finally:
        os.kill(oddly_named.pid, signal.SIGCONT)
    fields = proc_stat.stat_fields(oddly_named.pid)
    assert int(fields[1]) == os.getpid()  # (4) the parent
    ticks = os.sysconf("SC_CLK_TCK")
    started = psutil.boot_time() + int(fields[proc_stat.START_TIME]) / ticks
    assert abs(started - psutil.Process(oddly_named.pid).create_time()) < 2 / ticks


def test_the_argument_area_of_this_process_holds_its_command_line():
    fields = proc_stat.stat_fields()
    start, end = int(fields[proc_stat.ARG_START]), int(fields[proc_stat.ARG_END])
    with open("/proc/self/cmdline", "rb") as cmdline:
        assert end - start == len(cmdline.read())


def test_a_process_that_is_gone_raises_file_not_found(oddly_named):
    oddly_named.kill()
    oddly_named.wait()
    with pytest.raises(FileNotFoundError):
        proc_stat.state_of(oddly_named.pid)
