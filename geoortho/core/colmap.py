"""pycolmap, loaded as geoortho needs it (one place: every stage that reads or makes a COLMAP
model takes it from here)."""

from __future__ import annotations

import os
import signal
import sys
import threading
from typing import Any

from geoortho.errors import interrupted
from geoortho.feedback import reclaim_signal_handlers

__all__ = ["load_pycolmap"]


def load_pycolmap() -> Any:
    """pycolmap as every geoortho caller needs it: Python's SIGTERM handler taken back from glog,
    COLMAP's INFO logging off."""
    # glog puts its failure handler on SIGTERM part-way through the import: a SIGTERM inside that
    # window killed the process with a C++ dump (4 of 30 tries). Held here, in this thread, until
    # Python's handler is back. That narrows the window for a script; it cannot close it, as native
    # threads started earlier (OpenBLAS's) may still take the signal (8 of 40). The CLI closes it by
    # holding the signals from its first line (processing.cli.main), and loads pycolmap there.
    held = threading.current_thread() is threading.main_thread() and "pycolmap" not in sys.modules
    before = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM}) if held else None
    try:
        try:
            import pycolmap
        except RuntimeError as e:
            if interrupted(e):  # a Ctrl-C during the C++ backend's start-up, wrapped twice on its way
                raise KeyboardInterrupt from None
            raise
        reclaim_signal_handlers()
    finally:
        if before is not None:
            signal.pthread_sigmask(signal.SIG_SETMASK, before)
    # COLMAP logs every image and iteration at INFO, and its warnings reached stderr between
    # geoortho's own lines (under --quiet too); geoortho's feedback says what matters. Never to log
    # files: glog leaves one per run in the temp folder.
    if os.environ.get("GEOORTHO_COLMAP_LOG") is None:
        pycolmap.logging.minloglevel = int(pycolmap.logging.ERROR)
        pycolmap.logging.stderrthreshold = int(pycolmap.logging.FATAL)
    for level in (pycolmap.logging.INFO, pycolmap.logging.WARNING, pycolmap.logging.ERROR):
        pycolmap.logging.set_log_destination(level, "")
    pycolmap.logging.logtostderr = os.environ.get("GEOORTHO_COLMAP_LOG") is not None
    return pycolmap
