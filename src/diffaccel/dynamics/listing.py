"""Beamline specs (``Beamline.to_spec()``) as a text table, one row per element."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

__all__ = ["UNITS", "describe_entry", "spec_table"]

#: Units of element parameters, for the listing.
UNITS = {
    "length": "m",
    "k1": "1/m^2",
    "k2": "1/m^3",
    "ks": "1/m",
    "angle": "rad",
    "e1": "rad",
    "e2": "rad",
    "tilt": "rad",
    "dx": "m",
    "dy": "m",
    "voltage": "V",
    "frequency": "Hz",
    "phase": "rad",
    "hgap": "m",
    "hgapx": "m",
    "fint": "",
    "fintx": "",
    "num_steps": "",
}


def describe_entry(entry: Mapping[str, Any]) -> str:
    """``key = value unit`` for each parameter of a beamline spec entry.

    Example:
        >>> describe_entry({"type": "Quadrupole", "name": "Q1", "length": 0.1,
        ...                 "k1": -2.5})
        'length = 0.1 m, k1 = -2.5 1/m^2'
    """
    parts = []
    for key, value in entry.items():
        if key in ("type", "name"):
            continue
        if key == "matrix":
            parts.append("matrix = (7 x 7 affine map)")
        elif key == "shape":
            parts.append(f"shape = {value[0]} x {value[1]} px")
        elif key in ("pixel_size", "center"):
            parts.append(f"{key} = ({value[0]:.6g}, {value[1]:.6g}) m")
        else:
            unit = UNITS.get(key, "")
            parts.append(f"{key} = {value:.10g}{' ' + unit if unit else ''}")
    return ", ".join(parts)


def spec_table(spec: Sequence[Mapping[str, Any]]) -> list[str]:
    """A header and one row per element: position s [m] at its entrance, name,
    type and parameters (:func:`describe_entry`).

    Example:
        >>> rows = spec_table([{"type": "Drift", "name": "D1", "length": 1.0},
        ...                    {"type": "Screen", "name": "YAG1", "shape": [4, 6]}])
        >>> print("\\n".join(rows))
             s [m]  name  type    parameters
          0.000000  D1    Drift   length = 1 m
          1.000000  YAG1  Screen  shape = 4 x 6 px
    """
    width = max((len(e["name"]) for e in spec), default=4)
    kinds = max((len(e["type"]) for e in spec), default=4)
    rows = [f"{'s [m]':>10}  {'name':<{width}}  {'type':<{kinds}}  parameters"]
    s = 0.0
    for entry in spec:
        rows.append(
            f"{s:10.6f}  {entry['name']:<{width}}  {entry['type']:<{kinds}}  "
            f"{describe_entry(entry)}"
        )
        s += float(entry.get("length", 0.0))
    return rows
