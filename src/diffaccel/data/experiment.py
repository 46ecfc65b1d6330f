"""Build a quad-scan dataset (format version 2) from a DAQ folder described in YAML.

The description (``EXPERIMENT.yaml``, schema in ``docs/file_formats.md``) names
the beam (``p0c``, ``species``), and per scan its beamline, its screen
(calibration and orientation), a CSV table of camera frames with the knob
values of each, and background frames; then the preprocessing. Relative paths
start at the YAML file's folder.

Everything is read and checked before anything is written: a bad input raises
:class:`ExperimentError`, one line naming the file (and the CSV row: row 1 is
the header, so row ``n`` is line ``n`` of the file) and the problem.

Orientation: the camera's frame is first rotated by ``rotate`` degrees
(counter-clockwise as displayed with row 0 at the top), then ``row0`` and
``col0`` say where the rotated frame's first row and column lie on the screen
(``row0: top`` = +y, the usual camera readout; ``col0: left`` = -x). The
dataset stores rows with y ascending and columns with x ascending.

Default preprocessing is unbiased: the background (mean of the background
frames, else the median of a border band) is subtracted without clipping, so
the noise stays signed; no threshold, no median filter, no centring, no crop,
no binning; each shot is normalised to unit sum. Each step is recorded in the
root ``metadata["preprocessing"]`` with the scan it applies to.
"""

from __future__ import annotations

import csv
import glob
import json
import math
import os
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from diffaccel.data import preprocessing as pre
from diffaccel.data.errors import FormatError
from diffaccel.data.images_io import Frame, read_frame
from diffaccel.data.quad_scan import QuadScanDataset
from diffaccel.data.scans import MultiScanDataset
from diffaccel.dynamics import Beamline

__all__ = [
    "DEFAULT_PREPROCESSING",
    "ExperimentError",
    "import_experiment",
    "import_lines",
    "load_experiment",
]

#: Preprocessing when the description names none (unbiased; see module doc).
DEFAULT_PREPROCESSING: dict[str, Any] = {
    "background": {"method": "auto", "clip": False, "edge_pixels": 4},
    "median_filter": None,
    "threshold": None,
    "center": None,
    "crop": None,
    "bin": 1,
    "normalize": True,
}
#: An image is empty when the brightest pixel of its 3 x 3 box mean is below
#: this many times the noise rms of that mean (noise rms: 1.4826 times the
#: median absolute deviation of the background-subtracted image, over 3).
EMPTY_SIGNIFICANCE = 5.0
_KNOB = re.compile(
    r"^\s*(?P<el>[A-Za-z0-9_+\-]+)\.(?P<par>[A-Za-z0-9_]+)\s*\[(?P<unit>[^\]]+)\]\s*$"
)
_TOP_KEYS = {"p0c", "species", "description", "metadata", "scans", "preprocessing"}
_SCAN_KEYS = {"beamline", "screen", "images", "background", "preprocessing"}
_SCREEN_KEYS = {
    "pixel_size",
    "calibration",
    "center",
    "rotate",
    "row0",
    "col0",
    "saturation",
    "max_saturated_pixels",
    "resolution_pixels",
}


class ExperimentError(FormatError):
    """A bad experiment description or DAQ file (one line: file, row, problem)."""


# ------------------------------------------------------------------ helpers
def _number(value: Any, where: str) -> float:
    """A finite number; YAML reads ``43.36e6`` as text, so text is converted."""
    if isinstance(value, bool):
        raise ExperimentError(f"{where}: expected a number; found {value!r}")
    try:
        out = float(value)
    except (TypeError, ValueError):
        raise ExperimentError(f"{where}: expected a number; found {value!r}") from None
    if not math.isfinite(out):
        raise ExperimentError(f"{where}: expected a finite number; found {value!r}")
    return out


