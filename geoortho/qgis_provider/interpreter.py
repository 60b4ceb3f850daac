"""Find the Python that runs geoortho and ask it for the algorithm registry.

No qgis import here: this runs inside QGIS, but is tested without it too.
QGIS's own Python links QGIS's GDAL/GEOS/PROJ, so geoortho normally runs in
its own environment's interpreter, in a subprocess.
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import os
import shutil
import subprocess
import tempfile
from pathlib import Path
from typing import Any

__all__ = [
    "ENV_VAR",
    "InterpreterError",
    "clean_environment",
    "find_interpreter",
    "load_description",
    "HOW_TO_SET",
]

#: Environment variable naming the interpreter (for qgis_process and scripts).
ENV_VAR = "GEOORTHO_PYTHON"

HOW_TO_SET = (
    "set Processing > Options > Providers > geoortho > 'geoortho Python interpreter' "
    f"(or the environment variable {ENV_VAR}) to the python of the environment where "
    "geoortho is installed, e.g. /home/me/geoortho/.venv/bin/python"
)

#: Variables QGIS sets for its own Python, GDAL and PROJ; passed on, they would make
#: the geoortho environment load QGIS's libraries or data (e.g. an older proj.db).
_QGIS_ONLY_VARIABLES = (
    "PYTHONHOME",
    "PYTHONPATH",
    "PYTHONSTARTUP",
    "PROJ_LIB",
    "PROJ_DATA",
    "GDAL_DATA",
    "GDAL_DRIVER_PATH",
)


class InterpreterError(RuntimeError):
    """geoortho's interpreter is missing or cannot run geoortho."""


#: Where geoortho runs: a folder with no geoortho source in it (see PYTHONSAFEPATH).
NEUTRAL_CWD = tempfile.gettempdir()


def clean_environment() -> dict[str, str]:
    """os.environ without QGIS's Python/GDAL/PROJ variables, unbuffered UTF-8 output."""
    env = {k: v for k, v in os.environ.items() if k not in _QGIS_ONLY_VARIABLES}
    # `python -m` would put the current folder first on sys.path, so a geoortho
    # source folder there would shadow the installed one (Python >= 3.11).
    env["PYTHONSAFEPATH"] = "1"
    env["PYTHONUNBUFFERED"] = "1"
    env["PYTHONIOENCODING"] = "utf-8"
    return env


def _venv_python(root: Path) -> Path | None:
    for candidate in (root / "bin" / "python", root / "Scripts" / "python.exe"):
        if candidate.is_file():
            return candidate
    return None


def _from_importable_geoortho() -> Path | None:
    """The venv holding the geoortho this process can import, if any.

    ``sys.executable`` is no help inside QGIS (it is QGIS or whatever python3
    is first on PATH), so the venv is found from where the package lies: an
    installed package sits under ``<venv>/lib/pythonX.Y/site-packages``, a
    source checkout beside its ``.venv``.
    """
    spec = importlib.util.find_spec("geoortho")
    if spec is None or not spec.origin:
        return None
    package_dir = Path(spec.origin).resolve().parent
    for parent in package_dir.parents:
        if (parent / "pyvenv.cfg").is_file():
            return _venv_python(parent)
        checkout_venv = parent / ".venv"
        if (checkout_venv / "pyvenv.cfg").is_file() and (parent / "geoortho") == package_dir:
            return _venv_python(checkout_venv)
    return None


def _from_console_script() -> Path | None:
    """The interpreter in the shebang of the ``geoortho`` command on PATH."""
    script = shutil.which("geoortho")
    if script is None:
        return None
    try:
        with open(script, "rb") as f:
            first = f.readline(4096).decode("utf-8", "replace").strip()
    except OSError:
        return None
    if not first.startswith("#!"):
        return None
    candidate = Path(first[2:].strip().split()[0])
    return candidate if candidate.is_file() else None


