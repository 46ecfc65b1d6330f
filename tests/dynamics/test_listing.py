"""Beamline specs as a text table."""

from __future__ import annotations

from diffaccel.dynamics.listing import describe_entry, spec_table


def test_describe_entry_gives_units_and_skips_name_and_type() -> None:
    entry = {
        "type": "Screen", "name": "S", "shape": [4, 6], "pixel_size": [1e-4, 2e-4],
        "center": [0.0, 1e-3], "tilt": 0.5, "fint": 0.25, "unknown": 3.0,
    }  # fmt: skip
    assert describe_entry(entry) == (
        "shape = 4 x 6 px, pixel_size = (0.0001, 0.0002) m, center = (0, 0.001) m, "
        "tilt = 0.5 rad, fint = 0.25, unknown = 3"
    )
    assert describe_entry({"type": "Custom", "name": "M", "matrix": [[1.0]]}) == (
        "matrix = (7 x 7 affine map)"
    )


def test_spec_table_places_each_element_at_its_entrance() -> None:
    spec = [
        {"type": "Drift", "name": "D1", "length": 0.5},
        {"type": "Quadrupole", "name": "Q1", "length": 0.1, "k1": 2.0},
        {"type": "Screen", "name": "YAG"},
    ]
    header, *rows = spec_table(spec)
    assert header.split() == ["s", "[m]", "name", "type", "parameters"]
    assert [float(r.split()[0]) for r in rows] == [0.0, 0.5, 0.6]
    assert rows[1].endswith("Quadrupole  length = 0.1 m, k1 = 2 1/m^2")
    assert spec_table([]) == ["     s [m]  name  type  parameters"]  # header only