def _mapping(value: Any, where: str, keys: set[str] | None = None) -> dict:
    if not isinstance(value, Mapping):
        raise ExperimentError(
            f"{where}: expected a mapping (key: value); found {type(value).__name__}"
        )
    if keys is not None:
        unknown = sorted(set(value) - keys)
        if unknown:
            raise ExperimentError(
                f"{where}: unknown key(s) {', '.join(map(str, unknown))}; expected "
                f"some of {', '.join(sorted(keys))}"
            )
    return dict(value)


def _pair(value: Any, where: str) -> tuple[float, float]:
    if isinstance(value, Sequence) and not isinstance(value, str):
        if len(value) != 2:
            raise ExperimentError(
                f"{where}: expected one number or [x, y]; found {value!r}"
            )
        return (_number(value[0], where), _number(value[1], where))
    v = _number(value, where)
    return (v, v)


def load_experiment(path: str | os.PathLike) -> dict:
    """Read an experiment description (YAML, or JSON which is YAML too).

    Raises:
        FileNotFoundError: if ``path`` does not exist.
        ExperimentError: for a file that is not a YAML mapping.
        ImportError: without PyYAML (``pip install diffaccel[images]``).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: file not found")
    try:
        import yaml
    except ImportError as err:
        raise ImportError(
            "reading an experiment description needs PyYAML: "
            "pip install diffaccel[images]"
        ) from err
    try:
        doc = yaml.safe_load(path.read_text())
    except (yaml.YAMLError, UnicodeDecodeError) as err:
        first = str(err).strip().splitlines()[0] if str(err).strip() else ""
        raise ExperimentError(f"{path}: not valid YAML ({first})") from err
    return _mapping(doc, str(path), _TOP_KEYS)


# ------------------------------------------------------------------ beamline
def _beamline_spec(value: Any, base: Path, where: str) -> list[dict]:
    """Element dicts from an inline spec, a JSON file or a lattice file."""
    if isinstance(value, list):
        return value
    if isinstance(value, str):
        value = {"file": value}
    cfg = _mapping(value, where, {"spec", "file", "lattice", "start", "end"})
    given = [k for k in ("spec", "file", "lattice") if k in cfg]
    if len(given) != 1:
        raise ExperimentError(
            f"{where}: expected exactly one of spec (inline list), file (JSON) or "
            f"lattice (lattice file with start/end); found {given or 'none'}"
        )
    if "spec" in cfg:
        if not isinstance(cfg["spec"], list):
            raise ExperimentError(f"{where}.spec: expected a list of elements")
        return cfg["spec"]
    if "file" in cfg:
        path = base / str(cfg["file"])
        if not path.is_file():
            raise ExperimentError(f"{where}.file: {path}: file not found")
        try:
            spec = json.loads(path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as err:
            raise ExperimentError(f"{path}: not valid JSON ({err})") from err
        if isinstance(spec, dict) and "elements" in spec:
            spec = spec["elements"]
        if not isinstance(spec, list):
            raise ExperimentError(f"{path}: expected a JSON list of elements")
        return spec
    path = base / str(cfg["lattice"])
    if not hasattr(Beamline, "from_lattice"):
        raise ExperimentError(
            f"{where}.lattice: reading lattice files needs Beamline.from_lattice, "
            "which this diffaccel lacks; give the beamline as spec or file (JSON)"
        )
    if not path.is_file():
        raise ExperimentError(f"{where}.lattice: {path}: file not found")
    try:
        line = Beamline.from_lattice(path, start=cfg.get("start"), end=cfg.get("end"))
    except (ValueError, KeyError, OSError) as err:
        raise ExperimentError(f"{where}.lattice: {path}: {err}") from err
    return line.to_spec()


# ------------------------------------------------------------------ screen
@dataclass(frozen=True)
class _Screen:
    pixel_size: tuple[float, float]
    center: tuple[float, float]
    rotate: int
    row0: str
    col0: str
    saturation: float | str | None
    max_saturated: int
    resolution_pixels: float | None

    def orient(self, pixels: np.ndarray) -> np.ndarray:
        """Camera frame -> rows of ascending y, columns of ascending x."""
        out = np.rot90(pixels, k=self.rotate // 90)
        if self.row0 == "top":
            out = out[::-1, :]
        if self.col0 == "right":
            out = out[:, ::-1]
        return np.ascontiguousarray(out)

    def record(self) -> dict:
        return {"rotate_deg": self.rotate, "row0": self.row0, "col0": self.col0}


def _screen(value: Any, where: str) -> _Screen:
    cfg = _mapping(value, where, _SCREEN_KEYS)
    if ("pixel_size" in cfg) == ("calibration" in cfg):
        raise ExperimentError(
            f"{where}: give exactly one of pixel_size [m] (one number or [x, y]) "
            "or calibration ({length_m: L, pixels: N}, or per axis {x: ..., y: ...})"
        )
    if "pixel_size" in cfg:
        pixel_size = _pair(cfg["pixel_size"], f"{where}.pixel_size")
    else:
        cal = _mapping(cfg["calibration"], f"{where}.calibration")

        def axis(c: Any, w: str) -> float:
            c = _mapping(c, w, {"length_m", "pixels"})
            if set(c) != {"length_m", "pixels"}:
                raise ExperimentError(f"{w}: expected length_m and pixels")
            n = _number(c["pixels"], f"{w}.pixels")
            if not n > 0:
                raise ExperimentError(f"{w}.pixels: expected > 0; found {n:g}")
            return _number(c["length_m"], f"{w}.length_m") / n

        if set(cal) <= {"x", "y"} and cal:
            if set(cal) != {"x", "y"}:
                raise ExperimentError(f"{where}.calibration: expected both x and y")
            pixel_size = (
                axis(cal["x"], f"{where}.calibration.x"),
                axis(cal["y"], f"{where}.calibration.y"),
            )
        else:
            v = axis(cal, f"{where}.calibration")
            pixel_size = (v, v)
    if not all(v > 0 for v in pixel_size):
        raise ExperimentError(
            f"{where}: pixel sizes must be > 0 [m]; found {pixel_size}"
        )
    center = _pair(cfg.get("center", [0.0, 0.0]), f"{where}.center")
    rotate = cfg.get("rotate", 0)
    if isinstance(rotate, bool) or rotate not in (0, 90, 180, 270):
        raise ExperimentError(
            f"{where}.rotate: expected 0, 90, 180 or 270 [degrees, counter-clockwise]; "
            f"found {rotate!r}"
        )
    row0 = str(cfg.get("row0", "top"))
    col0 = str(cfg.get("col0", "left"))
    if row0 not in ("top", "bottom"):
        raise ExperimentError(
            f"{where}.row0: expected top (row 0 is +y, the usual camera readout) or "
            f"bottom (row 0 is -y); found {row0!r}"
        )
    if col0 not in ("left", "right"):
        raise ExperimentError(
            f"{where}.col0: expected left (column 0 is -x) or right (column 0 is +x, "
            f"e.g. a mirror image); found {col0!r}"
        )
    sat = cfg.get("saturation", "auto")
    if sat not in ("auto", "none", None):
        sat = _number(sat, f"{where}.saturation")
    max_sat = cfg.get("max_saturated_pixels", 0)
    if isinstance(max_sat, bool) or not isinstance(max_sat, int) or max_sat < 0:
        raise ExperimentError(
            f"{where}.max_saturated_pixels: expected an integer >= 0; found {max_sat!r}"
        )
    res = cfg.get("resolution_pixels")
    if res is not None:
        res = _number(res, f"{where}.resolution_pixels")
    return _Screen(
        pixel_size,
        center,
        int(rotate),
        row0,
        col0,
        None if sat in ("none", None) else sat,
        max_sat,
        res,
    )


# ------------------------------------------------------------------ table
@dataclass
class _Row:
    line: int
    ref: str
    setting: tuple[float, ...]
    shot: int | None


def _read_table(
    path: Path, spec: list[dict], scan: str
) -> tuple[list[str], list[str], list[_Row]]:
    """Knob names, units and rows of a scan's CSV table."""
    if not path.is_file():
        raise ExperimentError(f"scan {scan!r}: image table {path}: file not found")
    try:
        with path.open(newline="") as fh:
            rows = list(csv.reader(fh))
    except (OSError, UnicodeDecodeError, csv.Error) as err:
        raise ExperimentError(f"{path}: not a readable CSV file ({err})") from err
    if not rows or not any(c.strip() for c in rows[0]):
        raise ExperimentError(f"{path}: empty table; expected a header row")
    header = [c.strip() for c in rows[0]]
    if "file" not in header:
        raise ExperimentError(
            f"{path}, row 1: no 'file' column; the header is {', '.join(header)}"
        )
    names_in_line = {e.get("name") for e in spec if isinstance(e, dict)}
    knobs: list[tuple[int, str, str]] = []
    for col, name in enumerate(header):
        if name in ("file", "shot"):
            continue
        m = _KNOB.match(name)
        if not m:
            raise ExperimentError(
                f"{path}, row 1: column {name!r} is not a knob; knob columns are "
                "named ELEMENT.param [unit], e.g. 'Q1.k1 [1/m^2]' (other columns: "
                "file, shot)"
            )
        if m["el"] not in names_in_line:
            known = ", ".join(str(n) for n in names_in_line if n)
            raise ExperimentError(
                f"{path}, row 1: column {name!r} names no element of scan {scan!r}'s "
                f"beamline (elements: {known})"
            )
        knobs.append((col, f"{m['el']}.{m['par']}", m["unit"].strip()))
    if not knobs:
        raise ExperimentError(
            f"{path}, row 1: no knob column (ELEMENT.param [unit], e.g. "
            "'Q1.k1 [1/m^2]')"
        )
    if len({k[1] for k in knobs}) != len(knobs):
        raise ExperimentError(f"{path}, row 1: a knob column appears twice")
    i_file = header.index("file")
    i_shot = header.index("shot") if "shot" in header else None
    out: list[_Row] = []
    for line, cells in enumerate(rows[1:], start=2):
        if not any(c.strip() for c in cells):
            continue
        if len(cells) != len(header):
            raise ExperimentError(
                f"{path}, row {line}: {len(cells)} cells; the header has {len(header)}"
            )
        ref = cells[i_file].strip()
        if not ref:
            raise ExperimentError(f"{path}, row {line}: empty 'file' cell")
        setting = tuple(
            _number(cells[c].strip(), f"{path}, row {line}, column {header[c]!r}")
            for c, _, _ in knobs
        )
        shot = None
        if i_shot is not None:
            text = cells[i_shot].strip()
            try:
                shot = int(text)
            except ValueError:
                raise ExperimentError(
                    f"{path}, row {line}, column 'shot': expected an integer; "
                    f"found {text!r}"
                ) from None
        out.append(_Row(line, ref, setting, shot))
    if not out:
        raise ExperimentError(f"{path}: no data rows below the header")
    return [k[1] for k in knobs], [k[2] for k in knobs], out


