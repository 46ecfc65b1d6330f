"""``diffaccel hysteresis``: fit a Preisach model to a magnet history and predict."""

from __future__ import annotations

import json
import math
from pathlib import Path

import click
import torch
from tqdm import tqdm

from diffaccel.data import (
    DEFAULT_INPUT_COLUMN,
    DEFAULT_OUTPUT_COLUMN,
    atomic_write,
    atomic_write_text,
    read_magnet_csv,
    write_csv_atomic,
)
from diffaccel.hysteresis import PreisachMesh, PreisachModel, fit_preisach
from diffaccel.plotting.hysteresis import plot_preisach_density, plot_preisach_fit

__all__ = ["hysteresis"]

MODEL_FILE = "model.pt"
CONFIG_FILE = "model.json"
SUMMARY_FILE = "summary.json"
FIGURES = ("fit.png", "density.png")
# margin added to the training input range so that nearby inputs stay valid
RANGE_MARGIN = 0.01


def _write_json(dest: Path, obj: dict) -> None:
    atomic_write_text(dest, json.dumps(obj, indent=2) + "\n")


def _rms(x: torch.Tensor) -> float | None:
    return float(x.pow(2).mean().sqrt()) if x.numel() else None


@click.group("hysteresis")
def hysteresis() -> None:
    """Preisach hysteresis models of magnets: fit and predict."""


