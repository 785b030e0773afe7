"""Custom GTSAM factors for MISR calibration: pure residual/Jacobian functions + thin adapters."""

from __future__ import annotations

__all__: list[str] = []
