"""``diffaccel demo``: synthetic 6D quad scan -> reconstruction -> report."""

from __future__ import annotations

import json
import time
from pathlib import Path

import click

from diffaccel.cli.output import (
    OUT_DIR,
    force_option,
    out_option,
    output_folder,
    seed_option,
)
from diffaccel.cli.reconstruct import run_reconstruction
from diffaccel.data import atomic_write_text, write_quad_scan
from diffaccel.reconstruction import as_scans, training_selection
from diffaccel.reconstruction.results import (
    OWNED,
    demo_config,
    demo_dataset,
    demo_report_markdown,
)

__all__ = ["demo"]


@click.command("demo")
@out_option(OUT_DIR, "Output directory.")
@force_option("Replace an earlier demo in --out (at the end).")
@seed_option
def demo(out: Path, force: bool, seed: int) -> None:
    """Simulate a 6D quad scan and reconstruct it end to end (a few minutes on CPU)."""
    t0 = time.perf_counter()
    with output_folder(
        out, "demo", force=force, owned=(*OWNED, "dataset.h5", "report.md")
    ) as folder:
        click.echo(
            "simulating a 6D quad scan (preset 'correlated', chromatic tracking)..."
        )
        ds = demo_dataset(seed)
        path = out / "dataset.h5"
        write_quad_scan(ds, folder.path / path.name, overwrite=True)
        click.echo(f"wrote {path.name}; reconstructing (6D, 300 steps)...")
        config = demo_config(seed)
        scans = as_scans(ds)
        summary = run_reconstruction(
            scans,
            folder.path,
            config,
            training_selection(scans, "even"),
            dataset_path=path,
            device="cpu",
            resume=False,
        )
        seconds = time.perf_counter() - t0
        atomic_write_text(
            folder.path / "report.md", demo_report_markdown(summary, path.name, seconds)
        )
    report = out / "report.md"
    click.echo(json.dumps({"report": str(report), "seconds": round(seconds, 1)}))
    click.echo(f"report: {report}")
