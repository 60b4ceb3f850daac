"""The ground filters a DTM is made with: SMRF, cloth simulation, the cloud's own classification."""

from __future__ import annotations

import numpy as np

from geoortho.core.pointcloud import Chunk, PointSource
from geoortho.elevation.grid import (
    GROUND,
    Accumulator,
    Grid,
)
from geoortho.elevation.ground import SmrfParams, ground_mask, smrf_surface
from geoortho.errors import DependencyError


class GroundFilter:
    """A ground method as the two passes see it: it watches the points of pass 1,
    prepares between the passes, then says which points of pass 2 are ground."""

    #: The ground is known chunk by chunk in pass 1 already (the file's own classes).
    known_in_first_pass = False

    def __init__(self, src: PointSource, params: SmrfParams):
        self.src, self.params = src, params

    def observe(self, ch: Chunk) -> None:
        """Pass 1: one chunk of finite points."""

    def prepare(self) -> None:
        """Between the passes."""

    def ground(self, ch: Chunk) -> np.ndarray:
        """Pass 2 (pass 1 too when ``known_in_first_pass``): ground mask of a chunk of finite points."""
        raise NotImplementedError


class _SmrfGround(GroundFilter):
    """Pingel's SMRF on a minimum-elevation grid of its own cell size."""

    def __init__(self, src: PointSource, params: SmrfParams):
        super().__init__(src, params)
        xmin, ymin, _, xmax, ymax, _ = src.bounds
        self.grid = Grid.covering(xmin, ymin, xmax, ymax, params.cell_m / src.horizontal_m)
        self.zmin = Accumulator(self.grid, "min")
        self.surface: np.ndarray | None = None

    def observe(self, ch: Chunk) -> None:
        self.zmin.add(ch.x, ch.y, ch.z)

    def prepare(self) -> None:
        self.surface = smrf_surface(
            self.zmin.result(), self.grid.cell, self.params, self.src.horizontal_m, self.src.vertical_m
        )

    def ground(self, ch: Chunk) -> np.ndarray:
        assert self.surface is not None
        g = self.grid
        return ground_mask(
            ch.x, ch.y, ch.z, self.surface, g.x0, g.y0, g.cell, self.params, self.src.horizontal_m, self.src.vertical_m
        )


class _CsfGround(GroundFilter):
    """The cloth simulation filter: it needs every point at once, so pass 1 keeps them."""

    def __init__(self, src: PointSource, params: SmrfParams):
        super().__init__(src, params)
        self.xyz: list[np.ndarray] = []
        self.mask: np.ndarray | None = None
        self.offset = 0

    def observe(self, ch: Chunk) -> None:
        self.xyz.append(np.c_[ch.x, ch.y, ch.z])

    def prepare(self) -> None:
        self.mask = _csf(np.concatenate(self.xyz), self.src, self.params)
        self.xyz.clear()

    def ground(self, ch: Chunk) -> np.ndarray:
        assert self.mask is not None
        g = self.mask[self.offset : self.offset + len(ch.x)]
        self.offset += len(ch.x)
        return g


class _ClassificationGround(GroundFilter):
    """The file's own class 2."""

    known_in_first_pass = True

    def ground(self, ch: Chunk) -> np.ndarray:
        assert ch.classification is not None
        return np.asarray(ch.classification == GROUND)


#: ground_method -> its filter (a new method is a new entry, not a new branch in the passes).
GROUND_FILTERS: dict[str, type[GroundFilter]] = {
    "smrf": _SmrfGround,
    "csf": _CsfGround,
    "classification": _ClassificationGround,
}


def _csf(xyz: np.ndarray, src: PointSource, params: SmrfParams) -> np.ndarray:
    """Cloth simulation filter (Zhang et al. 2016; the ``cloth-simulation-filter`` package)."""
    try:
        import CSF
    except ImportError as e:
        raise DependencyError(
            "ground_method csf needs the cloth-simulation-filter package (pip install cloth-simulation-filter)"
        ) from e
    import contextlib
    import io

    c = CSF.CSF()
    c.params.bSloopSmooth = True
    c.params.cloth_resolution = params.cell_m / src.horizontal_m
    c.params.class_threshold = params.threshold_m / src.vertical_m
    c.params.rigidness = 2
    c.setPointCloud(xyz - xyz.min(axis=0))  # CSF works in float; keep the numbers small
    ground, other = CSF.VecInt(), CSF.VecInt()
    with contextlib.redirect_stdout(io.StringIO()):  # it prints its progress
        c.do_filtering(ground, other, exportCloth=False)
    mask = np.zeros(len(xyz), bool)
    mask[np.asarray(list(ground), np.int64)] = True
    return mask
