"""Imported by the fork server only, first of its preloads (``server.work.pool.PRELOAD``): the
fork server dies the moment the API process that started it does.

Linux sends the parent-death signal (SIGKILL here) when the thread that started the process
ends; ``server.work.pool`` starts the fork server from a thread that lives as long as the API
process. The fork server's children arm the same signal against the fork server, so a
``kill -9`` of the API ends the fork server and then every worker within the kernel, before any
of them could run another line.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import signal
import sys

PR_SET_PDEATHSIG = 1

if sys.platform.startswith("linux"):
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    if os.getppid() == 1:  # the API process died before the signal was armed
        os._exit(70)
