"""What a survey's own run measured of its DSM's accuracy, read beside the DSM (a run's DSM is
PROJECT/dem/dsm.tif): the checkpoints' (else the GCPs') vertical RMSE and the noise on open ground.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

#: A DSM's noise is taken as correlated over patches this wide (metres: a dense matcher's window).
NOISE_CORRELATION_M = 1.0
#: A photogrammetric DSM puts a wall within this many of its dense cloud's voxels (the demo survey's
#: seven buildings: their volumes 0.2-15 % off, within 2 sigma with 2 voxels, up to 2.6 sigma with 1.4).
WALL_VOXELS = 2.0
#: A surface steeper than this (rise over run) is a wall: where it stands is known to a cell.
WALL_SLOPE = 1.0


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


def run_wall_place_m(dsm: Path) -> float:
    """How far the run that made ``dsm`` may have put a wall from where it stands (metres):
    WALL_VOXELS of its dense cloud's voxels; NaN where no run says."""
    return WALL_VOXELS * run_dense_voxel_m(dsm)


def wall_place_m(dsm: Path, cell_m: float) -> float:
    """:func:`run_wall_place_m`, a cell over the square root of 12 at least (and where no run says)."""
    place_m = run_wall_place_m(dsm)
    return max(cell_m / math.sqrt(12.0), place_m if math.isfinite(place_m) else 0.0)


def walls_sigma_m3(z_m: np.ndarray, inside: np.ndarray, cell_m: float, place_m: float) -> float:
    """The volume's uncertainty from where the DSM puts its walls (m³): the steep cells' rise,
    each wall's place uncertain by ``place_m`` (at least ``cell / sqrt(12)``), all together (a DSM
    that erodes or fattens an object does so on all its sides)."""
    gy, gx = np.gradient(z_m, cell_m)
    slope = np.hypot(gx, gy)
    steep = inside & np.isfinite(slope) & (slope > WALL_SLOPE)
    place = max(cell_m / math.sqrt(12.0), place_m if math.isfinite(place_m) else 0.0)
    return float(slope[steep].sum() * cell_m * cell_m * place)


def _json(path: Path) -> dict[str, Any]:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}
