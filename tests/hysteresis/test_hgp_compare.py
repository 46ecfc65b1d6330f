"""The H-GP of a magnet history against a plain GP of the same rows."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from diffaccel.data import OptionError, write_csv_atomic
from diffaccel.hysteresis.hgp_compare import (
    RANGE_MARGIN,
    fit_gps,
    gp_line,
    gp_setup,
    gp_summary,
    read_gp_data,
)
from diffaccel.hysteresis.synthetic import synthetic_measurement


@pytest.fixture(scope="module")
def fitted():
    current, field, _ = synthetic_measurement(noise=1e-3, seed=1)
    X, Y = current[::2, None], field[::2, None]  # 53 rows
    n_train = 40
    setup = gp_setup(X, Y, n_train, mesh_size=6, initial_state="negative")
    calls = []
    res, plain_fit = fit_gps(
        setup, restarts=2, max_iter=15, seed=0, callback=lambda r, m: calls.append(r)
    )
    return X, Y, setup, res, plain_fit, calls


def test_setup_covers_every_row_and_trains_on_the_first(fitted) -> None:
    X, _, setup, *_ = fitted
    lo, hi = float(X.min()), float(X.max())
    margin = RANGE_MARGIN * (hi - lo)
    assert setup.input_range == pytest.approx((lo - margin, hi + margin))
    assert setup.n_train == 40 and setup.prior.alpha.numel() == 21  # 6 * 7 / 2
    assert setup.model.train_X.shape[-2] == setup.plain.train_X.shape[-2] == 40


def test_summary_scores_both_models_on_the_held_out_rows(fitted) -> None:
    X, Y, setup, res, plain_fit, calls = fitted
    assert len(calls) == 2  # both density starts
    s = gp_summary(
        setup, X, Y, res, plain_fit, data="m.csv", x="I", y="B", plain_inputs=(),
        initial_state="negative",
    )  # fmt: skip
    assert (s["n_points"], s["train_rows"], s["test_rows"]) == (53, 40, 13)
    with torch.no_grad():
        pred = setup.model.posterior_sequence(X[40:]).mean.reshape(-1)
    held = float((pred - Y[40:, 0]).pow(2).mean().sqrt())
    assert s["heldout_rmse"] == pytest.approx(held)
    assert math.isfinite(s["plain_gp_heldout_rmse"])
    assert s["noise_sigma"] == res.noise_sigma and s["restart_mlls"] == list(
        res.restart_mlls
    )
    assert s["warnings"] == [] or all(isinstance(w, str) for w in s["warnings"])
    line = gp_line(s)
    assert line.startswith(f"H-GP noise sigma {res.noise_sigma:.4g} (plain GP ")
    assert (
        f"held-out rmse {held:.4g} (plain GP" in line and "on the last 13 rows" in line
    )
    s["heldout_rmse"] = None
    assert "held-out" not in gp_line(s)


def test_read_gp_data_stacks_the_columns_and_holds_out_the_last_rows(
    tmp_path: Path,
) -> None:
    path = tmp_path / "m.csv"
    rows = [[i % 5, 10 + i, 2 * i] for i in range(20)]
    write_csv_atomic(path, ["I", "q", "y"], rows)
    X, Y, n_tr = read_gp_data(path, "I", "y", ["q"], holdout=0.25)
    assert X.shape == (20, 2) and Y.shape == (20, 1) and n_tr == 15
    assert X[3].tolist() == [3.0, 13.0] and float(Y[3, 0]) == 6.0
    with pytest.raises(OptionError, match="given more than once") as err:
        read_gp_data(path, "I", "y", ["q", "q"])
    assert err.value.option == "--plain"
    with pytest.raises(OptionError, match="'y' is the --y column"):
        read_gp_data(path, "I", "y", ["y"])
    with pytest.raises(OptionError, match="no column 't'"):
        read_gp_data(path, "I", "y", time_column="t")
    with pytest.raises(ValueError, match="leaves 2 of 20 rows to fit"):
        read_gp_data(path, "I", "y", holdout=0.9)
    const = tmp_path / "c.csv"
    write_csv_atomic(const, ["I", "y"], [[1, i] for i in range(8)])
    with pytest.raises(ValueError, match="column 'I' is constant"):
        read_gp_data(const, "I", "y")
