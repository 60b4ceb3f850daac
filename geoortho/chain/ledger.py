"""The project's ledger, ``run.json``: what each stage was run with (its fingerprint: options, the content
hashes of its inputs, the software versions) and what it made; paths in it kept as ``PROJECT/...``.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from geoortho.chain.stages import Stage
from geoortho.core.outputs import write_json
from geoortho.errors import InputError
from geoortho.photos.metadata import list_images

LEDGER_NAME = "run.json"
LEDGER_VERSION = 2
#: Prefix of a path inside the project, as the ledger keeps it.
PROJECT_PREFIX = "PROJECT/"


# --- content hashes ------------------------------------------------------------------------------


#: How much of a file's head is read on every run to trust its cached hash: a photo's EXIF/XMP
#: lies in it, and a geotagger writing it in place may keep the size and the time stamp
#: (``exiftool -P``).
HEAD_BYTES = 1 << 16


class Hasher:
    """SHA-256 of files and folders (sorted relative names + contents), cached by size, mtime and
    the file's head (its first 64 KiB, where a photo's metadata is), so that a second run over
    unchanged photos reads 64 KiB of each and no more."""

    def __init__(self, cache: dict[str, list[Any]] | None = None) -> None:
        self.cache: dict[str, list[Any]] = dict(cache) if isinstance(cache, dict) else {}
        self.bytes_read = 0
        # files checked in this run, by their stat: the photos are inputs of four stages and the
        # products are checked again when reused; a file rewritten since has another stat
        self._checked: dict[tuple[str, int, int, int], str] = {}

    def file(self, path: Path) -> str:
        st = path.stat()
        key = str(path.resolve())
        seen = (key, st.st_size, st.st_mtime_ns, st.st_ino)
        if seen in self._checked:
            return self._checked[seen]
        with open(path, "rb") as f:
            first = f.read(HEAD_BYTES)
            head = hashlib.sha256(first).hexdigest()
            hit = self.cache.get(key)
            if isinstance(hit, list) and hit[:2] == [st.st_size, st.st_mtime_ns] and hit[3:4] == [head]:
                self.bytes_read += len(first)
                digest = str(hit[2])
            else:
                h = hashlib.sha256(first)
                for block in iter(lambda: f.read(1 << 20), b""):
                    h.update(block)
                self.bytes_read += st.st_size
                digest = h.hexdigest()
                self.cache[key] = [st.st_size, st.st_mtime_ns, digest, head]
        self._checked[seen] = digest
        return digest

    def photos(self, folder: Path) -> str:
        """The photos of a folder as the stages read them (its image files, not below it): notes or
        a project folder beside them change nothing."""

        h = hashlib.sha256()
        for f in list_images(folder):
            h.update(f.name.encode() + b"\0" + self.file(f).encode() + b"\n")
        return h.hexdigest()

    def path(self, path: Path) -> str:
        if path.is_file():
            return self.file(path)
        if not path.is_dir():
            raise InputError("no such file or folder", path=path)
        h = hashlib.sha256()
        for f in sorted(p for p in path.rglob("*") if p.is_file() and not p.name.startswith(".")):
            h.update(f.relative_to(path).as_posix().encode() + b"\0" + self.file(f).encode() + b"\n")
        return h.hexdigest()


def software_versions() -> dict[str, str]:
    from importlib.metadata import PackageNotFoundError, version

    out = {}
    for name in ("geoortho", "pycolmap", "opencv-contrib-python-headless", "rasterio", "numpy"):
        try:
            out[name] = version(name)
        except PackageNotFoundError:
            continue
    return out


# --- paths as the ledger keeps them --------------------------------------------------------------


def to_ledger(v: Any, root: Path) -> Any:
    """Paths (and path strings) inside the project as ``PROJECT/...``; the rest as JSON values."""
    if isinstance(v, dict):
        return {k: to_ledger(x, root) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [to_ledger(x, root) for x in v]
    if isinstance(v, Path) or (isinstance(v, str) and os.path.isabs(v)):
        try:
            return PROJECT_PREFIX + Path(v).resolve().relative_to(root.resolve()).as_posix()
        except ValueError:
            return str(v)
    return v


def from_ledger(v: Any, root: Path) -> Any:
    """The inverse of :func:`to_ledger`: ``PROJECT/...`` back to a path string under ``root``."""
    if isinstance(v, dict):
        return {k: from_ledger(x, root) for k, x in v.items()}
    if isinstance(v, list):
        return [from_ledger(x, root) for x in v]
    if isinstance(v, str) and v.startswith(PROJECT_PREFIX):
        return str(root / v[len(PROJECT_PREFIX) :])
    return v


# --- the ledger ----------------------------------------------------------------------------------


class Ledger:
    """``PROJECT/run.json``: per stage its status, fingerprint, options, input hashes, outputs,
    seconds, peak memory and warnings; the runs; written atomically after every change of status."""

    def __init__(self, path: Path, force: bool = False) -> None:
        self.path = path
        self.data: dict[str, Any] = {"version": LEDGER_VERSION, "stages": {}, "runs": [], "hash_cache": {}}
        if path.is_file():
            try:
                loaded = json.loads(path.read_text())
                why = ledger_problem(loaded)
            except (ValueError, UnicodeDecodeError) as e:
                why = f"not JSON ({' '.join(str(e).split())})"
            if why and not force:
                raise InputError(
                    f"not a run ledger this version reads: {why}; give --force to start the project again",
                    path=path,
                )
            if not why:
                self.data = {**self.data, **loaded}

    def stage(self, name: str) -> dict[str, Any]:
        return dict(self.data["stages"].get(name, {}))

    def set_stage(self, name: str, record: dict[str, Any]) -> None:
        self.data["stages"][name] = record
        self.save()

    def save(self) -> None:

        write_json(self.path, self.data)


def ledger_problem(data: Any) -> str:
    """What is wrong with a ``run.json`` (a hand edit, another version); "" when nothing."""
    if not isinstance(data, dict):
        return f"it holds a {type(data).__name__}, not an object"
    if data.get("version") != LEDGER_VERSION:
        return f"version {data.get('version')!r}, not {LEDGER_VERSION}"
    kinds = {"stages": dict, "runs": list, "hash_cache": dict}
    for key, kind in kinds.items():
        if key in data and not isinstance(data[key], kind):
            return f"'{key}' is a {type(data[key]).__name__}, not {'an object' if kind is dict else 'a list'}"
    bad = [k for k, v in (data.get("stages") or {}).items() if not isinstance(v, dict)]
    if bad:
        return f"stage '{bad[0]}' is not an object"
    fields: dict[str, tuple[type, ...]] = {
        "status": (str,), "fingerprint": (str,), "outputs": (dict,), "values": (dict,), "inputs": (dict,),
        "seconds": (int, float), "started": (int, float), "warnings": (list,), "products": (dict,),
        "versions": (dict,),
    }  # fmt: skip
    for name, record in (data.get("stages") or {}).items():
        for key, allowed in fields.items():
            value = record.get(key)
            if value is not None and (not isinstance(value, allowed) or isinstance(value, bool)):
                return f"stage '{name}': '{key}' is a {type(value).__name__}"
    if any(not isinstance(r, dict) for r in data.get("runs") or []):
        return "a run record is not an object"
    if not isinstance(data.get("problems", []), list) or not isinstance(data.get("current_run", {}), dict):
        return "'problems' or 'current_run' is of the wrong type"
    return ""


@dataclass(frozen=True)
class StageRun:
    """What happened to one stage in this run."""

    name: str
    status: str  # "ran", "reused", "skipped" (does not apply), "failed", "not run" (after a failure)
    seconds: float
    outputs: dict[str, Any]


def fingerprint_of(
    stage: Stage, values: dict[str, Any], hashes: dict[str, str], versions: dict[str, str], root: Path
) -> str:
    # files read count by content only: a photo folder moved or given by another path is the same input
    record = {
        "stage": stage.name,
        "values": to_ledger({k: v for k, v in sorted(values.items()) if k not in hashes}, root),
        "inputs": hashes,
        "versions": versions,
    }
    return hashlib.sha256(json.dumps(record, sort_keys=True, default=str).encode()).hexdigest()


def outputs_there(outputs: dict[str, Any]) -> bool:
    """Every path the stage reported still exists (a product removed by hand is made again)."""
    for v in outputs.values():
        if isinstance(v, str) and os.path.isabs(v) and not Path(v).exists():
            return False
    return True


def product_digests(outputs: dict[str, Any], hasher: Hasher) -> dict[str, str]:
    """Each product file or folder a stage made, by its output name: its digest when made."""
    return {
        k: hasher.path(Path(v))
        for k, v in outputs.items()
        if isinstance(v, str) and os.path.isabs(v) and Path(v).exists()
    }


def products_intact(record: dict[str, Any], root: Path, hasher: Hasher) -> bool:
    """Every product is as its stage left it: one truncated, replaced or edited by hand is made again
    (and what reads it after it)."""
    outputs = from_ledger(record.get("outputs", {}), root)
    for k, digest in (record.get("products") or {}).items():
        path = outputs.get(k)
        if not isinstance(path, str) or not Path(path).exists() or hasher.path(Path(path)) != digest:
            return False
    return True
