"""``diffaccel hysteresis gp-fit``: joint hysteresis GP of a measured beam response."""

from __future__ import annotations

from pathlib import Path

import click
from tqdm import tqdm

from diffaccel.cli.hysteresis import check_input_range, time_column_option
from diffaccel.cli.output import (
    IN_FILE,
    OUT_DIR,
    SHOW_DEFAULTS,
    click_errors,
    echo_warnings,
    force_option,
    out_option,
    output_folder,
)
from diffaccel.data import atomic_write_json
from diffaccel.hysteresis.hgp_compare import (
    HOLDOUT,
    fit_gps,
    gp_line,
    gp_setup,
    gp_summary,
    read_gp_data,
)
from diffaccel.hysteresis.mesh import MAX_CLI_MESH_SIZE
from diffaccel.plotting.files import save_png
from diffaccel.plotting.hgp import plot_hgp_history

__all__ = ["gp_fit"]

SUMMARY_FILE = "gp_summary.json"
FIGURE_FILE = "gp_fit.png"
# largest seed torch takes
SEED_MAX = 2**64 - 1


@click.command("gp-fit", context_settings=SHOW_DEFAULTS)
@click.argument("data", type=IN_FILE)
@click.option(
    "--x",
    "x_col",
    required=True,
    help="Column of the hysteretic input (magnet current), rows in time order.",
)
@click.option("--y", "y_col", required=True, help="Column of the beam response.")
@time_column_option
@click.option(
    "--plain",
    "plain_cols",
    multiple=True,
    help="Extra non-hysteretic input column (repeatable).",
)
@out_option(OUT_DIR, f"Folder for {SUMMARY_FILE} and {FIGURE_FILE}.", "out_dir")
@click.option(
    "--mesh-size",
    type=click.IntRange(min=2, max=MAX_CLI_MESH_SIZE),
    default=30,
    help="Cells per axis of the triangular Preisach mesh (30: 465 hysterons).",
)
@click.option(
    "--restarts",
    type=click.IntRange(min=1),
    default=3,
    help="Optimisations of the H-GP, ranked by marginal likelihood: from the "
    "Preisach fit's density, from a uniform density (always both), the rest "
    "from prior samples.",
)
@click.option(
    "--max-iter",
    type=click.IntRange(min=1),
    default=200,
    help="L-BFGS-B iterations per restart.",
)
@click.option(
    "--input-range",
    type=(float, float),
    default=None,
    callback=check_input_range,
    help="Preisach input range LO HI [units of --x]; default: data range +- 1 %.",
)
@click.option(
    "--initial-state",
    type=click.Choice(["negative", "positive", "demagnetized"]),
    default="negative",
    help="Magnet state before the first row.",
)
@click.option(
    "--holdout",
    type=click.FloatRange(min=0.0, max=0.9),
    default=HOLDOUT,
    help="Share of the last rows held out: both GPs are fitted on the rows "
    "before them and predict them (the H-GP continuing the history); 0 fits "
    "every row.",
)
@click.option(
    "--seed",
    type=click.IntRange(min=0, max=SEED_MAX),
    default=0,
    help="Seed of the random restarts.",
)
@force_option("Replace an earlier result in OUT (at the end).")
def gp_fit(
    data: Path,
    x_col: str,
    y_col: str,
    time_column: str | None,
    plain_cols: tuple[str, ...],
    out_dir: Path,
    mesh_size: int,
    restarts: int,
    max_iter: int,
    input_range: tuple[float, float] | None,
    initial_state: str,
    holdout: float,
    seed: int,
    force: bool,
) -> None:
    """Fit a joint hysteresis GP (Preisach state -> response) to DATA.csv.

    Rows are measurements in the order the settings were applied (checked
    with a time column, see --time-column). The H-GP's density starts from a
    Preisach fit of the response (offset, linear term, density), the GP sees
    the input as well as the magnetisation, and its noise prior is centred on
    that fit's residual; restarts are ranked by marginal likelihood. A plain
    GP of the same rows is fitted for comparison. Writes a summary JSON
    (noise, held-out rms errors of both, warnings) and a figure of the fit
    into OUT; a warning line is printed where the H-GP is worse than the
    plain GP.
    """
    with click_errors():
        X, Y, n_tr = read_gp_data(data, x_col, y_col, plain_cols, time_column, holdout)
        setup = gp_setup(
            X,
            Y,
            n_tr,
            mesh_size=mesh_size,
            initial_state=initial_state,
            input_range=input_range,
        )
    with output_folder(
        out_dir,
        "hysteresis gp-fit",
        force=force,
        owned=(SUMMARY_FILE, FIGURE_FILE),
        inputs=[data],
    ) as folder:
        with tqdm(
            total=max(restarts, 2), desc="H-GP restarts", unit="fit", disable=None
        ) as bar:

            def progress(restart: int, mll: float) -> None:
                bar.set_postfix(mll=f"{mll:.3f}", refresh=False)
                bar.update(1)

            res, plain_fit = fit_gps(
                setup, restarts=restarts, max_iter=max_iter, seed=seed,
                callback=progress,
            )  # fmt: skip
        summary = gp_summary(
            setup, X, Y, res, plain_fit, data=str(data), x=x_col, y=y_col,
            plain_inputs=plain_cols, initial_state=initial_state,
        )  # fmt: skip
        fig = plot_hgp_history(setup.model, column=0, xlabel=x_col, ylabel=y_col)
        save_png(fig, folder.path / FIGURE_FILE)
        atomic_write_json(folder.path / SUMMARY_FILE, summary)
    echo_warnings(summary["warnings"])
    click.echo(
        f"{gp_line(summary)}; wrote {out_dir / SUMMARY_FILE}, {out_dir / FIGURE_FILE}"
    )