def _group(
    rows: list[_Row], path: Path, names: list[str], units: list[str]
) -> list[list[_Row]]:
    """Rows grouped by setting (first-appearance order), shots in order."""

    def show(setting: tuple[float, ...]) -> str:
        return ", ".join(
            f"{n} = {v:g} [{u}]" for n, v, u in zip(names, setting, units, strict=True)
        )

    by_file: dict[str, _Row] = {}
    for r in rows:
        if r.ref in by_file:
            first = by_file[r.ref]
            raise ExperimentError(
                f"{path}, row {r.line}: {r.ref} is already listed in row {first.line}"
                + (
                    ""
                    if first.setting == r.setting
                    else f" for another setting ({show(first.setting)})"
                )
                + "; each frame belongs to one shot of one setting"
            )
        by_file[r.ref] = r
    groups: dict[tuple[float, ...], list[_Row]] = {}
    last: tuple[float, ...] | None = None
    for r in rows:
        if r.setting in groups and r.setting != last and r.shot is None:
            first = groups[r.setting][0]
            raise ExperimentError(
                f"{path}, row {r.line}: setting {show(r.setting)} of row {first.line} "
                "is repeated after other settings, with different images; give a "
                "'shot' column (shots of one setting) or list each setting once"
            )
        group = groups.setdefault(r.setting, [])
        if r.shot is not None:
            for other in group:
                if other.shot == r.shot:
                    raise ExperimentError(
                        f"{path}, row {r.line}: setting {show(r.setting)} shot "
                        f"{r.shot} is repeated (row {other.line}) with a different "
                        "image"
                    )
        group.append(r)
        last = r.setting
    out = []
    for g in groups.values():
        if g[0].shot is not None:
            g = sorted(g, key=lambda r: r.shot)  # type: ignore[arg-type, return-value]
        out.append(g)
    counts = {len(g) for g in out}
    if len(counts) > 1:
        few = min(out, key=len)
        many = max(out, key=len)
        raise ExperimentError(
            f"{path}, row {few[0].line}: setting {show(few[0].setting)} has "
            f"{len(few)} shot(s), setting {show(many[0].setting)} (row "
            f"{many[0].line}) has {len(many)}; every setting of a scan needs the "
            "same number of shots"
        )
    return out


