"""``python -m geoortho``: argparse generated from the registry.

Exit codes: 0 done, 1 unexpected failure, 2 bad input (one line on stderr),
130 canceled.
"""

from __future__ import annotations

import argparse
import logging
import os
import re
import signal
import sys
import threading
import warnings
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any, NoReturn

from geoortho.errors import CanceledError, GeoorthoError, InputError, ParameterError, interrupted, shortened
from geoortho.feedback import Feedback, JsonLinesFeedback, TerminalFeedback
from geoortho.processing.registry import convert_values, describe_json, list_algorithms, run_algorithm
from geoortho.processing.spec import PARAM_TYPES, Algorithm, Param
from geoortho.version import __version__

__all__ = ["ARGPARSE_OPTIONS", "build_parser", "main"]

PROG = "geoortho"


def _metavar(word: str) -> Callable[[Param], dict[str, Any]]:
    return lambda p: {"metavar": word}


def _number_opts(p: Param) -> dict[str, Any]:
    return {"metavar": (p.unit or "NUMBER").upper().replace(" ", "_")}


#: One entry per parameter type: the extra argparse keywords for its option.
#: Values stay strings here; the registry's converters do the typing, so the
#: CLI and the Python API validate alike.
ARGPARSE_OPTIONS: dict[str, Callable[[Param], dict[str, Any]]] = {
    "folder": _metavar("DIR"),
    "file": _metavar("FILE"),
    "raster": _metavar("RASTER"),
    "vector": _metavar("VECTOR"),
    "pointcloud": _metavar("POINTS"),
    "number": _number_opts,
    "integer": _metavar("N"),
    "enum": lambda p: {
        "choices": list(p.choices),
        "metavar": "NAME" if len(p.choices) > _CHOICES_INLINE else "{" + ",".join(p.choices) + "}",
    },
    "bool": lambda p: {"action": argparse.BooleanOptionalAction},
    "crs": _metavar("CRS"),
    "string": _metavar("TEXT"),
}
assert set(ARGPARSE_OPTIONS) == set(PARAM_TYPES)


class _Parser(argparse.ArgumentParser):
    """Bad usage: one line on stderr and exit 2 (no usage dump)."""

    def error(self, message: str) -> NoReturn:
        # a value of hundreds of digits (or a pasted page) is cut: the line stays one line to read
        message = re.sub(r"\S{60,}", lambda m: shortened(m.group(0)), message)
        sys.stderr.write(f"{self.prog}: error: {message}\n")
        sys.exit(2)


#: An enum with more choices than this lists them once, in its help, not in the usage line too.
_CHOICES_INLINE = 8


def for_people(text: str, params: Sequence[Param] = ()) -> str:
    """Help or error text as a person reads it on a command line: no reStructuredText markup, and
    each option named by its flag (``max_gap_m`` is ``--max-gap-m``) where it is one of
    ``params``; the QGIS face keeps its own parameter names."""
    flags = {p.name: p.cli_flag for p in params}

    def literal(m: re.Match[str]) -> str:
        return flags.get(m.group(1), m.group(1))

    text = re.sub(r":[a-z]+:`~?([^`]+)`", lambda m: m.group(1).rsplit(".", 1)[-1], text)
    text = re.sub(r"``([^`]+)``", literal, text)
    for name in sorted((n for n in flags if "_" in n), key=len, reverse=True):
        # a Python name, not a file's (gcp_list.txt) nor part of a longer name
        text = re.sub(rf"(?<![\w./-]){re.escape(name)}(?![\w]|\.\w)", flags[name], text)
    return text


def _error_for_people(error: InputError, message: str, params: Sequence[Param]) -> str:
    """An error's line on the command line: the option a ParameterError is about leads by its flag
    (``points: no such file`` is ``--points: no such file``), every other by :func:`for_people`."""
    if isinstance(error, ParameterError) and message.startswith(f"{error.name}: "):
        flag = next((p.cli_flag for p in params if p.name == error.name), error.name)
        message = flag + message[len(error.name) :]
    return for_people(message, params)


def _option_help(p: Param, params: Sequence[Param] = ()) -> str:
    bits = [for_people(p.help.rstrip("."), params) if p.help else p.cli_flag]
    extra = []
    if p.unit:
        extra.append(f"unit: {p.unit}")
    if p.minimum is not None or p.maximum is not None:
        lo = "" if p.minimum is None else f"{p.minimum:g}"
        hi = "" if p.maximum is None else f"{p.maximum:g}"
        extra.append(f"range: {lo}..{hi}")
    if p.type == "enum" and len(p.choices) > _CHOICES_INLINE:
        extra.append("one of: " + ", ".join(p.choices))
    if p.required:
        extra.append("required")
    elif p.default not in (None, "") and p.type != "bool":
        extra.append(f"default: {p.default}")
    elif p.type == "bool":
        extra.append(f"default: {'on' if p.default else 'off'}")
    if extra:
        bits.append("(" + "; ".join(extra) + ")")
    return " ".join(bits).replace("%", "%%")


