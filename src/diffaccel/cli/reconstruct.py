"""``diffaccel reconstruct`` and ``diffaccel predict``: phase-space reconstruction."""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Any

import click
import numpy as np
import torch
from tqdm import tqdm

from diffaccel.data import (
    FormatError,
    QuadScanDataset,
    atomic_write,
    atomic_write_text,
    read_quad_scan,
    write_openpmd_particles,
)
from diffaccel.plotting.reconstruction import (
    plot_corner,
    plot_image_comparison,
    plot_rms_evolution,
    plot_training_curves,
)
from diffaccel.reconstruction import (
    Reconstruction,
    ReconstructionConfig,
    ScreenForwardModel,
    StepInfo,
    image_errors,
    load,
    moment_errors,
    reconstruct,
    sliced_wasserstein,
)
from diffaccel.reconstruction.training import checkpoint_config

__all__ = ["predict", "reconstruct_command", "run_reconstruction"]

CHECKPOINT = "checkpoint.pt"
_DEFAULTS = ReconstructionConfig()


def parse_train_indices(text: str, k: int) -> list[int]:
    """``even`` | ``odd`` | ``all`` | ``0,2,4`` -> indices in ``[0, k)``."""
    t = text.strip().lower()
    if t == "even":
        return list(range(0, k, 2))
    if t == "odd":
        return list(range(1, k, 2))
    if t == "all":
        return list(range(k))
    try:
        idx = [int(v) for v in t.split(",") if v.strip()]
    except ValueError as err:
        raise click.BadParameter(
            f"expected even, odd, all or a comma-separated list; got {text!r}"
        ) from err
    bad = [i for i in idx if not 0 <= i < k]
    if not idx or bad or len(set(idx)) != len(idx):
        raise click.BadParameter(
            f"indices must be distinct and in [0, {k}); got {text!r}"
        )
    return idx