# ------------------------------------------------------------------ frames
def _frame(ref: str, base: Path, where: str) -> Frame:
    try:
        return read_frame(ref, base)
    except FileNotFoundError as err:
        raise ExperimentError(f"{where}: {err}") from err
    except FormatError as err:
        raise ExperimentError(f"{where}: {err}") from err


def _saturation_level(screen: _Screen, frame: Frame) -> float | None:
    if screen.saturation == "auto":
        return frame.max_value
    return screen.saturation  # type: ignore[return-value]


def _check_saturation(frame: Frame, screen: _Screen, where: str) -> None:
    level = _saturation_level(screen, frame)
    if level is None:
        return
    n = int((frame.pixels >= level).sum())
    if n > screen.max_saturated:
        raise ExperimentError(
            f"{where}: {n} pixel(s) at the saturation level {level:g} (the beam is "
            "clipped: lower the gain or exposure; screen.max_saturated_pixels "
            f"allows {screen.max_saturated})"
        )


def _background_refs(value: Any, base: Path, where: str) -> list[str]:
    if value is None:
        return []
    if isinstance(value, str):
        if any(c in value for c in "*?["):
            found = sorted(glob.glob(str(base / value)))
            if not found:
                raise ExperimentError(f"{where}: no file matches {value!r}")
            return [os.path.relpath(f, base) for f in found]
        return [value]
    if isinstance(value, list) and all(isinstance(v, str) for v in value):
        return list(value)
    raise ExperimentError(
        f"{where}: expected a file, a glob pattern or a list of files; found {value!r}"
    )