def find_interpreter(configured: str | None = "") -> str:
    """The python to run geoortho with.

    In order: ``configured`` (the Processing setting), ``$GEOORTHO_PYTHON``,
    the environment of an importable geoortho, the shebang of the
    ``geoortho`` command on PATH. Raises :class:`InterpreterError` saying how
    to set it when none is found.
    """
    for source, value in (
        ("the setting 'geoortho Python interpreter'", configured),
        (f"${ENV_VAR}", os.environ.get(ENV_VAR, "")),
    ):
        if value:
            path = Path(value).expanduser()
            if not path.is_file() or not os.access(path, os.X_OK):
                raise InterpreterError(f"{source} is {value}, which is not an executable file; {HOW_TO_SET}")
            return str(path)
    for finder in (_from_importable_geoortho, _from_console_script):
        found = finder()
        if found is not None:
            return str(found)
    raise InterpreterError(f"geoortho's Python interpreter was not found; {HOW_TO_SET}")


def _package_signature(package_dir: str) -> str:
    """Changes when any module of the installed geoortho changes (upgrade, edit)."""
    h = hashlib.sha1()
    root = Path(package_dir)
    if not root.is_dir():
        return "missing"
    for path in sorted(root.rglob("*.py")):
        st = path.stat()
        h.update(f"{path.relative_to(root)}:{st.st_mtime_ns}:{st.st_size};".encode())
    return h.hexdigest()


def _interpreter_key(interpreter: str) -> str:
    st = Path(interpreter).stat()
    return f"{Path(interpreter).absolute()}:{st.st_mtime_ns}"


def _run_describe(interpreter: str, timeout_s: float) -> dict[str, Any]:
    cmd = [interpreter, "-m", "geoortho", "describe", "--json"]
    try:
        proc = subprocess.run(
            cmd,
            capture_output=True,
            text=True,
            encoding="utf-8",
            errors="replace",
            env=clean_environment(),
            cwd=NEUTRAL_CWD,
            timeout=timeout_s,
            check=False,
        )
    except (OSError, subprocess.TimeoutExpired) as e:
        raise InterpreterError(f"{interpreter} could not be run ({e}); {HOW_TO_SET}") from None
    if proc.returncode != 0:
        last = (proc.stderr.strip().splitlines() or ["no message"])[-1]
        raise InterpreterError(f"{interpreter} cannot run geoortho ({last}); {HOW_TO_SET}")
    try:
        description = json.loads(proc.stdout)
    except json.JSONDecodeError as e:
        raise InterpreterError(f"{interpreter} -m geoortho describe --json printed no JSON ({e})") from None
    if not isinstance(description, dict) or "algorithms" not in description:
        raise InterpreterError(f"{interpreter} -m geoortho describe --json: not a registry description")
    return description


def load_description(
    interpreter: str, cache_file: str | os.PathLike[str] | None = None, *, timeout_s: float = 120.0
) -> dict[str, Any]:
    """The registry description from ``interpreter -m geoortho describe --json``.

    Starting geoortho takes seconds, and QGIS asks at every start (and
    qgis_process at every call), so the answer is cached in ``cache_file``
    until the interpreter or any geoortho module changes.
    """
    key = _interpreter_key(interpreter)
    cache = Path(cache_file) if cache_file else None
    if cache is not None and cache.is_file():
        try:
            cached = json.loads(cache.read_text(encoding="utf-8"))
            if cached.get("interpreter") == key and cached.get("package") == _package_signature(
                cached["description"]["package_dir"]
            ):
                result: dict[str, Any] = cached["description"]
                return result
        except (OSError, ValueError, KeyError, TypeError):
            pass  # a stale or broken cache is simply rebuilt
    description = _run_describe(interpreter, timeout_s)
    if cache is not None:
        record = {
            "interpreter": key,
            "package": _package_signature(description.get("package_dir", "")),
            "description": description,
        }
        try:
            cache.parent.mkdir(parents=True, exist_ok=True)
            tmp = cache.with_name(f".{cache.name}.{os.getpid()}.tmp")
            tmp.write_text(json.dumps(record), encoding="utf-8")
            os.replace(tmp, cache)
        except OSError:
            pass  # no cache is slower, not wrong
    return description
