"""``diffaccel hysteresis fit``: fit a Preisach model to a magnet history."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click
from tqdm import tqdm

from diffaccel.cli.hysteresis import (
    check_finite,
    check_input_range,
    checked,
    time_column_option,
)
from diffaccel.cli.output import (
    IN_FILE,
    OUT_DIR,
    SHOW_DEFAULTS,
    click_errors,
    echo_lines,
    force_option,
    out_option,
    output_folder,
)
from diffaccel.data import (
    DEFAULT_INPUT_COLUMN,
    DEFAULT_OUTPUT_COLUMN,
    atomic_write_json,
)
from diffaccel.hysteresis import CONFIG_FILE, MODEL_FILE, STREAM_FILE, save_fit
from diffaccel.hysteresis.fit_report import (
    fit_history,
    fit_line,
    fit_messages,
    read_fit_history,
)
from diffaccel.hysteresis.predictive import (
    MAX_MESH_SIZE,
    check_mesh_size,
    min_training_rows,
    parse_mesh_adapt,
)
from diffaccel.plotting.hysteresis import FIT_FIGURES, write_fit_figures

__all__ = ["fit_command"]

SUMMARY_FILE = "summary.json"
# beyond it the data term (a normalised mse, ~1 at most) is lost in the float64
# round-off of the penalty, and far beyond it the loss overflows
MAX_SMOOTHNESS = 1e12


@click.command("fit", context_settings=SHOW_DEFAULTS)
@click.argument("data", type=IN_FILE)
@click.option(
    "--train-rows",
    type=click.IntRange(min=1),
    required=True,
    help=f"Fit on the first N rows (time order; at least {min_training_rows()}, "
    "some held out for validation); the rest are predicted.",
)
@click.option(
    "--input",
    "input_col",
    default=DEFAULT_INPUT_COLUMN,
    help="Column of the magnet's input (e.g. the current [A]).",
)
@click.option(
    "--output",
    "output_col",
    default=DEFAULT_OUTPUT_COLUMN,
    help="Column of the measured output (e.g. the integrated field [T m]).",
)
@time_column_option
@out_option(
    OUT_DIR,
    "Folder for summary.json, model.pt, model.json, stream.npz and figures.",
    "out_dir",
)
@click.option(
    "--mesh-size",
    type=click.IntRange(min=2),
    default=20,
    callback=checked(lambda size: check_mesh_size(size) or size),
    help="Cells per axis of the triangular Preisach mesh (20: 210 hysterons; "
    "chosen on validation rows held out of the training rows, see "
    f"benchmarks/preisach_acceptance.py); at most {MAX_MESH_SIZE}, as the "
    "predictive band needs dense hysteron x hysteron matrices.",
)
@click.option(
    "--symmetric/--no-symmetric",
    default=None,
    help="Density symmetric about zero input, mu(a, b) = mu(-b, -a), with an "
    "odd output B(-H) = -B(H) (the default input range is then centred on 0). "
    "Default: symmetric when the input range is centred on 0 or the training "
    "inputs and outputs both change sign (bipolar magnets, B-H loops).",
)
@click.option(
    "--odd/--no-odd",
    default=None,
    help="Odd output, B(-H) = -B(H) at mirrored states (no fitted offset). "
    "Default: odd when the density is symmetric and the input range centred "
    "on 0; --no-odd fits an offset (e.g. a probe offset at zero field).",
)
@click.option(
    "--mesh-adapt",
    default="auto",
    callback=checked(parse_mesh_adapt),
    help="Share of the mesh placed where the training output changes (0: a "
    "regular mesh; resolves coercive fields far below the input range); "
    "'auto' chooses among 0, 0.8 and 0.95 on every fourth training row.",
)
@click.option(
    "--smoothness",
    type=click.FloatRange(min=0, max=MAX_SMOOTHNESS),
    default=0.0,
    callback=check_finite,
    help="Weight of the density roughness penalty.",
)
@click.option(
    "--steps",
    type=click.IntRange(min=1),
    default=300,
    help="L-BFGS iterations per fit.",
)
@click.option(
    "--initial-state",
    type=click.Choice(["negative", "positive", "demagnetized", "learned"]),
    default="negative",
    help="Magnet state before the first row (demagnetized: a virgin curve; "
    "its input range is then centred on 0).",
)
@click.option(
    "--input-range",
    type=(float, float),
    default=None,
    callback=check_input_range,
    help="Model input range LO HI [input units]; default: training rows +- 1 % "
    "(+- 1.01 max|input| for --initial-state demagnetized).",
)
@click.option("--no-figures", is_flag=True, help="Skip fit.png and density.png.")
@force_option("Replace an earlier fit in OUT (at the end).")
def fit_command(
    data: Path,
    train_rows: int,
    input_col: str,
    output_col: str,
    time_column: str | None,
    out_dir: Path,
    no_figures: bool,
    force: bool,
    **fit_options: Any,
) -> None:
    """Fit a Preisach model to the first N rows of DATA (CSV) and test on the rest.

    Rows are measurements in the order they were made (checked with a time
    column, see --time-column).
    """
    with click_errors(OSError, ValueError):
        hist = read_fit_history(data, input_col, output_col, time_column, train_rows)
    with output_folder(
        out_dir,
        "hysteresis fit",
        force=force,
        owned=(SUMMARY_FILE, MODEL_FILE, CONFIG_FILE, STREAM_FILE, *FIT_FIGURES),
        inputs=[data],
    ) as folder:
        with tqdm(desc="fit", unit="eval", leave=False) as bar, click_errors():

            def progress(step: int, loss: float) -> None:
                bar.update(1)
                bar.set_postfix(loss=f"{loss:.3g}", refresh=False)

            # --mesh-size, --symmetric, --odd, --mesh-adapt, --smoothness, ...
            fit, score = fit_history(
                hist, train_rows, data=str(data), callback=progress, **fit_options
            )
        save_fit(
            folder.path,
            fit.model,
            fit.band,
            extra={"input_column": input_col, "output_column": output_col},
        )
        if not no_figures:
            write_fit_figures(
                folder.path, fit.model, hist.input, hist.output, train_rows,
                score.std, input_col, output_col,
            )  # fmt: skip
        atomic_write_json(folder.path / SUMMARY_FILE, score.summary)
    echo_lines(fit_messages(fit, score), err=True)
    click.echo(f"{fit_line(score.summary)}; wrote {out_dir}")