def _empty(images: torch.Tensor) -> torch.Tensor:
    """(K, S) True where an image shows no beam above its noise."""
    k, s, h, w = images.shape
    flat = images.reshape(k * s, 1, h, w).double()
    box = F.avg_pool2d(flat, kernel_size=3, stride=1) if min(h, w) >= 3 else flat
    med = flat.flatten(1).median(dim=1).values
    mad = (flat.flatten(1) - med[:, None]).abs().median(dim=1).values
    noise = 1.4826 * mad / 3.0
    peak = box.flatten(1).amax(dim=1)
    empty = (peak <= 0) | (peak < EMPTY_SIGNIFICANCE * noise)
    return empty.reshape(k, s)


# ------------------------------------------------------------------ preprocessing
def _preprocessing(value: Any, where: str) -> dict:
    cfg = dict(DEFAULT_PREPROCESSING)
    if value is None:
        return cfg
    given = _mapping(value, where, set(DEFAULT_PREPROCESSING))
    cfg.update(given)
    bg = cfg["background"]
    if isinstance(bg, str) or bg is None:
        bg = {"method": bg or "none"}
    bg = _mapping(bg, f"{where}.background", {"method", "clip", "edge_pixels"})
    bg = {**DEFAULT_PREPROCESSING["background"], **bg}
    if bg["method"] not in ("auto", "frames", "edge", "none"):
        raise ExperimentError(
            f"{where}.background.method: expected auto, frames, edge or none; "
            f"found {bg['method']!r}"
        )
    if not isinstance(bg["clip"], bool):
        raise ExperimentError(f"{where}.background.clip: expected true or false")
    cfg["background"] = bg
    return cfg


