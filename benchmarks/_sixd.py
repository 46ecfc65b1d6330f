"""The shared 6D benchmark: its files and acceptance limits.

Used by ``benchmarks/reconstruction_6d.py`` (train -> held-out test) and
``benchmarks/reconstruction_6d_beams.py`` (other beams in the same geometry).
"""

from __future__ import annotations

from pathlib import Path

DATA = Path(__file__).resolve().parents[1] / "data" / "phase_space"
TRAIN = DATA / "sixd_synthetic_train.h5"
TEST = DATA / "sixd_synthetic_test.h5"
KEYS = (
    "rms_x",
    "rms_px",
    "rms_y",
    "rms_py",
    "rms_z",
    "rms_pz",
    "emit_x",
    "emit_y",
    "emit_z",
    "emit_6d",
    "corr_diff_x_z",
    "corr_diff_y_py",
    "corr_diff_z_pz",
)
#: Acceptance limits: |relative error| of rms sizes, emittances, |corr diff|.
LIMITS = {
    **{f"rms_{c}": 0.05 for c in ("x", "px", "y", "py", "z", "pz")},
    "emit_x": 0.05,
    "emit_y": 0.05,
    "emit_z": 0.10,
    "emit_6d": 0.15,
    "corr_diff_x_z": 0.05,
    "corr_diff_y_py": 0.05,
    "corr_diff_z_pz": 0.05,
}
HELD_OUT_L1 = 0.15
WALL_LIMIT_S = 120.0
