"""Evaluation of a reconstruction on a dataset: predicted images, errors, summary.

One place for what the CLI (``summary.json``), the demo report and the
benchmarks report: images predicted for every scan and setting, their errors on
training and held-out settings per scan, the beam moments with ensemble spread,
and errors against a known ground truth.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping, Sequence
from typing import Any

import torch
from torch import Tensor

from diffaccel.data.atomic import clean_json
from diffaccel.data.quad_scan import QuadScanDataset
from diffaccel.data.scans import MultiScanDataset
from diffaccel.reconstruction.alarms import (
    FitAlarm,
    dataset_maps,
    fit_alarms,
    fit_signals,
    longitudinal_alarm,
    poor_fit_causes,
    scan_fits,
    scan_floor_share,
)
from diffaccel.reconstruction.design import observability_line
from diffaccel.reconstruction.ensemble import Reconstruction
from diffaccel.reconstruction.forward import ScreenForwardModel
from diffaccel.reconstruction.metrics import (
    COORDINATES,
    image_errors,
    moment_errors,
    prediction_noise_l1,
    shot_noise_l1,
    sliced_wasserstein,
)
from diffaccel.reconstruction.pipeline import as_scans
from diffaccel.reconstruction.prior_dependence import prior_dependence
from diffaccel.reconstruction.training import (
    ReconstructionConfig,
    loss_smoothing_for,
    smallest_spot,
    smoothed_for_loss,
)

__all__ = [
    "LOW_ON_SCREEN_FRACTION",
    "POOR_FIT_RELATIVE_L1",
    "check_on_screen",
    "check_same_beam",
    "clean_json",
    "evaluate",
    "off_screen_warnings",
    "predict_dataset",
    "predicted_dataset",
]

# pooled training-image relative L1 above which a reconstruction is reported as
# not reproducing its own training images: good runs end near 0.02-0.10 on the
# images they trained on (held-out 0.07-0.15 in the benchmarks);
# 0.5 means half of the image intensity is misplaced
POOR_FIT_RELATIVE_L1 = 0.5

#: Fraction of a predicted beam on the screen (dimensionless) below which a
#: predicted image is reported as showing only part of the beam
#: (:func:`off_screen_warnings`): predicted images are normalised to unit sum,
#: so a setting that throws most of the beam off the screen still gives a
#: plausible-looking image (of the part that hits it). A beam well inside the
#: screen has ~1 (the blur at the edges takes a little); below 0.5 the image
#: misses more of the beam than it shows.
LOW_ON_SCREEN_FRACTION = 0.5
#: Settings named in one scan's off-screen warning (more are counted).
MAX_LISTED_SETTINGS = 8

UNCONSTRAINED_NOTE = (
    "coordinates the scans do not see to first order (their column of the "
    "transfer matrices to screen x/y is ~0); their values follow the prior "
    "(ReconstructionConfig.longitudinal_scale); their std is the prior width of "
    "the moment-space posterior (>= ~50 % in rms), not a measurement"
)
PRIOR_DEPENDENCE_NOTE = (
    "correlations the scans cannot see (every screen's second moments are "
    "unchanged to first order along these directions): the prior sets them "
    "(zero partial correlation of the pair given the other four coordinates, "
    "with the strength ReconstructionConfig.unseen_weight). relative_change: "
    "how the moments would differ, with the same images, if the pair's partial "
    "correlation were the value listed (null: no valid beam there). See "
    "diffaccel.reconstruction.prior_dependence"
)
UNCERTAINTY_NOTE = (
    "std = calibrated 1-sigma: snapshot-ensemble scatter (std_ensemble) and the "
    "moment-space posterior (std_posterior: measurement error estimated from the "
    "training-image residuals, directions the scans do not constrain keep the "
    "prior width) in quadrature; it does not include model error (a wrong "
    "beamline, calibration or energy). See docs/methods/uncertainty.md"
)
UNCERTAINTY_NOTE_ENSEMBLE_ONLY = (
    "std = spread over snapshot-ensemble members only (this reconstruction has "
    "no moment-space posterior); it describes optimisation scatter and "
    "under-covers the actual error"
)


#: Largest relative difference between a dataset's ``p0c`` and that of the
#: reconstruction that images it (values rounded when recorded).
P0C_RELATIVE_TOLERANCE = 1e-3


def check_same_beam(
    result: Reconstruction, dataset: QuadScanDataset | MultiScanDataset
) -> None:
    """Refuse a dataset of another beam than the reconstruction's.

    Raises:
        ValueError: naming both species, or both ``p0c`` values, when they
            differ (``p0c`` by more than :data:`P0C_RELATIVE_TOLERANCE`).
    """
    fwd = result.forward
    if dataset.species != fwd.species:
        raise ValueError(
            f"the dataset is of species {dataset.species!r}; the reconstruction "
            f"is of {fwd.species!r} (its beam cannot be tracked as another species)"
        )
    if not abs(dataset.p0c - fwd.p0c) <= P0C_RELATIVE_TOLERANCE * fwd.p0c:
        raise ValueError(
            f"the dataset has p0c = {dataset.p0c:.6g} eV; the reconstruction was "
            f"made at p0c = {fwd.p0c:.6g} eV (a relative difference of "
            f"{(dataset.p0c - fwd.p0c) / fwd.p0c:+.3g}, over "
            f"{P0C_RELATIVE_TOLERANCE:g}); its particles' momenta are relative to "
            "its own p0c: predict a dataset of the same beam energy"
        )


#: Noise target of predicted images without measured ones to compare (a
#: prediction at new settings): the expected relative L1 that their own
#: sampling noise adds, mean over the settings. With measured images the target
#: is a third of the error they measure
#: (:data:`~diffaccel.reconstruction.ensemble.MEASURED_ERROR_SHARE`).
PREDICTION_NOISE_L1 = 0.02
#: Most particles per ensemble member a prediction images to meet its target.
MAX_PREDICTION_PARTICLES = 1_000_000


def predict_dataset(
    result: Reconstruction,
    dataset: QuadScanDataset | MultiScanDataset,
    *,
    n_particles: int = 50_000,
    seed: int = 0,
    return_std: bool = False,
    n_draws: int = 4,
    return_on_screen: bool = False,
    maps: Mapping[str, Tensor] | None = None,
    sharpen: bool = True,
    max_particles: int = MAX_PREDICTION_PARTICLES,
    return_particles: bool = False,
) -> dict[str, Tensor] | tuple[dict[str, Tensor], ...]:
    """Ensemble-mean images of every scan and setting of ``dataset``.

    Each scan is imaged with a forward model built from that scan (its
    beamline, screen grid and scanned names; the reconstruction's ``--blur``
    if one was given, else that scan's recorded resolution or the default by
    ``dims``: ``ReconstructionConfig.blur_for``), so a
    test file with other settings or another screen works; the same particles
    (``seed``) go through every scan. With ``sharpen`` each scan's images are
    made of enough particles that their own sampling noise adds ~5 % to their
    relative L1 against the scan's measured images, or at most
    :data:`PREDICTION_NOISE_L1` where it has none
    (``Reconstruction.predict_images(noise_l1=..., measured=...)``).

    Args:
        result: The reconstruction.
        dataset: Scans whose settings and screens to predict.
        n_particles: Particles per ensemble member (the least; with
            ``sharpen``, more where the images need them).
        seed: Sampling seed.
        return_std: Also return the per-pixel spread of every image
            (``Reconstruction.predict_images(return_std=True)``).
        n_draws: Posterior beams per member for the spread.
        return_on_screen: Also return the fraction of the beam on the screen
            at every setting (``Reconstruction.predict_images(
            return_on_screen=True)``: from the same images, no extra tracking).
        maps: ``{scan: (K_s, 7, 7)}`` transfer maps of every setting when the
            caller has them (:func:`~diffaccel.reconstruction.alarms.dataset_maps`).
        sharpen: Add particles up to the scan's noise target (see above).
        max_particles: Most particles per member ``sharpen`` may use.
        return_particles: Also return ``{scan name: particles per member}``.

    Returns:
        ``{scan name: (K_s, H_s, W_s)}`` float32 images, each summing to 1;
        with ``return_std`` a pair ``(images, spreads)`` of such dicts (the
        spread on the scale of the unit-sum images); with ``return_on_screen``
        ``{scan name: (K_s,)}`` fractions on the screen come next
        (``(images, fractions)`` or ``(images, spreads, fractions)``), with
        ``return_particles`` the particle counts last. The images are the same
        with and without any of them.

    Raises:
        ValueError: if ``dataset`` is of another species, or its ``p0c``
            differs from the reconstruction's by more than
            :data:`P0C_RELATIVE_TOLERANCE` (the beam's coordinates are relative
            to its own ``p0c``; the forward model takes the dataset's).
    """
    scans = as_scans(dataset)
    check_same_beam(result, scans)
    out, spread, on_screen, used = {}, {}, {}, {}
    for name, scan in scans:
        fwd = ScreenForwardModel.from_dataset(
            scan, blur_pixels=result.config.blur_for(scan)
        )
        pred = result.predict_images(
            scan.settings,
            forward=fwd,
            n_particles=n_particles,
            seed=seed,
            return_std=return_std,
            n_draws=n_draws,
            return_on_screen=True,
            maps=None if maps is None else maps[name],
            noise_l1=PREDICTION_NOISE_L1 if sharpen else None,
            measured=scan.mean_images(),
            max_particles=max(max_particles, n_particles),
            return_particles=True,
        )
        out[name], on_screen[name], used[name] = pred[0], pred[-2], pred[-1]
        if return_std:
            spread[name] = pred[1]
    parts = [out]
    if return_std:
        parts.append(spread)
    if return_on_screen:
        parts.append(on_screen)
    if return_particles:
        parts.append(used)
    return tuple(parts) if len(parts) > 1 else out


def _train_indices(result: Reconstruction, name: str, k: int) -> list[int]:
    per_scan = result.info.get("scans")
    if isinstance(per_scan, dict):
        return list(per_scan.get(name, {}).get("train_indices", []))
    return list(result.info.get("train_indices", range(k)))


def _pooled(
    parts: Sequence[tuple[Tensor, Tensor, Mapping[str, Any]]],
) -> dict[str, Any] | None:
    """Image errors over the images of several scans (each image weighs the same).

    ``parts``: per scan, its predicted and measured images and its errors, whose
    ``prediction_noise_l1`` and ``data_noise_l1`` are pooled the same way (None
    where any scan's is None).
    """
    parts = [q for q in parts if q[0].shape[0]]
    if not parts:
        return None
    per = [image_errors(p, m) for p, m, _ in parts]
    counts = [p.shape[0] for p, _, _ in parts]
    total = sum(counts)

    def mean(values: Sequence[Any]) -> float | None:
        if any(v is None for v in values):
            return None
        return sum(v * c for v, c in zip(values, counts, strict=True)) / total

    out: dict[str, Any] = {
        "mae_over_peak": mean([e["mae_over_peak"] for e in per]),
        "relative_l1": mean([e["relative_l1"] for e in per]),
        "n_images": total,
    }
    for key in ("prediction_noise_l1", "data_noise_l1"):
        out[key] = mean([errors[key] for _, _, errors in parts])
    return out


def evaluate(
    result: Reconstruction,
    dataset: QuadScanDataset | MultiScanDataset,
    *,
    train_indices: Mapping[str, Sequence[int]] | None = None,
    predicted: Mapping[str, Tensor] | None = None,
    n_sample: int = 100_000,
    sample: Tensor | None = None,
    on_screen: Mapping[str, Tensor] | None = None,
    prediction_particles: int | Mapping[str, int] | None = None,
) -> dict[str, Any]:
    """Moments, image errors per scan and ground-truth errors of a reconstruction.

    Args:
        result: The reconstruction.
        dataset: The data to score against (the training file, or a held-out
            file with the same scan names).
        train_indices: ``{scan: indices}`` of ``dataset`` used for training;
            default those stored in ``result.info`` (for a held-out file pass
            ``{}``: every setting counts as held out).
        predicted: Images from :func:`predict_dataset` (computed if None).
        n_sample: Particles drawn (per member for the moments) to compute the
            moments and to compare with the ground truth.
        sample: ``result.sample(n_sample)`` when the caller has drawn it (the
            CLI writes the same particles to its particles file); drawn here
            otherwise.
        on_screen: ``{scan: (K_s,)}`` fractions of the beam on the screen of
            the ``predicted`` images (``predict_dataset(return_on_screen=True)``);
            computed with the images when ``predicted`` is None, not checked
            when only ``predicted`` is given.
        prediction_particles: Particles per member behind ``predicted``
            (one count, or one per scan: :func:`predict_dataset` with
            ``return_particles``), for the predictions' own noise (None:
            ``prediction_noise_l1`` is None for ``predicted`` images).

    Returns:
        JSON-ready dict: ``scans`` (per scan: ``train_indices``,
        ``held_out_indices``, ``images_train``, ``images_held_out`` from
        :func:`~diffaccel.reconstruction.image_errors` with, beside each
        error, ``prediction_noise_l1`` (what the predicted images' own sampling
        noise adds, :func:`~diffaccel.reconstruction.metrics.prediction_noise_l1`),
        ``prediction_particles`` (per member behind the predicted images) and
        ``data_noise_l1`` (the measurement's floor from its shots,
        :func:`~diffaccel.reconstruction.metrics.shot_noise_l1`; None for
        single-shot data), and with the fractions
        ``fraction_on_screen`` per setting), ``metrics``
        (``images_train``/``images_held_out`` pooled over all scans,
        ``ground_truth`` from :func:`~diffaccel.reconstruction.moment_errors`
        plus the sliced Wasserstein distance when the truth is known),
        ``moments`` (:meth:`Reconstruction.moments`), ``observability``
        (:func:`~diffaccel.reconstruction.design.observability_line`),
        ``point_spread`` (:func:`point_spread_notes`: scans whose smallest
        spot is below their point spread),
        ``rms_relative_ensemble_spread``, ``unconstrained_coordinates``,
        ``prior_dependence`` (6D: what the prior sets, see
        :func:`~diffaccel.reconstruction.prior_dependence.prior_dependence`;
        4D: empty), notes,
        ``config``, ``snapshots``, ``timings_s``, ``fit_quality`` (the
        signals of :func:`~diffaccel.reconstruction.alarms.fit_signals`),
        ``fit_alarms`` (each :class:`~diffaccel.reconstruction.alarms.FitAlarm`
        as a dict) and ``warnings`` (a list of sentences; one when a scan's
        training images or all of them together have a relative L1 above
        :data:`POOR_FIT_RELATIVE_L1`: the reconstruction does not reproduce
        its own data, and its moments are not a measurement, its causes
        ordered by the other signals; one per fit-quality alarm (moments
        missed, scans that disagree, an image or scan that stands out, a beam
        cut by a screen edge, a 4D result through elements that read z or
        pz); one per scan whose predicted beam mostly misses the screen at
        some of its settings, training or held out, from
        :func:`off_screen_warnings`); for a single scan also
        ``train_indices``/``held_out_indices`` at the top level.
    """
    scans = as_scans(dataset)
    maps, specs = dataset_maps(scans)
    if predicted is None:
        predicted, on_screen, prediction_particles = predict_dataset(
            result, scans, return_on_screen=True, maps=maps, return_particles=True
        )
    pred = dict(predicted)
    per_scan: dict[str, Any] = {}
    screen_warnings: list[str] = []
    train_parts, test_parts = [], []
    selected: dict[str, list[int]] = {}
    for name, scan in scans:
        k = scan.n_settings
        if train_indices is not None:
            train = sorted(int(i) for i in train_indices.get(name, []))
        else:
            train = _train_indices(result, name, k)
        test = [i for i in range(k) if i not in set(train)]
        selected[name] = train
        meas = scan.mean_images()
        p = pred[name]
        entry: dict[str, Any] = {"train_indices": train, "held_out_indices": test}
        kappa = ScreenForwardModel.from_dataset(
            scan, blur_pixels=result.config.blur_for(scan)
        ).pixel_kernel_sum_sq()
        n_member = (
            prediction_particles.get(name)
            if isinstance(prediction_particles, Mapping)
            else prediction_particles
        )
        own = (
            None
            if n_member is None
            else prediction_noise_l1(p, kappa, int(n_member) * result.n_snapshots)
        )
        floor = shot_noise_l1(scan.images)
        for key, rows, parts in (
            ("images_train", train, train_parts),
            ("images_held_out", test, test_parts),
        ):
            if not rows:
                continue
            entry[key] = image_errors(p[rows], meas[rows])
            entry[key]["prediction_noise_l1"] = (
                None if own is None else float(own[rows].mean())
            )
            entry[key]["prediction_particles"] = n_member
            entry[key]["data_noise_l1"] = (
                None if floor is None else float(floor[rows].mean())
            )
            parts.append((p[rows], meas[rows], entry[key]))
        if on_screen is not None:
            fraction = on_screen[name]
            entry["fraction_on_screen"] = _rounded(fraction)
            screen_warnings += off_screen_warnings(
                fraction, scan.settings, scan.setting_names, scan=name
            )
        per_scan[name] = entry
    metrics: dict[str, Any] = {}
    for key, parts in (("images_train", train_parts), ("images_held_out", test_parts)):
        pooled = _pooled(parts)
        if pooled is not None:
            metrics[key] = pooled
    moments = result.moments(n=n_sample)
    rel_spread, rel_std = {}, {}
    for i, c in enumerate(COORDINATES):
        m, s = moments["rms"]["mean"][i], moments["rms"]["std"][i]
        rel_std[c] = s / m if m > 0 else None
        s = moments["rms"]["std_ensemble"][i]
        rel_spread[c] = s / m if m > 0 else None
    unc = result.info.get("uncertainty")
    truth = scans.ground_truth
    if truth is not None:
        if sample is None:
            sample = result.sample(n_sample)
        truth = truth.to(torch.float64)
        dims = result.config.dims
        gt = moment_errors(sample, truth)
        g = torch.Generator().manual_seed(0)
        gt[f"sliced_wasserstein_{dims}d"] = float(
            sliced_wasserstein(sample[:20_000, :dims], truth[:, :dims], generator=g)
        )
        metrics["ground_truth"] = gt
    signals = fit_signals(
        scan_fits(result, scans, pred, selected, maps),
        torch.tensor(moments["cov"]["mean"], dtype=torch.float64),
        result.config.dims,
    )
    longitudinal = longitudinal_alarm(result.config.dims, maps, specs)
    alarms = fit_alarms(signals, longitudinal=longitudinal)
    if longitudinal is not None:
        alarms.append(longitudinal)
    warnings = (
        _poor_fit_warnings(per_scan, metrics, alarms)
        + [a.text() for a in alarms]
        + screen_warnings
        + resolution_warnings(result.config, scans, selected)
    )
    dependence: list[dict] = []
    if result.config.dims == 6:
        try:
            dependence = prior_dependence(
                result.training_maps(),
                torch.tensor(moments["cov"]["mean"], dtype=torch.float64),
            )
        except ValueError as err:  # a degenerate covariance: no beam to move
            warnings.append(f"prior_dependence not computed: {err}")
    summary: dict[str, Any] = {
        "warnings": warnings,
        "fit_alarms": [a.to_dict() for a in alarms],
        "fit_quality": _signal_summary(signals),
        "config": result.config.to_dict(),
        "scans": per_scan,
        "snapshots": result.n_snapshots,
        "member_processes": result.info.get("member_processes", 1),
        "moments": moments,
        "rms_relative_std": rel_std,
        "rms_relative_ensemble_spread": rel_spread,
        "unconstrained_coordinates": result.unconstrained_coordinates(),
        "unconstrained_note": UNCONSTRAINED_NOTE,
        "prior_dependence": dependence,
        "prior_dependence_note": PRIOR_DEPENDENCE_NOTE,
        "uncertainty_note": (
            UNCERTAINTY_NOTE if unc is not None else UNCERTAINTY_NOTE_ENSEMBLE_ONLY
        ),
        "uncertainty": None if unc is None else unc.get("diagnostics"),
        "metrics": metrics,
        "timings_s": dict(result.info.get("timings_s", {})),
    }
    summary["observability"] = observability_line(
        result.training_maps(),
        torch.tensor(moments["cov"]["mean"], dtype=torch.float64),
        None if unc is None else torch.tensor(unc["theta_cov"], dtype=torch.float64),
    )
    summary["point_spread"] = point_spread_notes(result.config, scans, selected)
    if len(scans) == 1:
        only = next(iter(per_scan.values()))
        summary["train_indices"] = only["train_indices"]
        summary["held_out_indices"] = only["held_out_indices"]
    return clean_json(summary)


def _signal_summary(signals: Mapping[str, Any]) -> dict[str, Any]:
    """The pooled fit-quality signals and, per scan, the worst edge level and
    the median floor share
    (:func:`~diffaccel.reconstruction.alarms.scan_floor_share`)."""
    out = {k: v for k, v in signals.items() if k != "scans"}
    out["scans"] = {
        name: {
            "moment_residual": s["moment_residual"],
            "moment_residual_one_beam": s.get("moment_residual_one_beam"),
            "moment_residual_own_beam": s.get("moment_residual_own_beam"),
            "edge_level_max": max(s["edge_level"], default=0.0),
            "floor_share": scan_floor_share(s),
        }
        for name, s in signals.get("scans", {}).items()
    }
    return out


#: Share of an image's variance (x or y, about its centroid) on sparse pixels
#: above which the image term cannot resolve the image: pixels where fewer
#: than one simulated particle per step is expected, ``N s / kappa < 1``
#: (:func:`sparse_variance_share`). There the simulated image is the kernels
#: of lone particles, and the fitted tails follow the sample's noise. On
#: synthetic scans (4D camera scans with the "auto" smoothing and a 2 x 48
#: generator; a 6D scan at 300 x 300 pixels compared at 0-1 pixel with 4096
#: or 16 384 particles) shares up to 0.17 gave emittances within 0.8 % of the
#: truth, 0.25 gave 2.3 %, and 0.29-0.52 gave 6-14 % in x or y or 16-30 % in
#: the 4D and 6D emittances.
SPARSE_VARIANCE_SHARE = 0.2


def _training_images(
    scans: MultiScanDataset, train: Mapping[str, Sequence[int]]
) -> list[tuple[str, Any, Tensor]]:
    """``(name, scan, training images (K, H, W))`` of each scan: the settings
    ``train[name]``, every setting where it names none."""
    out = []
    for name, scan in scans:
        rows = list(train.get(name, [])) or list(range(scan.n_settings))
        out.append((name, scan, scan.mean_images()[rows]))
    return out


def sparse_variance_share(
    compared: Tensor, n_particles: int, kappa: float, share: float | None = None
) -> tuple[float, float]:
    """How much of each image's variance the sampled images leave unresolved.

    A pixel of the simulated image of ``N`` particles whose expected value is
    ``s`` (sum-normalised) holds on average ``N s / kappa`` particles' worth of
    signal (its relative variance is ``kappa / (N s)``, ``kappa`` from
    :meth:`~diffaccel.reconstruction.forward.ScreenForwardModel.pixel_kernel_sum_sq`);
    below 1 it is a lone particle's kernel or nothing. The measured image
    stands for ``s``.

    Args:
        compared: Measured images ``(K, H, W)`` as the image term compares
            them (smoothed and pooled,
            :func:`~diffaccel.reconstruction.training.compared_for`); negative
            pixels count as zero.
        n_particles: Simulated particles per step ``N``.
        kappa: Squared deposit weights of one particle summed over the pixels
            of the compared images.
        share: The share to resolve; default :data:`SPARSE_VARIANCE_SHARE`.

    Returns:
        ``(largest share, particles)``: the largest share, over images and
        axes, of an image's variance about its centroid on pixels with ``N s /
        kappa < 1``, and the particles per step that would bring every image's
        share to ``share``.

    Example:
        >>> im = torch.zeros(1, 1, 5); im[0, 0] = torch.tensor([1, 0, 98, 0, 1.0])
        >>> sparse_variance_share(im, 100, 1.0)  # the outer pixels: 1 particle each
        (0.0, 100.0)
        >>> sparse_variance_share(im, 50, 1.0)  # half a particle: all the variance
        (1.0, 100.0)
    """
    target = SPARSE_VARIANCE_SHARE if share is None else float(share)
    m = compared.detach().to(torch.float64).clamp_min(0.0).flatten(0, -3)
    m = m / m.sum((-2, -1), keepdim=True).clamp_min(1e-300)
    h, w = m.shape[-2:]
    ys = torch.arange(h, dtype=torch.float64)
    xs = torch.arange(w, dtype=torch.float64)
    worst, need = 0.0, 0.0
    for img in m:
        sparse = img * n_particles / kappa < 1.0
        order = torch.argsort(img.flatten())  # pixels by expected signal
        levels = img.flatten()[order]
        for pos in (xs.view(1, w), ys.view(h, 1)):
            mean = (img * pos).sum()
            var = img * (pos - mean).square()
            total = float(var.sum())
            if total <= 0.0:
                continue
            worst = max(worst, float(var[sparse].sum()) / total)
            # the level below which `target` of the variance lies: N there is 1
            cum = torch.cumsum(var.flatten()[order], 0) / total
            i = int(torch.searchsorted(cum, torch.tensor(target, dtype=cum.dtype)))
            level = float(levels[min(i, order.numel() - 1)])
            if level > 0.0:
                need = max(need, kappa / level)
    return worst, need


def resolution_warnings(
    config: ReconstructionConfig,
    scans: MultiScanDataset,
    train: Mapping[str, Sequence[int]],
) -> list[str]:
    """One sentence per scan whose training images the sampled images cannot
    resolve: more than :data:`SPARSE_VARIANCE_SHARE` of an image's variance
    on pixels where fewer than one of ``n_particles`` simulated particles per
    step is expected (:func:`sparse_variance_share`), the images compared as
    the image term compares them (smoothed by
    :func:`~diffaccel.reconstruction.training.loss_smoothing_for`, pooled)."""
    out = []
    for name, scan, images in _training_images(scans, train):
        blur = config.blur_for(scan)
        fwd = ScreenForwardModel.from_dataset(scan, blur_pixels=blur)
        [used] = loss_smoothing_for(config, [images], [blur])
        [cf], [cm] = smoothed_for_loss([fwd], [images], used)
        share, need = sparse_variance_share(
            cm, config.n_particles, cf.pixel_kernel_sum_sq()
        )
        if share <= SPARSE_VARIANCE_SHARE:
            continue
        capped = config.loss_smoothing == "auto" and used >= 0.999 * smallest_spot(
            images, blur
        )
        line = (
            f"scan {name!r}: {100 * share:.0f} % of an image's variance lies on "
            f"pixels that fewer than one of the {config.n_particles} particles "
            f"per step reaches (images compared at {used:.2g} pixels rms"
            + (", capped by the scan's smallest spot" if capped else "")
            + "), so the fitted tails follow the sample's noise and the emittances "
            f"may be biased; rerun with more --particles (about {need:.2g} bring "
            f"every image below {100 * SPARSE_VARIANCE_SHARE:.0f} %)"
        )
        if config.loss_smoothing != "auto":
            line += (
                " or with --loss-smoothing auto (compares the images at the "
                "resolution the sample supports)"
            )
        out.append(line)
    return out


def point_spread_notes(
    config: ReconstructionConfig,
    scans: MultiScanDataset,
    train: Mapping[str, Sequence[int]],
) -> list[str]:
    """One sentence per scan whose smallest beam spot is below its point spread.

    The spot is the smallest rms size of the scan's training images, x or y,
    with the point spread (``config.blur_for``) taken out in quadrature. Below
    the point spread an image's width is mostly the point spread's, and the
    emittance then depends on the point spread's *shape*, which the
    reconstruction assumes (a Gaussian after cloud-in-cell deposition), not
    only on its rms: on a scan with a 0.6-pixel waist behind a 1-pixel point
    spread the x emittance moved by 7 % (-4.7 to +2.4 %; 600 steps, moment
    weight 0.3) when the 0.58-pixel smoothing of the compared images was a
    discrete Gaussian kernel instead of the sampled one of the same variance.
    Settings whose waist spans several pixels (or a finer camera) decide it.
    """
    out = []
    for name, scan, images in _training_images(scans, train):
        spread = config.blur_for(scan)
        spot = smallest_spot(images, spread)
        if spot >= spread:
            continue
        out.append(
            f"scan {name!r}: its smallest beam spot ({spot:.2f} pixels rms, the "
            f"{spread:.2f}-pixel point spread taken out) is below the point "
            "spread, so the emittances there depend on the point spread's shape, "
            "not only its rms (by several percent); settings whose waist spans "
            "several pixels decide them"
        )
    return out


def _poor_fit_warnings(
    per_scan: Mapping[str, Any],
    metrics: Mapping[str, Any],
    alarms: Sequence[FitAlarm] = (),
) -> list[str]:
    """Warnings for training images the reconstruction does not reproduce."""
    bad = {
        name: entry["images_train"]["relative_l1"]
        for name, entry in per_scan.items()
        if "images_train" in entry
        and not entry["images_train"]["relative_l1"] <= POOR_FIT_RELATIVE_L1
    }
    pooled = metrics.get("images_train", {}).get("relative_l1")
    if not bad and (pooled is None or pooled <= POOR_FIT_RELATIVE_L1):
        return []
    where = "".join(f", scan {n!r}: {v:.3g}" for n, v in bad.items())
    causes = "; ".join(f"({i}) {c}" for i, c in enumerate(poor_fit_causes(alarms), 1))
    return [
        "the reconstruction does not reproduce its training images: relative L1 "
        f"{pooled:.3g} over all training images{where} (good fits end below "
        f"~0.15; warned above {POOR_FIT_RELATIVE_L1}), so its moments are not a "
        f"measurement of the beam; likely causes, most likely first: {causes}."
    ]


def check_on_screen(images: Tensor, settings: Tensor, *, scan: str = "") -> Tensor:
    """Sums of predicted images; raises if a prediction has nothing on the screen.

    Args:
        images: Predicted images ``(K, H, W)``.
        settings: Their settings ``(K, P)`` (named in the error).
        scan: Scan name for the error message.

    Returns:
        The image sums ``(K,)``.

    Raises:
        ValueError: naming the setting if an image is all zero (no particle
            reached the screen): such a prediction is not an image of the beam.
    """
    sums = images.sum((-2, -1))
    if bool((sums <= 0).any()):
        bad = int(torch.nonzero(sums <= 0)[0])
        where = f"scan {scan!r}: " if scan else ""
        raise ValueError(
            f"{where}no predicted particle reaches the screen at setting {bad} "
            f"({settings[bad].tolist()}; particles lost or off the screen, e.g. a "
            "setting or element too strong for the beam's momentum)."
        )
    return sums


def off_screen_warnings(
    on_screen: Tensor,
    settings: Tensor,
    names: Sequence[str],
    *,
    scan: str = "",
) -> list[str]:
    """A warning for the settings of a scan whose predicted beam misses the screen.

    Args:
        on_screen: Fraction of the beam on the screen at each setting ``(K,)``
            (dimensionless; ``return_on_screen`` of :func:`predict_dataset`).
        settings: The settings ``(K, P)`` (their values are named).
        names: The scanned parameters ``(P,)``, e.g. ``["Q1.k1"]``.
        scan: Scan name for the warning.

    Returns:
        One sentence naming the scan and each setting (index, values, fraction
        on the screen) with a fraction below :data:`LOW_ON_SCREEN_FRACTION`
        (the first :data:`MAX_LISTED_SETTINGS` of them, then their number), or
        an empty list if there is none.

    Example:
        >>> w = off_screen_warnings(torch.tensor([0.99, 0.098]),
        ...                         torch.tensor([[2.0], [200.0]]), ["Q1.k1"],
        ...                         scan="scan")
        >>> print(w[0][: w[0].index(" (warned")])  # doctest: +NORMALIZE_WHITESPACE
        scan 'scan': only part of the predicted beam lands on the screen at 1 of
        2 settings: setting 1 (Q1.k1 = 200) 9.8 %
    """
    fractions = on_screen.double().tolist()
    low = [k for k, f in enumerate(fractions) if not f >= LOW_ON_SCREEN_FRACTION]
    if not low:
        return []
    listed = []
    for k in low[:MAX_LISTED_SETTINGS]:
        values = ", ".join(
            f"{n} = {float(v):.6g}" for n, v in zip(names, settings[k], strict=True)
        )
        listed.append(f"setting {k} ({values}) {100 * fractions[k]:.1f} %")
    if len(low) > MAX_LISTED_SETTINGS:
        listed.append(f"and {len(low) - MAX_LISTED_SETTINGS} more")
    return [
        f"scan {scan!r}: only part of the predicted beam lands on the screen at "
        f"{len(low)} of {len(fractions)} settings: {', '.join(listed)} (warned "
        f"below {100 * LOW_ON_SCREEN_FRACTION:.0f} %); their images, normalised "
        "to unit sum, show only that part of the beam (a setting too strong for "
        "the beam, or a screen too small for it?)."
    ]


def _rounded(fraction: Tensor) -> list[float]:
    """Fractions on the screen ``(K,)`` as a list, to 6 decimals (for JSON)."""
    return [round(v, 6) for v in fraction.double().tolist()]


def predicted_dataset(
    dataset: QuadScanDataset | MultiScanDataset,
    predicted: Mapping[str, Tensor],
    *,
    source: str = "",
    on_screen: Mapping[str, Tensor] | None = None,
) -> MultiScanDataset:
    """``dataset`` with its images replaced by predictions (one shot, unit sum).

    Settings, beamlines, screen calibrations, ground truth and format version
    are kept, so any reader of measurements reads the predictions; the step
    ``{"step": "predicted", "reconstruction": source}`` is appended to
    ``metadata["preprocessing"]`` (of each scan and of the container). With
    ``on_screen`` each scan's step also records ``fraction_on_screen`` (one
    value per setting) and ``warnings`` (:func:`off_screen_warnings`: settings
    whose beam mostly misses the screen), and the container's step the
    warnings of all scans.

    Args:
        dataset: The dataset the predictions were made for.
        predicted: ``{scan: (K_s, H_s, W_s)}`` from :func:`predict_dataset`.
        source: Where the reconstruction came from (e.g. its folder).
        on_screen: ``{scan: (K_s,)}`` fractions of the beam on the screen
            (``predict_dataset(return_on_screen=True)``).

    Raises:
        ValueError: naming the scan and setting if a predicted image is all
            zero (no particle reached the screen) or shapes do not match.
    """
    scans = as_scans(dataset)
    step: dict[str, Any] = {"step": "predicted", "reconstruction": source}
    out = {}
    warnings: list[str] = []
    for name, scan in scans:
        images = predicted[name].detach().to("cpu", torch.float32)
        k, _, h, w = scan.shape
        if tuple(images.shape) != (k, h, w):
            raise ValueError(
                f"scan {name!r}: predicted images {tuple(images.shape)} do not match "
                f"the scan's (K, H, W) = {(k, h, w)}."
            )
        sums = check_on_screen(images, scan.settings, scan=name)
        scan_step = dict(step)
        if on_screen is not None:
            fraction = on_screen[name]
            scan_step["fraction_on_screen"] = _rounded(fraction)
            scan_step["warnings"] = off_screen_warnings(
                fraction, scan.settings, scan.setting_names, scan=name
            )
            warnings += scan_step["warnings"]
        images = (images / sums[:, None, None])[:, None]
        out[name] = scan.with_step(scan_step, images=images)
    if on_screen is not None:
        step["warnings"] = warnings
    metadata = copy.deepcopy(scans.metadata)  # a version-2 file keeps this one
    metadata.setdefault("preprocessing", []).append(dict(step))
    return MultiScanDataset(out, scans.format_version, metadata)
