"""What every command shares: one-line usage errors, value types, output checks, the layout and
physics flags.

Sizes on the command line are ``WIDTHxHEIGHT`` like OpenCV's ``dsize`` ("257x129" is 257 wide);
the Python API uses ``(H, W)``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import re
import selectors
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any, NoReturn

__all__ = [
    "DECODER_LINE",
    "FLAGS",
    "NEW_FOLDERS",
    "Formatter",
    "Parser",
    "UsageError",
    "add_command",
    "add_layout_args",
    "add_physics_args",
    "add_run_args",
    "check_sensor_memory",
    "distinct_files",
    "existing_folder",
    "int_range",
    "layout_from_args",
    "non_negative_float",
    "non_negative_int",
    "not_within",
    "number_type",
    "out_dir",
    "out_file",
    "parse_range",
    "parse_theta",
    "parse_um",
    "parse_wxh",
    "physics_from_args",
    "pick_device",
    "positive_float",
    "positive_int",
    "quiet_decoders",
    "readable_image",
]


#: Library argument names and the command-line flags that set them, for error lines.
FLAGS = {
    "out": "--out",
    "report": "--report",
    "dst": "DST",
    "src": "SRC",
    "format": "--format",
    "grid_um": "--grid-um",
    "tol_um": "--tol-um",
    "tol": "--tol",
    "workers": "--workers",
    "label_rule": "--label-rule",
    "engine": "--engine",
    "address": "--address",
    "labels": "--labels",
    "px_per_um": "--px-per-um",
    "line_width": "--line-width",
    "min_feature_um": "--min-feature-um",
    "sensor_um": "--sensor-um",
}


class UsageError(Exception):
    """A bad command-line value: printed as one line, exit status 2."""


class Parser(argparse.ArgumentParser):
    """An ``ArgumentParser`` whose errors are one line (no usage block) with exit status 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message}\n")


class Formatter(argparse.ArgumentDefaultsHelpFormatter):
    """Shows every default as ``(default: X)``, except for flags and options without one."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        if action.default is None or action.default is False or isinstance(action, argparse._VersionAction):
            return action.help
        return super()._get_help_string(action)


def add_command(sub: argparse._SubParsersAction, name: str, summary: str) -> argparse.ArgumentParser:
    """A command's parser under ``sub``: its summary is both its help line and its description."""
    return sub.add_parser(name, help=summary, description=summary, formatter_class=Formatter)


# ----------------------------------------------------------------------------------------
# Value types
# ----------------------------------------------------------------------------------------
_WXH = re.compile(r"(-?[0-9]+)[xX](-?[0-9]+)", re.ASCII)


def parse_wxh(text: str) -> tuple[int, int]:
    """``"257x129"`` (width x height) to ``(H, W) = (129, 257)``: ASCII digits, no spaces or
    underscores (``int`` would read ``8_0`` as 80)."""
    match = _WXH.fullmatch(text)
    if match is None:
        raise argparse.ArgumentTypeError(f"must be WIDTHxHEIGHT, e.g. 257x129, got {text!r}")
    w, h = int(match[1]), int(match[2])
    if w <= 0 or h <= 0:
        raise argparse.ArgumentTypeError(f"width and height must be >= 1, got {text!r}")
    return h, w


