"""Where ../shared/data/real is (tests/ and tests_qgis/ share this)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

# ../shared/data/real beside the checkout; GEOORTHO_REAL_DATA or the team's /work/shared when cloned elsewhere
_CANDIDATES = [Path(os.environ["GEOORTHO_REAL_DATA"])] if os.environ.get("GEOORTHO_REAL_DATA") else []
_CANDIDATES += [Path(__file__).resolve().parents[2] / "shared" / "data" / "real", Path("/work/shared/data/real")]
REAL_DATA = next((p for p in _CANDIDATES if p.exists()), _CANDIDATES[0])


def real_data(name: str) -> Path:
    """A folder of ../shared/data/real, or skip with the reason."""
    path = REAL_DATA / name
    if not path.exists():
        pytest.skip(f"real data folder {path} is absent")
    return path
