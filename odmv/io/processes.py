"""Processes the apps start end with them: a killed parent (``kill -9``, a closed terminal)
never leaves a child rendering or training on into folders that a rerun then writes too."""

from __future__ import annotations

import os
import signal
import subprocess
import sys


def die_with_parent(parent: int | None, sig: int = signal.SIGKILL) -> None:
    """Have the kernel send ``sig`` to this process when ``parent`` dies (Linux; elsewhere a
    no-op). Exits at once if the parent is already gone."""
    if sys.platform != "linux" or parent is None:
        return
    import ctypes

    pr_set_pdeathsig = 1
    ctypes.CDLL(None, use_errno=True).prctl(pr_set_pdeathsig, int(sig))
    if os.getppid() != parent:  # the parent died before the request took effect
        os._exit(1)


def run_child(cmd: list[str], log) -> subprocess.CompletedProcess:
    """Run ``cmd`` with its output into the open file ``log``; if this process dies first, the
    child gets SIGTERM (a training then stops at its step's end, releasing its run folder)."""
    parent = os.getpid()
    return subprocess.run(
        cmd,
        stdout=log,
        stderr=subprocess.STDOUT,
        check=False,
        preexec_fn=lambda: die_with_parent(parent, signal.SIGTERM),
    )
