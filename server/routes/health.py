"""Liveness."""

from __future__ import annotations

from fastapi import APIRouter

from server.schemas import HealthPublic

router = APIRouter(tags=["health"])


@router.get("/healthz", operation_id="healthz")
async def healthz() -> HealthPublic:
    """The server is up."""
    return HealthPublic(status="ok")