def _clean(obj: Any) -> Any:
    """Replace NaN/inf by None so the JSON is standard."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _clean(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_clean(v) for v in obj]
    return obj


def summarize(
    result: Reconstruction, dataset: QuadScanDataset, train_idx: list[int]
) -> dict[str, Any]:
    """Moments with ensemble spread, flags and metrics for ``summary.json``."""
    k = dataset.n_settings
    test_idx = [i for i in range(k) if i not in set(train_idx)]
    pred = result.predict_images(dataset.settings)
    meas = dataset.mean_images()
    metrics: dict[str, Any] = {
        "images_train": image_errors(pred[train_idx], meas[train_idx]),
    }
    if test_idx:
        metrics["images_held_out"] = image_errors(pred[test_idx], meas[test_idx])
    moments = result.moments()
    unconstrained = result.unconstrained_coordinates()
    rel_spread = {}
    for i, c in enumerate(("x", "px", "y", "py", "z", "pz")):
        m, s = moments["rms"]["mean"][i], moments["rms"]["std"][i]
        rel_spread[c] = s / m if m > 0 else None
    if dataset.ground_truth is not None:
        sample = result.sample(100_000)
        truth = dataset.ground_truth.to(torch.float64)
        dims = result.config.dims
        metrics["ground_truth"] = moment_errors(sample, truth)
        g = torch.Generator().manual_seed(0)
        metrics["ground_truth"][f"sliced_wasserstein_{dims}d"] = float(
            sliced_wasserstein(sample[:20_000, :dims], truth[:, :dims], generator=g)
        )
    return _clean(
        {
            "dataset": dataset.metadata.get("source_path", None),
            "config": result.config.to_dict(),
            "train_indices": train_idx,
            "held_out_indices": test_idx,
            "snapshots": result.n_snapshots,
            "moments": moments,
            "rms_relative_ensemble_spread": rel_spread,
            "unconstrained_coordinates": unconstrained,
            "unconstrained_note": (
                "coordinates the scan does not see to first order (their column of "
                "the transfer matrices to screen x/y is ~0); their values follow the "
                "prior (ReconstructionConfig.longitudinal_scale), so their moments "
                "are unknown: the small ensemble spread of these coordinates is NOT "
                "an uncertainty estimate"
            ),
            "uncertainty_note": (
                "std = spread over snapshot-ensemble members; it describes "
                "optimisation scatter and under-covers the actual error (on "
                "benchmarks with known truth the error was several std)"
            ),
            "metrics": metrics,
            "timings_s": result.info.get("timings_s", {}),
        }
    )


def write_figures(
    result: Reconstruction, dataset: QuadScanDataset, train_idx: list[int], out: Path
) -> list[Path]:
    """Write the four PNG figures into ``out``; returns their paths."""
    k = dataset.n_settings
    pred = result.predict_images(dataset.settings)
    train = set(train_idx)
    figs = {
        "phase_space.png": plot_corner(result, dataset.ground_truth),
        "images.png": plot_image_comparison(
            dataset.mean_images(),
            pred,
            dataset.settings,
            setting_name=dataset.setting_names[0],
            extent=result.forward.extent_mm(),
            held_out=[i not in train for i in range(k)],
        ),
        "training.png": plot_training_curves(result),
        "rms_evolution.png": plot_rms_evolution(result, dataset.ground_truth),
    }
    paths = []
    for name, fig in figs.items():
        path = out / name
        atomic_write(path, lambda p, fig=fig: fig.savefig(p, format="png", dpi=110))
        paths.append(path)
    return paths


def prepare_out_dir(out: Path, force: bool, resume: bool) -> None:
    """Refuse a non-empty ``out`` unless ``force`` or ``resume``."""
    if out.exists() and not out.is_dir():
        raise click.ClickException(f"--out {out} exists and is not a directory")
    if out.exists() and any(out.iterdir()) and not (force or resume):
        raise click.ClickException(
            f"--out {out} is not empty; pass --force to overwrite or --resume to "
            "continue an interrupted run"
        )
    out.mkdir(parents=True, exist_ok=True)
    if force and not resume:
        ck = out / CHECKPOINT
        if ck.exists():
            ck.unlink()


def run_reconstruction(
    dataset_path: Path,
    out: Path,
    config: ReconstructionConfig,
    train_indices: str,
    device: str,
    resume: bool,
    figures: bool = True,
    dataset: QuadScanDataset | None = None,
) -> dict[str, Any]:
    """Reconstruct, then write ensemble, summary.json, particles and figures."""
    t0 = time.perf_counter()
    try:
        ds = dataset if dataset is not None else read_quad_scan(dataset_path)
    except (FormatError, OSError) as err:
        raise click.ClickException(f"cannot read {dataset_path}: {err}") from err
    idx = parse_train_indices(train_indices, ds.n_settings)
    ck = out / CHECKPOINT
    if resume and ck.exists():
        try:
            config = checkpoint_config(ck)
        except Exception as err:
            raise click.ClickException(f"cannot resume from {ck}: {err}") from err
    bar = tqdm(total=config.epochs, desc="reconstruct", unit="step", leave=False)

    def callback(info: StepInfo) -> None:
        bar.n = info.step
        bar.set_postfix(image=f"{info.image_loss:.4f}", lr=f"{info.lr:.1e}")
        bar.refresh()

    try:
        result = reconstruct(
            ds,
            config,
            train_indices=idx,
            checkpoint=ck,
            resume=resume,
            callback=callback,
            device=device,
        )
    except ValueError as err:
        raise click.ClickException(str(err)) from err
    finally:
        bar.close()
    t_train = time.perf_counter() - t0
    result.info["dataset"] = str(dataset_path)
    result.save(out, overwrite=True)
    summary = summarize(result, ds, idx)
    summary["dataset"] = str(dataset_path)
    parts = write_openpmd_particles(
        out / "particles.h5", result.sample(100_000), ds.p0c, ds.species, overwrite=True
    )
    summary["particles_file"] = parts.name
    if figures:
        summary["figures"] = [p.name for p in write_figures(result, ds, idx, out)]
    summary["timings_s"]["total_wall"] = time.perf_counter() - t0
    summary["timings_s"]["reconstruct_wall"] = t_train
    atomic_write_text(out / "summary.json", json.dumps(_clean(summary), indent=2))
    return summary


@click.command("reconstruct")
@click.argument("dataset", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option(
    "--out",
    type=click.Path(file_okay=False, path_type=Path),
    required=True,
    help="Output directory (ensemble, summary.json, figures).",
)
@click.option(
    "--particles",
    type=click.IntRange(min=16),
    default=_DEFAULTS.n_particles,
    show_default=True,
    help="Fresh particles per training step.",
)
@click.option(
    "--epochs",
    type=click.IntRange(min=1),
    default=_DEFAULTS.epochs,
    show_default=True,
    help="Optimisation steps (multiple of --snapshots).",
)
@click.option(
    "--snapshots",
    type=click.IntRange(min=1),
    default=_DEFAULTS.snapshots,
    show_default=True,
    help="Ensemble members (cosine cycles).",
)
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--device", default="cpu", show_default=True, help="cpu, cuda, cuda:1...")
@click.option(
    "--train-indices",
    default="all",
    show_default=True,
    help="Settings to train on: all, even, odd, or a list like 0,2,4; the others "
    "are held out and scored (use 'even' to validate on the odd settings).",
)
@click.option(
    "--dims",
    type=click.Choice(["4", "6"]),
    default="4",
    show_default=True,
    help="4: transverse phase space only; 6: also z, pz (weakly constrained).",
)
@click.option(
    "--image-loss",
    type=click.Choice(["kl", "l1", "l2"]),
    default=_DEFAULTS.image_loss,
    show_default=True,
)
@click.option(
    "--blur",
    type=click.FloatRange(min=0),
    default=_DEFAULTS.blur_pixels,
    show_default=True,
    help="Point-spread rms of simulated images [pixels].",
)
@click.option("--no-figures", is_flag=True, help="Skip the PNG figures.")
@click.option("--force", is_flag=True, help="Overwrite a non-empty --out.")
@click.option("--resume", is_flag=True, help="Continue from --out/checkpoint.pt.")
def reconstruct_command(
    dataset: Path,
    out: Path,
    particles: int,
    epochs: int,
    snapshots: int,
    seed: int,
    device: str,
    train_indices: str,
    dims: str,
    image_loss: str,
    blur: float,
    no_figures: bool,
    force: bool,
    resume: bool,
) -> None:
    """Reconstruct a beam's phase space from the quad-scan file DATASET."""
    prepare_out_dir(out, force, resume)
    try:
        config = ReconstructionConfig(
            dims=int(dims),
            n_particles=particles,
            epochs=epochs,
            snapshots=snapshots,
            seed=seed,
            image_loss=image_loss,  # type: ignore[arg-type]
            blur_pixels=blur,
        )
    except ValueError as err:
        raise click.ClickException(str(err)) from err
    summary = run_reconstruction(
        dataset, out, config, train_indices, device, resume, figures=not no_figures
    )
    m = summary["metrics"]
    click.echo(f"wrote {out / 'summary.json'}")
    if "images_held_out" in m:
        click.echo(
            f"held-out image relative L1: {m['images_held_out']['relative_l1']:.4f}"
        )
    click.echo(f"train image relative L1: {m['images_train']['relative_l1']:.4f}")
    if summary["unconstrained_coordinates"]:
        click.echo(
            "not constrained by the scan: "
            + ", ".join(summary["unconstrained_coordinates"])
        )


