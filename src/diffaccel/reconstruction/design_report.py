"""The experiment design of a reconstruction, as text and JSON.

:func:`posterior_beam` turns a reconstruction's moment posterior into the
beam and prior that :func:`~diffaccel.reconstruction.design.observability`
and :func:`~diffaccel.reconstruction.design.recommend` take;
:func:`design_lines` and :func:`design_json` present their answers.
:func:`design_answers` is ``diffaccel design``: the inputs read from a scan
file or JSON spec (and a result folder), the answers computed.
"""

from __future__ import annotations

import json
import statistics
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from diffaccel.data import FormatError
from diffaccel.data.scans import read_scans
from diffaccel.reconstruction import design as dz
from diffaccel.reconstruction.design import LONGITUDINAL_RMS
from diffaccel.reconstruction.ensemble import load
from diffaccel.reconstruction.uncertainty import MomentUncertainty

__all__ = [
    "design_answers",
    "design_inputs",
    "design_json",
    "design_lines",
    "posterior_beam",
]


def posterior_beam(
    uncertainty: MomentUncertainty,
) -> tuple[Tensor, Tensor, float | None]:
    """Beam covariance, moment posterior and error scale of a reconstruction.

    Args:
        uncertainty: The reconstruction's moment-space posterior.

    Returns:
        ``(cov (6, 6) float64, theta_cov, relative_error)``: the beam (a 4D
        result gets uncorrelated z and pz of rms :data:`LONGITUDINAL_RMS`),
        the posterior covariance of its second moments, and the median fitted
        relative error of the screen second moments (None where not fitted).
    """
    cov = uncertainty.cov.to(torch.float64).clone()
    if uncertainty.dims == 4:
        for i in (4, 5):
            cov[i, :] = 0.0
            cov[:, i] = 0.0
            cov[i, i] = LONGITUDINAL_RMS[i - 4] ** 2
    scales = uncertainty.diagnostics.get("error_scale_second_moments") or []
    rel = float(statistics.median(scales)) if scales else None
    return cov, uncertainty.theta_cov, rel


def design_lines(report: Mapping[str, Any] | None, obs: Mapping[str, Any]) -> list[str]:
    """The observability (and the recommended settings) as lines of text.

    Args:
        report: :func:`~diffaccel.reconstruction.design.recommend`'s answer,
            or None (no candidate knobs).
        obs: ``Observability.to_dict()``.

    Returns:
        The summary, the smallest singular values, the determined moments and
        those left to the prior, each unseen direction with what it moves;
        with a report the targets' std today, a table of the recommended
        settings (expected std per target [%], their values) and the
        exclusions.
    """
    lines = [obs["summary"]]
    sv = obs["singular_values"]
    lines.append(
        "singular values (relative, smallest 4): "
        + ", ".join(f"{v:.2g}" for v in sv[-4:])
        + (
            "; longitudinal block: "
            + ", ".join(f"{v:.2g}" for v in obs["longitudinal_singular_values"][-3:])
            if obs["longitudinal_singular_values"]
            else ""
        )
    )
    lines.append("determined: " + ", ".join(obs["determined"]))
    lines.append("left to the prior: " + (", ".join(obs["left_to_prior"]) or "none"))
    for u in obs["unseen"]:
        moves = ", ".join(
            f"{q} "
            + " / ".join("n/a" if c is None else f"{100 * c:+.1f} %" for c in ch)
            for q, ch in u["moves"].items()
            if any(c is not None and abs(c) > 0.005 for c in ch)
        )
        lines.append(
            f"  unseen: {u['words']} (singular value {u['singular_value']:.1e}); "
            f"{u['pair']} partial correlation -0.6 / +0.6 moves: {moves or 'nothing'}"
        )
    if report is None:
        return lines
    targets = report["targets"]
    base = report["baseline_std"]
    lines.append(
        "today's relative std: "
        + ", ".join(f"{t} {100 * base[t]:.3g} %" for t in targets)
    )
    if not report["recommended"]:
        lines.append("no candidate setting reduces the targets' std")
    else:
        head = f"{'#':>2}  {'scan':<14} {'images':>6}  " + "  ".join(
            f"{t + ' std':>12}" for t in targets
        )
        lines += ["recommended added settings:", head]
        for n, r in enumerate(report["recommended"], 1):
            stds = "  ".join(f"{100 * r['expected_std'][t]:>10.3g} %" for t in targets)
            lines.append(f"{n:>2}  {r['scan']:<14} {r['n_images']:>6}  {stds}")
            lines.append("      " + ", ".join(r["names"]) + ":")
            for v in r["values"]:
                lines.append("        " + ", ".join(f"{x:g}" for x in v))
    for e in report["excluded"]:
        lines.append(f"excluded: {e}")
    return lines