def _apply(ds: QuadScanDataset, cfg: dict, dark: torch.Tensor | None, where: str):
    bg = cfg["background"]
    method = bg["method"]
    if method == "auto":
        method = "frames" if dark is not None else "edge"
    if method == "frames":
        if dark is None:
            raise ExperimentError(
                f"{where}: preprocessing.background.method is frames but the scan "
                "lists no background frames"
            )
        ds = pre.subtract_background(ds, dark=dark, clip=bg["clip"])
    elif method == "edge":
        ds = pre.subtract_background(
            ds, edge_pixels=int(bg["edge_pixels"]), clip=bg["clip"]
        )
    yield "background", ds
    if cfg["median_filter"]:
        ds = pre.median_filter(ds, size=int(cfg["median_filter"]))
        yield "median_filter", ds
    if cfg["threshold"]:
        t = _mapping(
            cfg["threshold"], f"{where}.threshold", {"method", "value", "subtract"}
        )
        ds = pre.threshold(
            ds,
            method=t.get("method", "triangle"),
            value=None if t.get("value") is None else _number(t["value"], where),
            subtract=bool(t.get("subtract", False)),
        )
        yield "threshold", ds
    if cfg["center"]:
        ds = pre.center_centroids(ds, mode=cfg["center"])
        yield "center", ds
    if cfg["crop"]:
        c = _mapping(cfg["crop"], f"{where}.crop", {"n_rms", "shape"})
        if "shape" in c:
            ds = pre.crop_to_beam(ds, shape=tuple(int(v) for v in c["shape"]))
        else:
            ds = pre.crop_to_beam(ds, n_rms=_number(c.get("n_rms", 4.0), where))
        yield "crop", ds
    factor = cfg["bin"]
    if factor not in (1, None, [1, 1]):
        f = tuple(int(v) for v in factor) if isinstance(factor, list) else int(factor)
        ds = pre.pool(ds, factor=f)  # type: ignore[arg-type]
        yield "bin", ds
    if cfg["normalize"]:
        ds = pre.normalize(ds)
        yield "normalize", ds