@hysteresis.command("fit")
@click.argument("data", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option(
    "--train-rows",
    type=click.IntRange(min=1),
    required=True,
    help="Fit on the first N rows (time order); the rest are predicted.",
)
@click.option("--input", "input_col", default=DEFAULT_INPUT_COLUMN, show_default=True)
@click.option(
    "--output", "output_col", default=DEFAULT_OUTPUT_COLUMN, show_default=True
)
@click.option(
    "--out",
    "out_dir",
    type=click.Path(file_okay=False, path_type=Path),
    required=True,
    help="Folder for summary.json, model.pt, model.json and figures.",
)
@click.option(
    "--mesh-size",
    type=click.IntRange(min=2),
    default=44,
    show_default=True,
    help="Cells per axis of the triangular Preisach mesh (44: 990 hysterons).",
)
@click.option(
    "--smoothness",
    type=click.FloatRange(min=0),
    default=0.0,
    show_default=True,
    help="Weight of the density roughness penalty.",
)
@click.option("--steps", type=click.IntRange(min=1), default=300, show_default=True)
@click.option(
    "--optimizer",
    type=click.Choice(["lbfgs", "adam"]),
    default="lbfgs",
    show_default=True,
)
@click.option(
    "--initial-state",
    type=click.Choice(["negative", "positive", "demagnetized", "learned"]),
    default="negative",
    show_default=True,
    help="Magnet state before the first row.",
)
@click.option(
    "--input-range",
    type=(float, float),
    default=None,
    help="Model input range LO HI [input units]; default: training rows +- 1 %.",
)
@click.option("--force", is_flag=True, help="Overwrite files of an earlier fit in OUT.")
def fit_command(
    data: Path,
    train_rows: int,
    input_col: str,
    output_col: str,
    out_dir: Path,
    mesh_size: int,
    smoothness: float,
    steps: int,
    optimizer: str,
    initial_state: str,
    input_range: tuple[float, float] | None,
    force: bool,
) -> None:
    """Fit a Preisach model to the first N rows of DATA (CSV) and test on the rest."""
    try:
        hist = read_magnet_csv(data, input_col, output_col)
    except ValueError as err:
        raise click.ClickException(str(err)) from err
    if train_rows > len(hist):
        raise click.BadParameter(
            f"{train_rows} exceeds the {len(hist)} rows of {data}.",
            param_hint="--train-rows",
        )
    targets = [out_dir / n for n in (SUMMARY_FILE, MODEL_FILE, CONFIG_FILE, *FIGURES)]
    existing = [str(p) for p in targets if p.exists()]
    if existing and not force:
        raise click.ClickException(
            f"{out_dir} already holds {existing}; pass --force to overwrite."
        )
    u, y = hist.input, hist.output
    u_tr, y_tr = u[:train_rows], y[:train_rows]
    if input_range is None:
        lo, hi = float(u_tr.min()), float(u_tr.max())
        pad = RANGE_MARGIN * max(hi - lo, abs(hi), 1e-12)
        input_range = (lo - pad, hi + pad)
    try:
        model = PreisachModel(
            PreisachMesh.triangular(mesh_size),
            input_range=input_range,
            initial_state=initial_state,
        )
        # L-BFGS reports every objective evaluation (their number is not
        # known in advance); Adam every step
        total = steps if optimizer == "adam" else None
        unit = "step" if optimizer == "adam" else "eval"
        with tqdm(total=total, desc="fit", unit=unit, leave=False) as bar:

            def progress(step: int, loss: float) -> None:
                bar.update(1)
                bar.set_postfix(loss=f"{loss:.3g}", refresh=False)

            result = fit_preisach(
                model,
                u_tr,
                y_tr,
                optimizer=optimizer,
                steps=steps,
                smoothness=smoothness,
                callback=progress,
            )
        with torch.no_grad():
            u_te = u[train_rows:]
            in_range = (u_te >= input_range[0]) & (u_te <= input_range[1])
            if not bool(in_range.all()):
                raise ValueError(
                    f"test rows hold inputs outside the model's input range "
                    f"{input_range}; pass a wider --input-range."
                )
            pred = model(u)
    except ValueError as err:
        raise click.ClickException(str(err)) from err
    span = float(y.max() - y.min())
    resid = pred - y
    train_rmse, test_rmse = _rms(resid[:train_rows]), _rms(resid[train_rows:])

    def pct(v: float | None) -> float | None:
        return None if v is None else 100.0 * v / span

    summary = {
        "data": str(data),
        "input_column": input_col,
        "output_column": output_col,
        "rows": len(hist),
        "train_rows": train_rows,
        "test_rows": len(hist) - train_rows,
        "output_range": span,
        "train_rmse": train_rmse,
        "train_rmse_percent": pct(train_rmse),
        "test_rmse": test_rmse,
        "test_rmse_percent": pct(test_rmse),
        "fit_seconds": result.seconds,
        "optimizer": optimizer,
        "steps": result.steps,
        "mesh_size": mesh_size,
        "n_hysterons": int(model.alpha.numel()),
        "smoothness": smoothness,
        "initial_state": initial_state,
        "input_range": list(input_range),
    }
    out_dir.mkdir(parents=True, exist_ok=True)
    tensors = {k: v.detach().cpu().clone() for k, v in model.state_dict().items()}
    atomic_write(out_dir / MODEL_FILE, lambda p: torch.save(tensors, p))
    config = {**model.config(), "input_column": input_col, "output_column": output_col}
    _write_json(out_dir / CONFIG_FILE, config)
    fig = plot_preisach_fit(
        model,
        u,
        y,
        n_train=train_rows,
        input_label=input_col,
        output_label=output_col,
    )
    atomic_write(out_dir / "fit.png", lambda p: fig.savefig(p, format="png", dpi=120))
    fig = plot_preisach_density(model, input_label=input_col)
    atomic_write(
        out_dir / "density.png", lambda p: fig.savefig(p, format="png", dpi=120)
    )
    _write_json(out_dir / SUMMARY_FILE, summary)
    test_txt = (
        "n/a" if test_rmse is None else f"{test_rmse:.4g} ({pct(test_rmse):.3f} %)"
    )
    click.echo(
        f"fit {train_rows} rows in {result.seconds:.2f} s: train rmse "
        f"{train_rmse:.4g} ({pct(train_rmse):.3f} %), test rmse {test_txt} "
        f"of output range {span:.4g}; wrote {out_dir}"
    )


def load_fitted_model(fit_dir: Path) -> tuple[PreisachModel, dict]:
    """Model and config written by ``diffaccel hysteresis fit`` (safe loading)."""
    config = json.loads((fit_dir / CONFIG_FILE).read_text())
    tensors = torch.load(fit_dir / MODEL_FILE, weights_only=True, map_location="cpu")
    return PreisachModel.from_config(config, tensors), config


@hysteresis.command("predict")
@click.argument(
    "fit_dir", type=click.Path(exists=True, file_okay=False, path_type=Path)
)
@click.option(
    "--input",
    "data",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    required=True,
    help="CSV with the input column of the fit, rows in time order.",
)
@click.option(
    "--out", "out_file", type=click.Path(dir_okay=False, path_type=Path), required=True
)
@click.option("--force", is_flag=True, help="Overwrite OUT if it exists.")
def predict_command(fit_dir: Path, data: Path, out_file: Path, force: bool) -> None:
    """Predict the output for every row of a CSV, from the fit's initial state."""
    if out_file.exists() and not force:
        raise click.ClickException(f"{out_file} exists; pass --force to overwrite.")
    try:
        model, config = load_fitted_model(fit_dir)
    except (OSError, ValueError, KeyError, RuntimeError) as err:
        raise click.ClickException(f"cannot load a fit from {fit_dir}: {err}") from err
    in_col = config.get("input_column", DEFAULT_INPUT_COLUMN)
    out_col = config.get("output_column", DEFAULT_OUTPUT_COLUMN)
    try:
        hist = read_magnet_csv(data, in_col, out_col, require_output=False)
        with torch.no_grad():
            pred = model(hist.input)
    except ValueError as err:
        raise click.ClickException(str(err)) from err
    name = f"{out_col}_predicted"
    rows = [
        [*row, repr(float(p))] for row, p in zip(hist.rows, pred.tolist(), strict=True)
    ]
    write_csv_atomic(out_file, [*hist.header, name], rows, overwrite=force)
    finite = all(math.isfinite(v) for v in pred.tolist())
    click.echo(f"predicted {len(rows)} rows ({name}); wrote {out_file}")
    if not finite:
        raise click.ClickException("predictions contain non-finite values.")
