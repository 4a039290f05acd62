"""Test support: paths and real service processes (see :mod:`services.common.launch`)."""

from __future__ import annotations

from services.common.launch import ROOT, ServiceProcess, free_port, running_service

__all__ = ["ROOT", "ServiceProcess", "free_port", "running_service"]