def parse_um(text: str) -> tuple[float, float]:
    """``"5600x4200"`` (width x height in µm) to ``(H_um, W_um) = (4200.0, 5600.0)``."""
    try:
        w, h = (float(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"must be WIDTHxHEIGHT in µm, e.g. 5600x4200, got {text!r}"
        ) from None
    if not (0 < w < math.inf and 0 < h < math.inf):
        raise argparse.ArgumentTypeError(f"width and height must be finite and > 0, got {text!r}")
    return h, w


def _inside_pair(text: str, names: str, example: str) -> tuple[float, float, bool]:
    """``text`` as two comma-separated numbers (``names``, e.g. ``"TX,TY"``, and ``example`` word
    the error), and whether both are finite with ``|v| < 1``."""
    try:
        a, b = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be {names}, e.g. {example}, got {text!r}") from None
    return a, b, all(math.isfinite(v) and abs(v) < 1 for v in (a, b))


def parse_theta(text: str) -> tuple[float, float]:
    """``"0.3,-0.1"`` to ``(0.3, -0.1)``; each value finite with ``|θ| < 1``."""
    tx, ty, inside = _inside_pair(text, "TX,TY", "0.3,0.1")
    if not inside:
        raise argparse.ArgumentTypeError(f"each θ must be finite with |θ| < 1, got {text!r}")
    return tx, ty


def parse_range(text: str) -> tuple[float, float]:
    """``"-0.8,0.8"`` to ``(-0.8, 0.8)``: finite, ``|θ| < 1``, low below high."""
    lo, hi, inside = _inside_pair(text, "LO,HI", "-0.8,0.8")
    if not (inside and lo < hi):
        raise argparse.ArgumentTypeError(f"must have -1 < LO < HI < 1, got {text!r}")
    return lo, hi


def number_type(lo: float, *, integer: bool = False, open_lo: bool = False) -> Callable[[str], Any]:
    """An argparse type: a finite number ``>= lo`` (``> lo`` with ``open_lo``)."""
    kind = "an integer" if integer else "a number"
    bound = f"{'>' if open_lo else '>='} {lo:g}"

    def parse(text: str) -> int | float:
        try:
            v = int(text) if integer else float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be {kind} {bound}, got {text!r}") from None
        if not math.isfinite(v) or (v <= lo if open_lo else v < lo):
            raise argparse.ArgumentTypeError(f"must be {kind} {bound}, got {text!r}")
        return v

    return parse


positive_int = number_type(1, integer=True)


def int_range(lo: int, hi: int) -> Callable[[str], int]:
    """An argparse type: an integer in ``[lo, hi]``."""

    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            v = None
        if v is None or not lo <= v <= hi:
            raise argparse.ArgumentTypeError(f"must be an integer in [{lo}, {hi}], got {text!r}")
        return v

    return parse


non_negative_int = number_type(0, integer=True)
positive_float = number_type(0, open_lo=True)
non_negative_float = number_type(0)


# ----------------------------------------------------------------------------------------
# Inputs and outputs, checked before any work
# ----------------------------------------------------------------------------------------
def check_sensor_memory(size: tuple[int, int], flag: str = "--size") -> None:
    """Refuse a sensor whose pixels alone need more memory than is available, before allocating
    ([`check_memory`][layoutwarp.checks.check_memory], with the flag named)."""
    from ..checks import ArgumentError, check_memory

    h, w = size
    try:
        check_memory(size, shown=f"{w}x{h}")
    except ArgumentError as exc:
        raise UsageError(f"argument {flag}: {str(exc).removeprefix('size ')}") from None


def existing_folder(path: str | Path, flag: str) -> Path:
    """A folder that must exist: refused in one line if it is missing or is a file."""
    path = Path(path)
    if path.is_file():
        raise UsageError(f"argument {flag}: must be a folder; {str(path)!r} is a file")
    if not path.is_dir():
        raise UsageError(f"argument {flag}: no such folder {str(path)!r}")
    return path


#: Output folders the running command will create (a failed command removes them if empty).
NEW_FOLDERS: list[Path] = []


def out_dir(path: str | Path, flag: str = "--out") -> Path:
    """An output folder that can be created: refused in one line if it is, or lies under, a file."""
    from ..files import file_in_the_way

    path = Path(path)
    blocker = file_in_the_way(path)
    if blocker is not None:
        what = "is a file" if blocker == path else f"lies under {str(blocker)!r}, which is a file"
        raise UsageError(f"argument {flag}: must be a folder; {str(path)!r} {what}")
    missing = [path, *path.parents]  # the folder and those above it the command will create
    NEW_FOLDERS.extend(reversed([folder for folder in missing if not folder.exists()]))
    return path


def distinct_files(outputs: dict[str, str | Path | None], inputs: dict[str, str | Path | None]) -> None:
    """Refuse, in one line, an output file named twice or naming an input (one would overwrite
    the other): ``outputs`` and ``inputs`` map flags to paths (``None``: not given)."""
    seen: dict[Path, str] = {}
    for flag, path in inputs.items():
        if path is not None:
            seen.setdefault(Path(path).resolve(), flag)
    for flag, path in outputs.items():
        if path is None:
            continue
        other = seen.get(Path(path).resolve())
        if other is not None:
            role = "an input" if other in inputs else "another output"
            raise UsageError(f"argument {flag}: {str(path)!r} is also {other} ({role}); name another file")
        seen[Path(path).resolve()] = flag


def readable_image(path: str | Path, flag: str = "--image") -> Path:
    """An image file the command can decode: refused in one line where it does not exist, is a
    folder, or is no image OpenCV reads (a file cut short, a text file)."""
    from ..preprocess import read_image

    path = Path(path)
    if path.is_dir():
        raise UsageError(f"argument {flag}: {str(path)!r} is a folder; give an image file")
    if not path.is_file():
        raise UsageError(f"argument {flag}: no such file {str(path)!r}")
    try:
        with quiet_decoders():  # a broken file is named once, in our words
            read_image(path)
    except ValueError as exc:
        raise UsageError(f"argument {flag}: cannot read {str(path)!r}: {exc}") from None
    return path


def not_within(path: str | Path, flag: str, folder: str | Path, folder_flag: str) -> None:
    """Refuse, in one line, an output folder ``path`` that is ``folder`` (another option's) or lies
    inside it: what one command writes there would be read as the other's (e.g. a landscape's
    runs among a study's)."""
    inner, outer = Path(path).resolve(), Path(folder).resolve()
    if inner == outer or inner.is_relative_to(outer):
        where = "is" if inner == outer else "lies inside"
        raise UsageError(
            f"argument {flag}: {str(path)!r} {where} {folder_flag} {str(folder)!r}; choose another folder"
        )


def out_file(path: str | Path | None, flag: str) -> Path | None:
    """An output file that can be written (``None`` passes): refused in one line, before the
    command's work, if it is a folder or lies under a file."""
    if path is None:
        return None
    from ..checks import ArgumentError
    from ..files import check_file_destination

    try:
        return check_file_destination(path, flag)
    except ArgumentError as exc:
        raise UsageError(f"argument {flag}: {str(exc).removeprefix(flag + ' ')}") from None


def pick_device(name: str | None) -> str:
    """``--device``: the given torch device, checked, or CUDA when available, else the CPU."""
    import torch

    from ..experiments.training import default_device

    if name is None:  # under torchrun each rank takes the GPU of its local rank
        local = os.environ.get("LOCAL_RANK")
        return f"cuda:{local}" if local is not None and torch.cuda.is_available() else default_device()
    from ..checks import check_device

    try:
        return str(check_device(name, "argument --device"))
    except ValueError as exc:
        raise UsageError(str(exc)) from None


def add_run_args(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--device", help="torch device, e.g. cpu, cuda, cuda:1 (default: cuda when available, else cpu)"
    )
    p.add_argument(
        "--amp",
        action="store_true",
        help="mixed precision for the network (float16 on CUDA, bfloat16 on CPU); the sensor stays float32",
    )


# ----------------------------------------------------------------------------------------
# The layout and sensor-physics flags
# ----------------------------------------------------------------------------------------
def add_layout_args(p: argparse.ArgumentParser, families: Sequence[str]) -> None:
    p.add_argument("--layout", metavar="FILE", help="layout file (written by save_layout or train)")
    p.add_argument(
        "--family",
        choices=families,
        help="or a layout family with --theta (spline and grid hold more than two numbers: --layout FILE)",
    )
    p.add_argument("--theta", type=parse_theta, help="θ as TX,TY with --family, each |θ| < 1")
    p.add_argument("--size", type=parse_wxh, help="sensor WIDTHxHEIGHT (default: the layout file's)")


def layout_from_args(args: argparse.Namespace):
    """The fixed layout and sensor size from ``--layout FILE`` or ``--family/--theta``, and ``--size``."""
    import torch

    from ..layoutfile import load_layout
    from ..layouts import FAMILIES

    if args.layout and (args.family or args.theta):
        raise UsageError("argument --layout: give a layout file or --family/--theta, not both")
    if args.layout:
        try:
            layout, info = load_layout(args.layout, dtype=torch.float64)
        except ValueError as exc:
            raise UsageError(f"argument --layout: {exc}") from None
        size = args.size or (tuple(info["size_hw"]) if info.get("size_hw") else None)
    elif args.family:
        cls = FAMILIES[args.family]
        if cls.num_params is None:
            raise UsageError(
                f"argument --family: a {args.family!r} layout has more parameters than --theta holds; "
                "give it as --layout FILE (e.g. written by train or save_layout)"
            )
        if cls.num_params and args.theta is None:
            raise UsageError(
                f"argument --family: {args.family!r} needs --theta TX,TY (θ = 0,0 is the uniform layout)"
            )
        if not cls.num_params and args.theta is not None:
            raise UsageError(
                f"argument --theta: the {args.family!r} layout has no parameters, got {args.theta!r}"
            )
        layout, size = cls(args.theta, dtype=torch.float64), args.size
    else:
        raise UsageError("argument --layout: give a layout file, or --family (with --theta)")
    if size is None:
        raise UsageError("argument --size: needed (the layout file stores no sensor size)")
    check_sensor_memory(size)
    return layout, size


def add_physics_args(p: argparse.ArgumentParser, extent: str | None = None) -> None:
    """``--physics FILE`` and the common fields as flags (a flag overrides the file's value)."""
    g = p.add_argument_group(
        "sensor physics", "record as a real sensor would: photons, noise, full well, ADC, optics"
    )
    g.add_argument(
        "--physics",
        metavar="FILE",
        help="a SensorPhysics JSON file (SensorPhysics.to_json); the flags below override its values",
    )
    g.add_argument(
        "--photons-per-um2",
        type=positive_float,
        help="the light: mean photons per µm² where the image is at full scale",
    )
    if extent is None:
        g.add_argument("--sensor-um", type=parse_um, help="the sensor's extent WIDTHxHEIGHT in µm")
    g.add_argument("--read-noise-e", type=non_negative_float, help="read noise in electrons (rms)")
    g.add_argument("--full-well-per-um2", type=positive_float, help="electrons a pixel holds per µm²")
    g.add_argument("--adc-bits", type=int_range(1, 32), help="ADC resolution in bits")
    g.add_argument("--psf", choices=["gaussian", "airy"], help="the optics' point spread function")
    g.add_argument("--f-number", type=positive_float, help="the optics' f-number (with --psf)")
    g.add_argument(  # checks.SEED_MAX: the parsers import no torch
        "--noise-seed", type=int_range(0, 2**63 - 1), help="seed of the temporal noise"
    )


#: Physics flags and the SensorPhysics fields they set.
PHYSICS_FLAGS = {
    "photons_per_um2": "photons_per_um2",
    "sensor_um": "sensor_um",
    "read_noise_e": "read_noise_e",
    "full_well_per_um2": "full_well_per_um2",
    "adc_bits": "adc_bits",
    "psf": "psf",
    "f_number": "f_number",
    "noise_seed": "seed",
}


def physics_from_args(args: argparse.Namespace, extent: tuple[float, float] | None = None):
    """The [`SensorPhysics`][layoutwarp.physics.SensorPhysics] of ``--physics FILE`` and the physics flags, or
    ``None`` when none is given. ``extent``: the sensor extent when no flag or file sets one.
    A flag overrides the file's value, and the values are checked once merged, so a file may
    leave out what the flags give; an error names the flag, or the file, that set the value."""
    from ..physics import SensorPhysics

    values: dict[str, Any] = {}
    source = f"--physics: {args.physics}"
    if args.physics:
        try:
            values = json.loads(Path(args.physics).read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise UsageError(f"argument {source}: {exc}") from None
        if not isinstance(values, dict):
            raise UsageError(f"argument {source}: must hold a JSON object, got {type(values).__name__}")
    flags = {
        field: ("--" + dest.replace("_", "-"), getattr(args, dest))
        for dest, field in PHYSICS_FLAGS.items()
        if getattr(args, dest, None) is not None
    }
    if not values and not set(flags) - {"sensor_um"}:  # an extent alone (export's own) asks for no physics
        return None
    values |= {field: value for field, (_, value) in flags.items()}
    if "sensor_um" not in values and extent is not None:
        values["sensor_um"] = extent
    for field, flag in (("photons_per_um2", "--photons-per-um2"), ("sensor_um", "--sensor-um")):
        if field not in values:
            raise UsageError(f"argument {flag}: needed for sensor physics (or give it in --physics FILE)")
    if "f_number" in flags and values.get("psf") is None:  # it sets the PSF's width, and nothing else
        raise UsageError(f"argument --f-number: needs --psf gaussian or airy, got {flags['f_number'][1]:g}")
    try:
        return SensorPhysics.from_dict(values)
    except ValueError as exc:
        field = getattr(exc, "argument", None)
        where = flags[field][0] if field in flags else source if args.physics else None
        raise UsageError(f"argument {where}: {exc}" if where else f"sensor physics: {exc}") from None


# ----------------------------------------------------------------------------------------
# The image decoders' own lines
# ----------------------------------------------------------------------------------------
#: A line of the image libraries under OpenCV (libpng, libjpeg, libtiff, OpenCV's log): they write
#: to the process's stderr themselves, whatever Python does with ``sys.stderr``, and a message
#: may follow a progress bar's text on its line.
DECODER_LINE = re.compile(
    rb"(libpng (error|warning)|Corrupt JPEG data|Premature end of JPEG|Invalid SOS|Bogus |"
    rb"JPEG datastream|Not a JPEG file|Unsupported JPEG|Warning: unknown JFIF|TIFF\w*: |"
    rb"\[ ?(WARN|ERROR|INFO|DEBUG):)[^\n]*\n?"
)


@contextlib.contextmanager
def quiet_decoders() -> Iterator[list[str]]:
    """Within: the lines the image libraries print on the process's stderr (`DECODER_LINE`) are
    kept from the terminal and collected in the list this yields; everything else written there
    (warnings, progress bars) passes through as it comes. The command reports a file the
    libraries could not decode in its own words, once.

    The process's stderr is a pipe meanwhile, read by a thread; a child process started within
    keeps writing through it after the context ends, and the thread forwards that until the
    last writer has gone.
    """
    sys.stderr.flush()
    try:
        terminal = os.dup(2)
        read_end, write_end = os.pipe()
    except OSError:  # no stderr to filter (a closed descriptor): nothing reaches a terminal anyway
        yield []
        return
    dropped: list[str] = []
    mark = b"\x00layoutwarp-stderr-mark\x00"  # bytes no library writes
    marked = threading.Event()

    def drop(match: re.Match) -> bytes:
        dropped.append(match.group().decode(errors="replace").strip())
        return b""

    def show(data: bytes) -> None:
        with contextlib.suppress(OSError):  # a reader gone (| head): the output goes nowhere
            os.write(terminal, data)

    def forward() -> None:
        pending = b""
        try:
            with selectors.DefaultSelector() as sel:  # (select.select fails past fd 1023)
                sel.register(read_end, selectors.EVENT_READ)
                while True:
                    chunk = os.read(read_end, 65536) if sel.select(0.1) else None
                    if chunk == b"":  # the last writer has gone
                        break
                    pending += chunk or b""
                    if mark in pending:  # everything before it is sorted: the caller goes on
                        before, pending = pending.split(mark, 1)
                        show(DECODER_LINE.sub(drop, before))
                        marked.set()
                    *lines, pending = re.split(rb"(?<=[\n\r])", pending)
                    if pending and chunk is None and not DECODER_LINE.search(pending):
                        lines.append(pending)  # a partial line that waited 0.1 s (a prompt, a bar); a
                        pending = b""  # library's message (one write, whole) waits for its line's end
                    for line in lines:
                        if line := DECODER_LINE.sub(drop, line):
                            show(line)
        except Exception:  # never lose the output: pass the rest through as it is
            show(pending)
            pending = b""
            marked.set()
            while chunk := os.read(read_end, 65536):
                show(chunk.replace(mark, b""))
        show(DECODER_LINE.sub(drop, pending))
        marked.set()
        os.close(read_end)
        os.close(terminal)

    restore = os.dup(2)
    os.dup2(write_end, 2)
    os.close(write_end)
    threading.Thread(target=forward, name="layoutwarp-stderr", daemon=True).start()
    try:
        yield dropped
    finally:
        sys.stderr.flush()
        os.write(2, mark)  # the pipe keeps order: once the reader meets it, all before is sorted
        marked.wait(10)
        os.dup2(restore, 2)
        os.close(restore)
