"""What a survey's own run measured of its DSM's accuracy, read beside the DSM (a run's DSM is
PROJECT/dem/dsm.tif): the checkpoints' (else the GCPs') vertical RMSE and the noise on open ground.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

#: A DSM's noise is taken as correlated over patches this wide (metres: a dense matcher's window).
NOISE_CORRELATION_M = 1.0


def run_vertical_accuracy(dsm: Path) -> tuple[float, str]:
    """The run's checkpoints' vertical RMSE (else its GCPs'), and where it came from; NaN, "" when none."""
    report = _json(dsm.parent.parent / "sfm" / "report.json")
    for key, label in (("checkpoint_accuracy", "checkpoints"), ("gcp_accuracy", "GCPs")):
        acc = report.get(key) or {}
        z = acc.get("rmse_z_m")
        if isinstance(z, (int, float)) and math.isfinite(z) and int(acc.get("n") or 0) > 0:
            return float(z), f"vertical accuracy from the run's {acc.get('n')} {label} (RMSE {z:.3f} m)"
    return math.nan, ""


def run_noise(dsm: Path) -> float:
    """The run's dem stage's measure of the DSM's noise on open ground (metres), NaN when none."""
    ledger = _json(dsm.parent.parent / "run.json")
    value = (((ledger.get("stages") or {}).get("dem") or {}).get("outputs") or {}).get("ground_noise_m")
    return float(value) if isinstance(value, (int, float)) and math.isfinite(value) else math.nan


def run_dense_voxel_m(dsm: Path) -> float:
    """The run's dense cloud's voxel (metres): how finely its matcher placed an edge; NaN when none."""
    value = _json(dsm.parent.parent / "dense" / "dense_report.json").get("voxel_m")
    return float(value) if isinstance(value, (int, float)) and math.isfinite(value) else math.nan


def _json(path: Path) -> dict[str, Any]:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}
