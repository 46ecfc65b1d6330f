"""Figures of the experiment design."""

from __future__ import annotations

from pathlib import Path

import matplotlib
import pytest

from diffaccel.plotting.design import (
    plot_expected_std,
    plot_spectrum,
    write_design_figures,
)

matplotlib.use("Agg")


def test_spectrum_names_the_unseen_directions() -> None:
    obs = {
        "singular_values": [1.0, 0.3, 2e-3, 3e-5],
        "unseen": [
            {"singular_value": 2e-3, "words": "py-z together with z-z"},
            {"singular_value": 3e-5, "words": "px-pz together with pz-pz"},
        ],
        "not_seen": [],
    }
    fig = plot_spectrum(obs)
    texts = " ".join(t.get_text() for t in fig.axes[0].texts)
    assert "py-z together with z-z" in texts and "px-pz together with pz-pz" in texts
    assert [p.get_height() for p in fig.axes[0].patches] == obs["singular_values"]


def test_expected_std_has_one_line_per_quantity_from_zero_images() -> None:
    report = {
        "targets": ["emit_z"],
        "baseline_std": {"emit_z": 0.6, "emit_x": 0.01, "rms_pz": 0.2},
        "recommended": [
            {
                "n_images": 3,
                "all_std": {"emit_z": 0.05, "emit_x": 0.01, "rms_pz": 0.02},
            },
            {
                "n_images": 2,
                "all_std": {"emit_z": 0.04, "emit_x": 0.01, "rms_pz": 0.01},
            },
        ],
    }
    fig = plot_expected_std(report)
    lines = fig.axes[0].get_lines()
    assert [ln.get_label() for ln in lines] == ["emit_z", "rms_pz"]  # emit_x: flat
    assert list(lines[0].get_xdata()) == [0, 3, 5]
    assert list(lines[0].get_ydata()) == [60.0, 5.0, 4.0]


def test_write_design_figures_never_replaces_a_file(tmp_path: Path) -> None:
    obs = {"singular_values": [1.0, 0.3], "unseen": [], "not_seen": []}
    folder = tmp_path / "plots"
    (written,) = write_design_figures(folder, obs)
    assert written == folder / "singular_values.png"
    assert written.read_bytes().startswith(b"\x89PNG")
    with pytest.raises(FileExistsError) as err:
        write_design_figures(folder, obs)
    assert err.value.filename == str(written)