def design_json(
    report: Mapping[str, Any] | None, obs: Mapping[str, Any]
) -> dict[str, Any]:
    """The design's answer as one JSON object (see :func:`design_lines`).

    Keys: ``unseen``, ``recommended`` (empty without a report),
    ``observability`` (``obs``); with a report also ``baseline_std`` and
    ``excluded``.
    """
    out: dict[str, Any] = {
        "unseen": (report or {}).get("unseen", obs["unseen"]),
        "recommended": [] if report is None else report["recommended"],
        "observability": obs,
    }
    if report is not None:
        out["baseline_std"] = report["baseline_std"]
        out["excluded"] = report["excluded"]
    return out


def design_inputs(
    data: Path, result: Path | None = None
) -> tuple[list[dz.ScanLayout], Tensor, Tensor | None, float | None]:
    """The scans, beam, moment posterior and error scale of a design's inputs.

    ``data``: a quad-scan file or a JSON spec of planned scans
    (:func:`~diffaccel.reconstruction.design.layouts_from_spec`). The beam is
    the spec's, else the Gaussian fit of the file's images; with a
    reconstruction's folder ``result``, its beam, moment posterior and
    fitted error scale (:func:`posterior_beam`); posterior and error scale
    are None otherwise.

    Raises:
        ValueError: naming ``data`` (or ``--result RESULT``) and the problem.
    """
    posterior = rel = None
    if data.suffix.lower() == ".json":
        try:
            spec = json.loads(data.read_text())
        except (OSError, json.JSONDecodeError) as err:
            raise ValueError(f"{data}: not a readable JSON file ({err})") from None
        if not isinstance(spec, dict):
            raise ValueError(f"{data}: expected a JSON object")
        try:
            layouts, cov = dz.layouts_from_spec(spec)
        except ValueError as err:
            raise ValueError(f"{data}: {err}") from None
    else:
        try:
            ds = read_scans(data)
        except (FormatError, OSError, ValueError) as err:
            raise ValueError(f"{data}: {err}") from None
        layouts = dz.layouts_from_dataset(ds)
        cov = None
        if result is None:
            try:
                cov = dz.beam_from_images(ds)
            except ValueError as err:
                raise ValueError(f"{data}: {err}") from None
    if result is not None:
        try:
            rec = load(result)
        except (FileNotFoundError, ValueError, OSError) as err:
            raise ValueError(f"--result {result}: {err}") from None
        if rec.uncertainty is None:
            raise ValueError(
                f"--result {result}: the reconstruction has no moment posterior "
                "(run reconstruct without --no-uncertainty)"
            )
        cov, posterior, rel = posterior_beam(rec.uncertainty)
    return layouts, cov, posterior, rel


def design_answers(
    data: Path,
    *,
    result: Path | None = None,
    knobs: Sequence[str] = (),
    targets: Sequence[str] = (),
    relative_error: float | None = None,
    max_images_per_scan: int = 8,
) -> tuple[dict[str, Any], dict[str, Any] | None]:
    """What the scans of ``data`` determine, and which settings of ``knobs`` to add.

    Reads the inputs (:func:`design_inputs`), parses the knob ranges
    (:func:`~diffaccel.reconstruction.design.parse_knob`) and returns the
    observability as a dict and, with knobs, the recommendation of
    :func:`~diffaccel.reconstruction.design.recommend` for ``targets``
    (default :data:`~diffaccel.reconstruction.design.DEFAULT_TARGETS`); None
    without. ``relative_error``: of each screen second moment (default: the
    result's fitted error scale, else
    :data:`~diffaccel.reconstruction.design.RELATIVE_ERROR`).

    Raises:
        ValueError: unreadable inputs, a bad knob or target.
    """
    layouts, cov, posterior, rel = design_inputs(data, result)
    r = relative_error or rel or dz.RELATIVE_ERROR
    parsed = [dz.parse_knob(k) for k in knobs]
    obs = dz.observability(layouts, cov, relative_error=r, posterior=posterior)
    report = None
    if parsed:
        report = dz.recommend(
            layouts,
            cov,
            parsed,
            targets=targets or dz.DEFAULT_TARGETS,
            relative_error=r,
            posterior=posterior,
            max_images_per_scan=max_images_per_scan,
        )
    return obs.to_dict(), report