def _add_common(parser: argparse.ArgumentParser) -> None:
    g = parser.add_argument_group("output control")
    g.add_argument("--quiet", action="store_true", help="no progress bar, no info messages")
    g.add_argument("--json", action="store_true", help="print the outputs as JSON on stdout when done")
    g.add_argument(
        "--progress-json",
        action="store_true",
        help="machine-readable progress and messages on stderr, one JSON object a line",
    )
    g.add_argument("--debug", action="store_true", help="show tracebacks and debug logging")
    g = parser.add_argument_group("cluster")
    g.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        default=None,
        help="run the per-photo and per-tile work on the Dask cluster at ADDRESS (tcp://host:8786; "
        "default $GEOORTHO_SCHEDULER); its workers must see the same paths (a shared file system)",
    )


def _add_algorithm(sub: Any, alg: Algorithm) -> None:
    p = sub.add_parser(
        alg.id,
        help=for_people(alg.short_help, alg.params),
        description=for_people(alg.help, alg.params),
        prog=f"{PROG} {alg.id}",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        add_help=False,  # -h goes under the one "options" heading, not a second one of its own
    )
    req = p.add_argument_group("required")
    opt = p.add_argument_group("options")
    opt.add_argument("-h", "--help", action="help", help="show this help message and exit")
    for param in alg.params:
        group = req if param.required else opt
        kwargs = ARGPARSE_OPTIONS[param.type](param)
        group.add_argument(
            param.cli_flag,
            *param.cli_aliases,
            dest=param.name,
            default=None,
            required=param.required,
            help=_option_help(param, alg.params),
            **kwargs,
        )
    _add_common(p)


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog=PROG,
        description="geoortho: drone photos to survey products, georeference first.",
        epilog=f"Run '{PROG} <algorithm> --help' for its options.",
    )
    parser.add_argument("--version", action="version", version=f"{PROG} {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="<algorithm>", parser_class=_Parser)
    for alg in list_algorithms():
        _add_algorithm(sub, alg)
    d = sub.add_parser(
        "describe", help="describe every algorithm (use --json for the machine form)", prog=f"{PROG} describe"
    )
    d.add_argument("--json", action="store_true", help="print the registry as JSON")
    return parser


def _describe_text() -> str:
    lines = []
    for a in list_algorithms():
        lines.append(f"{a.id}: {a.title} [{a.group}]")
        for p in a.params:
            lines.append(f"  {p.cli_flag} ({p.type}) {_option_help(p, a.params)}")
    return "\n".join(lines)


@contextmanager
def _signals_cancel(feedback: Feedback) -> Iterator[None]:
    """While the command runs, SIGTERM (QGIS Cancel, systemd's stop) cancels the feedback: the run
    stops at its next progress call and removes its temporary outputs. SIGINT does that too and
    still raises KeyboardInterrupt at once: a library that swallows the KeyboardInterrupt (an
    optional import whose failure is caught as ImportError, which pybind11 makes of a Ctrl-C during
    a module's initialisation) would otherwise lose the Ctrl-C and run to the end. A SIGINT the
    parent ignored (nohup, a background job) stays ignored. The previous handlers come back after."""

    def on_sigterm(signum: int, frame: Any) -> None:
        feedback.cancel()

    def on_sigint(signum: int, frame: Any) -> NoReturn:
        feedback.cancel()
        raise KeyboardInterrupt

    previous = {sig: signal.getsignal(sig) for sig in (signal.SIGTERM, signal.SIGINT)}
    try:
        signal.signal(signal.SIGTERM, on_sigterm)
        if previous[signal.SIGINT] is signal.default_int_handler:
            signal.signal(signal.SIGINT, on_sigint)
    except ValueError:  # not the main thread: no handler to set or restore
        previous = {}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            if handler is not None:  # None: set outside Python, cannot be put back
                signal.signal(sig, handler)


def _forget_unhandled_interrupt() -> None:
    """Keep the exit code after a caught Ctrl-C. CPython 3.11 marks a KeyboardInterrupt that
    leaves an exec() of a string (dataclasses and namedtuple build their methods so, at import) as
    unhandled even when it is caught, and under ``python -m`` then ends the process by SIGINT at
    exit instead of with the code returned. Any exec() of a string that completes clears the mark."""
    exec("pass")


# the commands that load pycolmap whatever their values; others do when given an SfM model
_COLMAP_ALWAYS = frozenset({"sfm", "run", "demo", "report"})
_HELD = frozenset({signal.SIGINT, signal.SIGTERM})


def main(argv: Sequence[str] | None = None) -> int:
    """The command line; returns the exit code. A command that returns has handled any Ctrl-C
    (130, or a run that ended anyway after a library swallowed it): the exit is the code."""
    main_thread = threading.current_thread() is threading.main_thread()
    before = signal.pthread_sigmask(signal.SIG_BLOCK, _HELD) if main_thread else None
    try:
        code = _main(argv, before)
    finally:
        if before is not None:
            signal.pthread_sigmask(signal.SIG_SETMASK, before)
    _forget_unhandled_interrupt()
    return code


def _load_then_release(alg: Algorithm, values: dict[str, Any], before: set[int | signal.Signals] | None) -> None:
    """Import the command's code, and pycolmap if it will need it, with SIGINT and SIGTERM held,
    then let them through. The native threads those imports start (OpenBLAS's, OpenCV's) inherit
    the held mask and never take a signal; and glog, which puts its failure handler on SIGTERM
    part-way through pycolmap's import, hands it back before any other thread could run it. A
    SIGTERM in that window was a C++ dump and exit -15 instead of "canceled" (8 of 40 tries)."""
    try:
        convert_values(alg, values)  # bad input is told before the imports (sfm, a missing folder: 0.23 s, not 0.69)
        alg.function  # noqa: B018 - the import is the point
        if alg.id in _COLMAP_ALWAYS or values.get("sfm"):
            from geoortho.core.colmap import load_pycolmap

            load_pycolmap()
    finally:
        if before is not None:
            signal.pthread_sigmask(signal.SIG_SETMASK, before)


def _main(argv: Sequence[str] | None, before: set[int | signal.Signals] | None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help(sys.stderr)
        return 2
    if args.command == "describe":
        print(describe_json() if args.json else _describe_text())
        return 0
    alg = next(a for a in list_algorithms() if a.id == args.command)
    if args.debug:  # the feedback prints messages itself; logging only for debugging
        logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
        logging.getLogger("geoortho").setLevel(logging.DEBUG)
    if not args.debug:
        # numpy's "invalid value encountered" and the like are not for a surveyor: what matters is
        # said through the feedback; --debug shows them
        warnings.filterwarnings("ignore", category=RuntimeWarning)
        from geoortho.core.parallel import SCHEDULER_ENV  # here: the pool's imports are no part of --help

        if args.scheduler or os.environ.get(SCHEDULER_ENV):
            _quiet_dask()
    values = {p.name: getattr(args, p.name) for p in alg.params}
    feedback: Feedback
    if args.progress_json:
        feedback = JsonLinesFeedback(sys.stderr)
    else:
        feedback = TerminalFeedback(alg.id, quiet=args.quiet)
    prog = f"{PROG} {alg.id}"

    def fail(kind: str, message: str, code: int) -> int:
        """The last stderr line: plain text, or one JSON object under --progress-json."""
        feedback.close()
        if args.progress_json:
            from geoortho.core.outputs import json_text

            line = f"{prog}: {message}"
            sys.stderr.write(json_text({"type": kind, "message": line, "exit_code": code}) + "\n")
        else:
            sys.stderr.write(f"{prog}: {message}\n")
        return code

    try:
        with _signals_cancel(feedback):
            _load_then_release(alg, values, before)
            outputs = run_algorithm(alg, values, feedback, scheduler=args.scheduler)
    except InputError as e:
        message = _one_line(e)
        if not args.progress_json:  # (the QGIS face's line: it names its parameters its own way)
            message = _error_for_people(e, message, alg.params)
        return fail("error", f"error: {message}", 2)
    except (CanceledError, KeyboardInterrupt):
        return fail("canceled", "canceled", 130)
    except GeoorthoError as e:
        if args.debug:
            feedback.close()
            raise
        return fail("error", f"error: {_one_line(e)}", 1)
    except Exception as e:  # unexpected: a bug or an environment problem
        if interrupted(e):  # a Ctrl-C a library wrapped in its own error
            return fail("canceled", "canceled", 130)
        if args.debug:
            feedback.close()
            raise
        return fail("error", f"unexpected error: {type(e).__name__}: {_one_line(e)} (run with --debug for details)", 1)
    feedback.close()
    if args.json:
        from geoortho.core.outputs import json_text

        print(json_text(outputs, indent=2))
    elif not args.quiet:
        for k, v in outputs.items():
            if not isinstance(v, (dict, list)):
                print(f"{k}: {v}")
    return 0


def _quiet_dask() -> None:
    """Dask's client logs its reconnection attempts and their tracebacks on stderr; the run's own
    last line says what happened (--debug keeps them). Set after the import, which configures them."""
    try:
        import distributed  # noqa: F401
    except ImportError:
        return  # the run says that the extra is missing
    names = [n for n in logging.root.manager.loggerDict if n.split(".")[0] in ("distributed", "tornado")]
    for name in ["distributed", "tornado", *names]:
        logging.getLogger(name).setLevel(logging.CRITICAL)


def _one_line(e: BaseException) -> str:
    return " ".join(str(e).split())
