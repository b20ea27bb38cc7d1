"""Command line: ``layoutwarp <command>`` (also ``python -m layoutwarp``).

Sizes on the command line are ``WIDTHxHEIGHT`` like OpenCV's ``dsize`` ("257x129" is 257
wide); the Python API uses ``(H, W)``. Every error ends in one line on stderr that names the
flag, the value and what is allowed, with exit status 2. Each command lives in a module of
this package (``tools``: demo, doctor, bench; ``training``: train, study, landscape, evaluate;
``data``: preprocess, export), on the flags, types and checks of ``common``.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import re
import signal
import sys
import warnings
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

from . import data, tools, training
from .common import (
    FLAGS,
    NEW_FOLDERS,
    Formatter,
    Parser,
    UsageError,
    parse_theta,
    parse_wxh,
    positive_int,
)

if TYPE_CHECKING:
    from ..experiments.protocols import TaskSpec

_ROOT = __name__.rpartition(".")[0]  # the layoutwarp package, whose registries the parser lists

__all__ = ["build_parser", "join_negative_values", "main", "parse_theta", "parse_wxh", "positive_int", "run"]


def _catalogues() -> tuple[dict[str, TaskSpec], list[str], list[str]]:
    """The tasks' protocols, the families and the two-parameter families the parser lists: the
    built-in ones from torch-free modules, and, in a process that has loaded the registries, any a
    user registered there (without loading them)."""
    from ..catalog import BUILTIN_FAMILIES, TWO_PARAMETER_FAMILIES
    from ..experiments.protocols import SPECS

    specs, families, two = dict(SPECS), list(BUILTIN_FAMILIES), list(TWO_PARAMETER_FAMILIES)
    layouts = sys.modules.get(f"{_ROOT}.layouts")
    if layouts is not None:
        for name, cls in layouts.FAMILIES.items():
            if name not in families:
                families.append(name)
                if cls.num_params == 2:
                    two.append(name)
    tasks = sys.modules.get(f"{_ROOT}.experiments.tasks")
    if tasks is not None:
        specs |= {name: task.spec for name, task in tasks.TASKS.items() if name not in specs}
    return specs, families, two


def build_parser() -> argparse.ArgumentParser:
    """The ``layoutwarp`` argument parser. It imports nothing heavy (the tasks and families it
    lists come from torch-free modules), so help and argument errors answer at once."""
    from ..version import __version__

    specs, families, two = _catalogues()
    p = Parser(
        prog="layoutwarp",
        description="Differentiable sensor pixel layouts: simulate, learn and export task-specific sensors.",
        formatter_class=Formatter,
    )
    p.add_argument("--version", action="version", version=f"layoutwarp {__version__}")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND", parser_class=Parser)
    tools.add_commands(sub)
    training.add_commands(sub, specs, families, two)
    data.add_commands(sub, families)
    return p


def join_negative_values(argv: Sequence[str]) -> list[str]:
    """``--flag -0.5,0.5`` as ``--flag=-0.5,0.5``: a value that starts with a minus and a digit is
    the flag's value, not a flag (argparse takes only plain negative numbers so, and read
    ``--theta -0.5,0.5`` or ``--size -4x4`` as a missing value)."""
    out: list[str] = []
    i = 0
    while i < len(argv):
        arg = argv[i]
        if arg.startswith("--") and "=" not in arg and i + 1 < len(argv) and _NEGATIVE.match(argv[i + 1]):
            out.append(f"{arg}={argv[i + 1]}")
            i += 2
        else:
            out.append(arg)
            i += 1
    return out


_NEGATIVE = re.compile(r"^-\.?\d")


def main(argv: Sequence[str] | None = None, *, own_process: bool = False) -> int:
    """Run the command line; returns the exit status. ``own_process``: the process is the
    command's alone, and its allocator keeps freed memory for the next training step
    ([`retain_freed_memory`][layoutwarp.kernels.retain_freed_memory])."""
    argv = join_negative_values(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    args, unknown = parser.parse_known_args(argv)
    if unknown:  # said by the command's own parser: its name and usage, not the top level's
        _leaf_parser(parser, args).error(f"unrecognized arguments: {' '.join(unknown)}")
    if own_process:
        from ..kernels import retain_freed_memory

        retain_freed_memory()
        warnings.formatwarning = _one_line_warning
    prog = f"layoutwarp {args.command}" + (
        f" {args.task}" if args.command in ("train", "study", "landscape") else ""
    )
    NEW_FOLDERS.clear()
    status = 1  # what an unexpected exception leaves
    try:
        status = int(args.func(args) or 0)
    except (UsageError, ValueError, FileNotFoundError) as exc:
        line = _os_error(exc) if isinstance(exc, OSError) and exc.strerror else _name_the_flag(exc)
        print(f"{prog}: error: {line}", file=sys.stderr)
        status = 2
    except OSError as exc:  # a file that cannot be written or read, a server not reached
        print(f"{prog}: error: {_os_error(exc)}", file=sys.stderr)
        status = 1
    except ImportError as exc:  # an optional extra not installed: its message says which
        print(f"{prog}: error: {exc}", file=sys.stderr)
        status = 1
    except RuntimeError as exc:
        if not _a_process_group_failure(exc):
            raise
        # a rank of a torchrun gone (killed, failed): the others' collectives fail with the
        # backend's traceback; one line instead, torchrun's own report follows
        first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        print(f"{prog}: error: the process group failed (did another rank stop?): {first}", file=sys.stderr)
        status = 1
    except KeyboardInterrupt as exc:  # what was finished is kept: a command run again goes on from there
        status = _stopped(prog, exc)
    finally:
        if status != 0:  # a failed command leaves no empty output folder of its own behind
            for folder in reversed(NEW_FOLDERS):
                with contextlib.suppress(OSError):  # kept if anything was written there
                    folder.rmdir()
    return status


def _a_process_group_failure(exc: RuntimeError) -> bool:
    """Whether ``exc`` is the failure of the ``torchrun`` process group this process joined
    (torch.distributed's own error, or its backend's): nothing imported to ask. Any other
    ``RuntimeError`` (out of memory, a bug of ours) keeps its traceback."""
    dist = sys.modules.get("torch.distributed")
    if dist is None or not dist.is_available() or not dist.is_initialized():
        return False
    backend = ("gloo", "NCCL", "Connection closed")  # its backends' own errors come as RuntimeError
    return isinstance(exc, dist.DistError) or any(word in str(exc) for word in backend)


def _leaf_parser(parser: argparse.ArgumentParser, args: argparse.Namespace) -> argparse.ArgumentParser:
    """The parser of the command (and task) ``args`` were parsed for."""
    for name in ("command", "task"):
        sub = next((a for a in parser._actions if isinstance(a, argparse._SubParsersAction)), None)
        if sub is None or getattr(args, name, None) not in sub.choices:
            break
        parser = sub.choices[getattr(args, name)]
    return parser


def _one_line_warning(message: Warning | str, category: type[Warning], *args: Any, **kwargs: Any) -> str:
    """A warning on the command line: one line, no source location."""
    return f"layoutwarp: warning: {message}\n"


class Terminated(KeyboardInterrupt):
    """SIGTERM (a scheduler's stop, ``torchrun`` ending the other ranks, ``kill``) as the command
    line takes it: as a Ctrl-C, so the command stops as one does (what it finished kept, its
    temporary files and child processes gone, a manifest written), with status 143."""


def _terminate(signum: int, frame: object) -> None:
    raise Terminated


def _stopped(prog: str, exc: KeyboardInterrupt) -> int:
    """Say that ``prog`` was stopped (a Ctrl-C, or SIGTERM as [`Terminated`][]), in one line, and
    return the status a shell reports for the signal: 130 for SIGINT, 143 for SIGTERM."""
    ended = isinstance(exc, Terminated)
    print(f"{prog}: {'terminated' if ended else 'interrupted'}", file=sys.stderr)
    return 143 if ended else 130


def run() -> None:
    """The ``layoutwarp`` command (and ``python -m layoutwarp``): [`main`][] in a process of
    its own. Output cut short by its reader (``| head``) ends the command quietly; SIGTERM
    stops it as a Ctrl-C does ([`Terminated`][])."""
    signal.signal(signal.SIGTERM, _terminate)
    try:
        status = main(own_process=True)
        sys.stdout.flush()
    except BrokenPipeError:
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no second error at exit
        status = 141  # as a shell reports a command ended by SIGPIPE
    except KeyboardInterrupt as exc:  # before the command's work began (its parser, its imports)
        status = _stopped("layoutwarp", exc)
    sys.exit(status)


def _os_error(exc: OSError) -> str:
    """An operating system's error in one line: what failed, and on which file."""
    if exc.strerror and exc.filename is not None:
        return f"{exc.strerror}: {str(exc.filename)!r}"
    return str(exc) or type(exc).__name__


def _name_the_flag(exc: Exception) -> str:
    """A library error about an argument ([`ArgumentError`][layoutwarp.checks.ArgumentError]) prefixed
    with the flag that sets it; any other error's message as it is."""
    from ..checks import ArgumentError

    flag = FLAGS.get(exc.argument) if isinstance(exc, ArgumentError) else None
    return f"argument {flag}: {exc}" if flag else str(exc)