# ------------------------------------------------------------------ scans
def _scan_frames(
    name: str,
    cfg: dict,
    base: Path,
    progress: Callable[[int], None] | None,
) -> tuple[
    list[dict],
    _Screen,
    list[str],
    list[str],
    list[list[_Row]],
    np.ndarray,
    np.ndarray | None,
    dict,
]:
    where = f"scan {name!r}"
    cfg = _mapping(cfg, where, _SCAN_KEYS)
    for key in ("beamline", "screen", "images"):
        if key not in cfg:
            raise ExperimentError(f"{where}: missing key {key!r}")
    spec = _beamline_spec(cfg["beamline"], base, f"{where}.beamline")
    screen = _screen(cfg["screen"], f"{where}.screen")
    table = base / str(cfg["images"])
    names, units, rows = _read_table(table, spec, name)
    groups = _group(rows, table, names, units)
    shape: tuple[int, int] | None = None
    first_ref = ""
    dtypes: set[str] = set()
    stack = None
    k, s = len(groups), len(groups[0])
    for i, group in enumerate(groups):
        for j, row in enumerate(group):
            here = f"{table}, row {row.line} ({row.ref})"
            frame = _frame(row.ref, table.parent, here)
            _check_saturation(frame, screen, here)
            pixels = screen.orient(frame.pixels)
            if shape is None:
                shape, first_ref = pixels.shape, row.ref
                stack = np.empty((k, s, *shape), dtype=np.float32)
            elif pixels.shape != shape:
                raise ExperimentError(
                    f"{here}: image of {frame.pixels.shape[0]} x "
                    f"{frame.pixels.shape[1]} pixels; {first_ref} has "
                    f"{shape[0]} x {shape[1]} (after rotation); every frame of a "
                    "scan needs the same shape"
                )
            dtypes.add(frame.dtype)
            stack[i, j] = pixels  # type: ignore[index]
            if progress is not None:
                progress(1)
    assert stack is not None and shape is not None
    refs = _background_refs(cfg.get("background"), base, f"{where}.background")
    dark = None
    if refs:
        acc = np.zeros(shape, dtype=np.float64)
        for ref in refs:
            here = f"{where}.background ({ref})"
            frame = _frame(ref, base, here)
            pixels = screen.orient(frame.pixels)
            if pixels.shape != shape:
                raise ExperimentError(
                    f"{here}: background frame of {frame.pixels.shape[0]} x "
                    f"{frame.pixels.shape[1]} pixels; the scan's images have "
                    f"{shape[0]} x {shape[1]} (after rotation)"
                )
            acc += pixels
            if progress is not None:
                progress(1)
        dark = acc / len(refs)
    record = {
        "step": "import",
        "scan": name,
        "table": os.path.relpath(table, base),
        "frames": [[r.ref for r in g] for g in groups],
        "rows": [[r.line for r in g] for g in groups],
        "background_frames": refs,
        "pixel_dtype": sorted(dtypes),
        "orientation": screen.record(),
        "pixel_size_camera": list(screen.pixel_size),
    }
    return spec, screen, names, units, groups, stack, dark, record


def count_frames(description: Mapping[str, Any], base: Path) -> int:
    """Frames an import will read (rows of every table plus background frames);
    0 where a table cannot be read (the import then names the problem)."""
    total = 0
    scans = description.get("scans")
    if not isinstance(scans, Mapping):
        return 0
    for cfg in scans.values():
        if not isinstance(cfg, Mapping):
            continue
        try:
            with (base / str(cfg.get("images"))).open(newline="") as fh:
                total += max(
                    sum(1 for r in csv.reader(fh) if any(c.strip() for c in r)) - 1, 0
                )
            total += len(_background_refs(cfg.get("background"), base, ""))
        except (OSError, ExperimentError, csv.Error, UnicodeDecodeError):
            continue
    return total


