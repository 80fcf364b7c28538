"""The auction house over HTTP, the job backend and the `srd` command line."""
