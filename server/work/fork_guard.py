"""Imported by the fork server only, first of its preloads (``server.work.pool.PRELOAD``): the
fork server dies the moment the API process that started it does.

Linux sends the parent-death signal (SIGKILL here) when the thread that started the process
ends; ``server.work.pool`` starts the fork server from a thread that lives as long as the API
process. The fork server's children arm the same signal against the fork server, so a
``kill -9`` of the API ends the fork server and then every worker within the kernel, before any
of them could run another line.
"""

from __future__ import annotations

from server.work.pool import arm_parent_death_signal

# No check of the parent's pid after arming: the API may be pid 1 (a container's command). Had
# the API died before this line, the fork server would end anyway, at the end of its "alive"
# pipe, before it forks anything.
arm_parent_death_signal()