def import_experiment(
    path: str | os.PathLike,
    progress: Callable[[int], None] | None = None,
) -> MultiScanDataset:
    """Read the DAQ files an experiment description names into scans.

    Args:
        path: The description (YAML; schema in ``docs/file_formats.md``).
        progress: Called with 1 after each frame read (images and background
            frames; :func:`count_frames` gives the total).

    Returns:
        The scans (format version 2), one per entry of ``scans``, with
        per-shot images ``(K, S, H, W)``, preprocessed; the root metadata
        records the source, the description and every step.

    Raises:
        ExperimentError: one line naming the file (and CSV row) and the
            problem: a missing file, frames of unequal shapes, a saturated or
            empty image, a knob column naming no element, a setting repeated
            with different images, an invalid key or value.
        FileNotFoundError: if the description does not exist.
        ImportError: without the ``[images]`` extra where PNG/TIFF/YAML need it.
    """
    path = Path(path)
    doc = load_experiment(path)
    base = path.parent
    for key in ("p0c", "species", "scans"):
        if key not in doc:
            raise ExperimentError(f"{path}: missing key {key!r}")
    p0c = _number(doc["p0c"], f"{path}: p0c")
    species = str(doc["species"])
    scans_cfg = _mapping(doc["scans"], f"{path}: scans")
    if not scans_cfg:
        raise ExperimentError(f"{path}: scans: expected at least one scan")
    top_pre = doc.get("preprocessing")
    steps: list[dict] = []
    scans: dict[str, QuadScanDataset] = {}
    for name, cfg in scans_cfg.items():
        name = str(name)
        spec, screen, names, units, groups, stack, dark, record = _scan_frames(
            name, cfg, base, progress
        )
        where = f"scan {name!r}"
        pcfg = _preprocessing(
            cfg.get("preprocessing", top_pre) if isinstance(cfg, Mapping) else top_pre,
            f"{where}.preprocessing",
        )
        settings = torch.tensor([g[0].setting for g in groups], dtype=torch.float64)
        try:
            ds = QuadScanDataset(
                images=torch.from_numpy(stack),
                settings=settings,
                setting_names=names,
                setting_units=units,
                p0c=p0c,
                species=species,
                beamline_spec=spec,
                pixel_size=screen.pixel_size,
                center=screen.center,
                metadata={"preprocessing": []},
                resolution_pixels=screen.resolution_pixels,
            )
        except FormatError as err:
            raise ExperimentError(f"{path}: {where}: {err}") from err
        dark_t = None if dark is None else torch.from_numpy(dark).float()
        try:
            stages = _apply(ds, pcfg, dark_t, where)
            try:
                stage, ds = next(stages)
                empty = _empty(ds.images)
            except ValueError as err:  # a sum <= 0 after the subtraction
                m = re.search(r"setting (\d+) \(shot (\d+)\)", str(err))
                if m is None or "afterwards" not in str(err):
                    raise
                empty = torch.zeros(len(groups), len(groups[0]), dtype=torch.bool)
                empty[int(m[1]), int(m[2])] = True
            if bool(empty.any()):
                i, j = (int(v) for v in torch.nonzero(empty)[0])
                row = groups[i][j]
                raise ExperimentError(
                    f"{base / str(cfg['images'])}, row {row.line} ({row.ref}): empty "
                    f"image: no beam above the noise after background subtraction "
                    f"(peak of the 3 x 3 mean below {EMPTY_SIGNIFICANCE:g} times its "
                    "noise rms, or a sum <= 0)"
                )
            for stage, ds in stages:  # noqa: B007
                pass
        except (ValueError, FormatError) as err:
            if isinstance(err, ExperimentError):
                raise
            first = str(err).strip().splitlines()[0]
            m = re.search(r"setting (\d+) \(shot (\d+)\)", first)
            if m and int(m[1]) < len(groups) and int(m[2]) < len(groups[int(m[1])]):
                row = groups[int(m[1])][int(m[2])]
                first = f"row {row.line} ({row.ref}): {first}"
            raise ExperimentError(
                f"{base / str(cfg['images'])}: {where}, preprocessing: {first}"
            ) from err
        steps.append(record)
        for step in ds.metadata.get("preprocessing", []):
            steps.append({**step, "scan": name})
        scans[name] = ds
    metadata: dict[str, Any] = {
        "source": {"experiment": path.name},
        "preprocessing": steps,
    }
    if "description" in doc:
        metadata["description"] = str(doc["description"])
    if "metadata" in doc:
        metadata["experiment"] = _mapping(doc["metadata"], f"{path}: metadata")
    try:
        return MultiScanDataset(scans, metadata=metadata)
    except FormatError as err:
        raise ExperimentError(f"{path}: {err}") from err


def import_lines(dataset: MultiScanDataset) -> list[str]:
    """What an imported dataset holds, indented lines for ``data import`` to print.

    One line per scan (settings x shots, image size and pixel size [um], the
    knobs) and the preprocessing steps of the first scan.
    """
    lines = []
    for name, scan in dataset:
        k, s, h, w = scan.shape
        px, py = scan.pixel_size
        lines.append(
            f"  scan {name}: {k} settings x {s} shots, {h} x {w} pixels of "
            f"{px * 1e6:.4g} x {py * 1e6:.4g} um, knobs {', '.join(scan.setting_names)}"
        )
    steps = [
        step["step"]
        for step in dataset.metadata.get("preprocessing", [])
        if step.get("scan") == dataset.names[0]
    ]
    lines.append(f"  preprocessing ({dataset.names[0]}): {' -> '.join(steps)}")
    return lines
