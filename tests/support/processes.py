"""Real ``srd serve`` processes for the crash, restart and replica tests."""

from __future__ import annotations

import secrets
from pathlib import Path

from server.launch import ServerProcess


def server_pair(
    database_url: str, folder: Path, extra_env: dict[str, str] | None = None
) -> tuple[tuple[ServerProcess, ServerProcess], dict[str, str]]:
    """Two servers on one database and one data folder with one fresh operator token (not
    started): a restart's first and second life, or two replicas. Also the admin header."""
    token = secrets.token_hex(16)
    a, b = (
        ServerProcess(
            database_url=database_url,
            data_dir=folder / "data",
            admin_token=token,
            extra_env=extra_env,
            log_path=folder / f"serve-{name}.log",
        )
        for name in ("a", "b")
    )
    return (a, b), {"Authorization": f"Bearer {token}"}