@click.command("predict")
@click.argument(
    "result_dir", type=click.Path(exists=True, file_okay=False, path_type=Path)
)
@click.option(
    "--dataset",
    "dataset_path",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    default=None,
    help="Predict for this file's settings and screen grid.",
)
@click.option(
    "--settings",
    "settings_text",
    default=None,
    help="Instead of --dataset: values of the scanned parameter(s) of the "
    "training scan, e.g. '-3,0,2.5' (one parameter) or '1:2;3:4' (rows ';').",
)
@click.option(
    "--out",
    type=click.Path(dir_okay=False, path_type=Path),
    required=True,
    help="Output .npy file, (K, H, W) float32, each image sums to 1.",
)
@click.option(
    "--particles",
    type=click.IntRange(min=100),
    default=50_000,
    show_default=True,
    help="Particles per ensemble member.",
)
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--force", is_flag=True, help="Overwrite --out.")
def predict(
    result_dir: Path,
    dataset_path: Path | None,
    settings_text: str | None,
    out: Path,
    particles: int,
    seed: int,
    force: bool,
) -> None:
    """Ensemble-mean screen images of a reconstruction (RESULT_DIR) for new settings."""
    if out.exists() and not force:
        raise click.ClickException(f"{out} exists; pass --force to overwrite it")
    if (dataset_path is None) == (settings_text is None):
        raise click.ClickException("give exactly one of --dataset or --settings")
    try:
        result = load(result_dir)
        if dataset_path is not None:
            other = read_quad_scan(dataset_path)
            fwd = ScreenForwardModel.from_dataset(
                other, blur_pixels=result.config.blur_pixels
            )
            settings = other.settings
        else:
            fwd = result.forward
            rows = [r for r in settings_text.replace(" ", "").split(";") if r]
            if len(fwd.names) == 1 and len(rows) == 1:
                rows = rows[0].split(",")
                vals = [[float(v)] for v in rows]
            else:
                vals = [[float(v) for v in r.split(":")] for r in rows]
            settings = torch.tensor(vals, dtype=torch.float64)
        images = result.predict_images(
            settings, forward=fwd, n_particles=particles, seed=seed
        )
    except (FormatError, ValueError, FileNotFoundError, OSError) as err:
        raise click.ClickException(str(err)) from err
    out.parent.mkdir(parents=True, exist_ok=True)
    array = images.numpy().astype(np.float32)

    def _save(p: Path) -> None:
        with p.open("wb") as f:
            np.save(f, array)

    atomic_write(out, _save)
    k, h, w = images.shape
    click.echo(f"wrote {out}: {k} images of {h} x {w} pixels")
