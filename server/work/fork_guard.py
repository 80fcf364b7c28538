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
import os
import signal

from server.work.pool import arm_parent_death_signal

# No check of the parent's pid after arming: the API may be pid 1 (a container's command). Had
# the API died before this line, the fork server would end anyway, at the end of its "alive"
# pipe, before it forks anything.
arm_parent_death_signal()

# It ends with the API (the signal above, or its "alive" pipe), never on its own: a SIGTERM or
# SIGINT to the server's process group, or to every process of the service, had ended it
# first, and the workers it had forked were reported dead (code 255), failing their jobs.
signal.signal(signal.SIGTERM, signal.SIG_IGN)
signal.signal(signal.SIGINT, signal.SIG_IGN)
if hasattr(os, "setpgrp"):
    with contextlib.suppress(OSError):
        os.setpgrp()
