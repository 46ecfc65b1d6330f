"""What a set of scans determines, and which settings to add: observability and design.

**The moment design** (:mod:`~diffaccel.reconstruction.screen_moments`, the
one the initial guess, the unseen directions, the prior report and the moment
posterior use). :func:`moment_design` maps the 21 upper-triangular entries of
the beam covariance to the second moments of every screen at every setting of
every scan; :func:`scaled_design` puts it in the units in which directions are
compared: unknowns in correlation units (``S_ij / (sig_i sig_j)``) and rows
relative to the screen sizes of the beam. It is exact for the first-order part
of the optics; chromatic and higher-order terms (a cavity's streak of an
energy-spread beam, a bend's ``T166``) make tracked images differ at the
per-cent level (``tests/reconstruction/test_design.py`` checks it against
tracked images).

**Observability** (:func:`observability`). With a relative error ``r`` of each
screen moment (``r <xx>``, ``r sqrt(<xx><yy>/2)``, ``r <yy>``) and the prior of
:func:`~diffaccel.reconstruction.uncertainty.analyse_moments` (each variance
known to 100 %, each correlation to 0.5) the posterior of the entries is
Gaussian, covariance ``(D^T W D + P^-1)^-1`` in correlation units. The std of
a named quantity (emittances, rms sizes, Twiss, chirp; :data:`QUANTITIES`) is
its std over posterior draws (as ``MomentUncertainty.moment_std``). An entry
or quantity is *determined* unless its std grows by more than
:data:`PRIOR_SENSITIVITY` when the prior is made ten times wider (or, for a
quantity, an unseen direction moves it by more than :data:`MOVE_LIMIT`); then
it is *left to the prior*. The singular values of the scaled design, relative to the
largest, name the directions the scans do not see (below
:data:`~diffaccel.reconstruction.unseen.UNSEEN_TOLERANCE`): each is described
by its largest entries ("py-z together with z-z") and by how far the named
quantities move when the beam moves along it until the pair it trades has a
partial correlation of +-0.6 (:data:`MOVE_PARTIALS`; the range real beams
take), with :func:`~diffaccel.reconstruction.prior_dependence.move_to_partial`.
Coordinates whose every entry has a zero column (z and pz behind quadrupoles
and drifts alone) are reported as not seen at all.

**Recommendation** (:func:`recommend`). Candidate knobs (any element
parameter of a scan's beamline, a range each) give candidate added settings:
per scan, the scan's own distinct settings with the knobs set to values on
their grid, all of them or 3 evenly spaced ones, at most
:data:`MAX_IMAGES_PER_SCAN` per scan. Each candidate adds its rows' information
``D_c^T W D_c`` to the current one (the prior plus the scans, or the inverse of
a reconstruction's moment posterior); candidates are picked greedily by the
reduction of the targets' posterior std (relative to today's) per added image.
Every candidate image is tracked (the full, nonlinear tracking, a Gaussian
sample of the beam) and kept only where at least :data:`MIN_ON_SCREEN` of the
beam lands on the screen. Changing a bend's ``angle`` changes the reference
orbit it defines, and the screen behind it sits on that orbit (the model's
convention); where the beam then lands follows from the tracking.

**Sequential quadrupole design** (:func:`propose_quad_settings`). For a plain
quadrupole scan: the classic rms fit of ``(S11, S12, S22)`` per plane from the
measured image moments, and the next strength(s) that minimise the summed
relative variance of the emittances after adding them (jointly, a
look-ahead).
"""

from __future__ import annotations

import functools
import itertools
import math
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor

from diffaccel.dynamics.beamline import Beamline
from diffaccel.reconstruction.forward import ScreenForwardModel
from diffaccel.reconstruction.initial import fit_gaussian
from diffaccel.reconstruction.metrics import COORDINATES
from diffaccel.reconstruction.prior_dependence import _moves
from diffaccel.reconstruction.screen_moments import (
    ENTRIES,
    moment_design,
    pair_indices,
    scaled_design,
)
from diffaccel.reconstruction.unseen import UNSEEN_TOLERANCE, traded_pairs

__all__ = [
    "DEFAULT_TARGETS",
    "QUANTITIES",
    "Knob",
    "Observability",
    "ScanLayout",
    "beam_from_images",
    "beam_from_spec",
    "image_kurtosis",
    "layouts_from_dataset",
    "layouts_from_spec",
    "observability",
    "observability_line",
    "parse_knob",
    "propose_quad_settings",
    "quad_scan_posterior",
    "quantities",
    "recommend",
    "tail_variance",
]

#: Entry names, e.g. ``"py-z"``.
ENTRY_NAMES = [f"{COORDINATES[i]}-{COORDINATES[j]}" for i, j in ENTRIES]
#: Named quantities of :func:`quantities`.
QUANTITIES = (
    "emit_x",
    "emit_y",
    "emit_z",
    "emit_4d",
    "emit_6d",
    *(f"rms_{c}" for c in COORDINATES),
    "beta_x",
    "alpha_x",
    "beta_y",
    "alpha_y",
    "chirp",
)
#: Quantities a recommendation targets unless told otherwise.
DEFAULT_TARGETS = ("emit_z", "emit_6d")
#: Relative error of each screen second moment when nothing better is known
#: (shot noise, background and calibration of a camera image: about 1 %).
RELATIVE_ERROR = 0.01
#: Prior std of a variance relative to its value and of a correlation
#: coefficient (the defaults of ``analyse_moments``).
PRIOR_VARIANCE = 1.0
PRIOR_CORRELATION = 0.5
#: Partial correlations of the traded pair at which the quantities' moves are
#: evaluated (real beams reach +-0.6).
MOVE_PARTIALS = (-0.6, 0.6)
#: A quantity or entry is left to the prior when its posterior std grows by
#: more than this factor if the prior is made ten times wider (a determined
#: one keeps its std: the data set it).
PRIOR_SENSITIVITY = 1.5
#: A quantity that moves by more than this fraction along an unseen direction
#: (over :data:`MOVE_PARTIALS`) is left to the prior whatever its std (at a
#: point of largest entropy the std of the linearised posterior misses it).
MOVE_LIMIT = 0.05
#: Fraction of the beam that must land on the screen for a candidate image.
MIN_ON_SCREEN = 0.95
#: Most added images per scan of a recommendation.
MAX_IMAGES_PER_SCAN = 8
#: Most combinations :func:`propose_quad_settings` evaluates jointly.
JOINT_LIMIT = 200_000
#: Grid points of a knob range unless the knob says ``:N``.
KNOB_POINTS = 5


# ------------------------------------------- the design's information
def _row_weights(n_rows: int, relative_error: float | Tensor) -> Tensor:
    """Inverse variances of scaled rows: ``1/r^2`` for ``<xx>, <yy>``, ``2/r^2``
    for ``<xy>``."""
    r = torch.as_tensor(relative_error, dtype=torch.float64)
    w = torch.tensor([1.0, 2.0, 1.0], dtype=torch.float64).repeat(n_rows // 3)
    return w / r**2


def _prior_precision() -> Tensor:
    p = [PRIOR_VARIANCE if i == j else PRIOR_CORRELATION for i, j in ENTRIES]
    return torch.diag(torch.tensor(p, dtype=torch.float64) ** -2)


def information(scaled: Tensor, relative_error: float | Tensor) -> Tensor:
    """Fisher information ``D^T W D`` of scaled rows, ``(3 K, 21) -> (21, 21)``."""
    w = _row_weights(scaled.shape[0], relative_error)
    return scaled.T @ (scaled * w[:, None])


# ------------------------------------------------------------- the quantities
def quantities(cov: Tensor) -> dict[str, Tensor]:
    """Named quantities of a covariance (differentiable, batched).

    Geometric emittances [m, m, m, m^2, m^3], rms of every coordinate, Twiss
    ``beta`` [m] and ``alpha``, and the chirp ``<z pz> / <z z>`` [1/m].

    Shapes:
        ``cov (*B, 6, 6)`` -> each ``(*B,)``.
    """

    def det_sqrt(idx: list[int]) -> Tensor:
        sub = cov[..., idx, :][..., :, idx]
        return torch.linalg.det(sub).clamp_min(1e-300).sqrt()

    out = {
        "emit_x": det_sqrt([0, 1]),
        "emit_y": det_sqrt([2, 3]),
        "emit_z": det_sqrt([4, 5]),
        "emit_4d": det_sqrt([0, 1, 2, 3]),
        "emit_6d": det_sqrt([0, 1, 2, 3, 4, 5]),
    }
    for i, c in enumerate(COORDINATES):
        out[f"rms_{c}"] = cov[..., i, i].clamp_min(1e-300).sqrt()
    for name, i in (("x", 0), ("y", 2)):
        out[f"beta_{name}"] = cov[..., i, i] / out[f"emit_{name}"]
        out[f"alpha_{name}"] = -cov[..., i, i + 1] / out[f"emit_{name}"]
    out["chirp"] = cov[..., 4, 5] / cov[..., 4, 4].clamp_min(1e-300)
    return out


#: Posterior draws behind each std (the same normal deviates for every
#: candidate, so that candidates are compared without sampling noise).
N_DRAWS = 256


def _draw_stds(cov: Tensor, info: Tensor, names: Sequence[str]) -> Tensor:
    """Std over posterior draws of each quantity (as ``MomentUncertainty``
    reports it): entries ``theta0 + L z`` with ``L L^T = info^-1`` in
    correlation units, quantities of each drawn covariance.

    Shapes: ``cov (6, 6)``, ``info (*B, 21, 21)`` -> ``(*B, Q)``.
    """
    s0 = cov.to(torch.float64)
    sig = s0.diagonal().clamp_min(1e-300).sqrt()
    g = torch.Generator().manual_seed(0)
    z = torch.randn(N_DRAWS, len(ENTRIES), generator=g, dtype=torch.float64)
    c = torch.linalg.inv(0.5 * (info + info.transpose(-1, -2)))
    w, v = torch.linalg.eigh(0.5 * (c + c.transpose(-1, -2)))
    lc = v * w.clamp_min(0).sqrt()[..., None, :]
    delta = z @ lc.transpose(-1, -2)  # (*B, n, 21)
    ii = torch.tensor([e[0] for e in ENTRIES])
    jj = torch.tensor([e[1] for e in ENTRIES])
    m = torch.zeros(*delta.shape[:-1], 6, 6, dtype=torch.float64)
    m[..., ii, jj] = delta * sig[ii] * sig[jj]
    draws = s0 + m + m.transpose(-1, -2) - torch.diag_embed(m.diagonal(0, -2, -1))
    q = quantities(draws)
    return torch.stack([q[n].std(-1) for n in names], -1)


# ------------------------------------------------------------------ scans
@dataclass
class ScanLayout:
    """One scan as the design sees it: its forward model and settings.

    Args:
        name: Scan name.
        forward: The scan's forward model (beamline, screen, scanned names).
        settings: The scan's settings ``(K, P)`` (those measured, or those
            planned); may be empty ``(0, P)`` for a layout only knobs fill.
    """

    name: str
    forward: ScreenForwardModel
    settings: Tensor

    def maps(self) -> Tensor:
        """First-order maps ``(K, 7, 7)`` of the settings."""
        if self.settings.shape[0] == 0:
            return torch.zeros(0, 7, 7, dtype=torch.float64)
        return self.forward.transfer_maps(self.settings)


def layouts_from_dataset(dataset: Any) -> list[ScanLayout]:
    """Layouts of every scan of a ``MultiScanDataset`` (or one ``QuadScanDataset``)."""
    scans = list(dataset) if hasattr(dataset, "names") else [("scan", dataset)]
    return [
        ScanLayout(n, ScreenForwardModel.from_dataset(s), s.settings.clone())
        for n, s in scans
    ]


#: Rms of z [m] and pz [1] given to a beam whose images do not see them
#: (``ReconstructionConfig.longitudinal_scale``'s default).
LONGITUDINAL_RMS = (1e-3, 1e-3)


def beam_from_images(dataset: Any) -> Tensor:
    """Prior beam ``(6, 6)`` of a dataset: the Gaussian fit to its image moments.

    :func:`~diffaccel.reconstruction.initial.fit_gaussian` (no training);
    coordinates the scans do not see get :data:`LONGITUDINAL_RMS`, uncorrelated,
    and the result is made positive definite (correlations within 0.98).
    """
    scans = list(dataset) if hasattr(dataset, "names") else [("scan", dataset)]
    fwds = [
        ScreenForwardModel.from_dataset(
            s, blur_pixels=s.resolution_pixels if s.resolution_pixels else 1.0
        )
        for _, s in scans
    ]
    guess = fit_gaussian(
        fwds, [s.mean_images() for _, s in scans], [s.settings for _, s in scans]
    )
    cov = guess.cov.clone()
    for i in (4, 5):
        if not float(cov[i, i]) > 0:
            cov[i, :] = 0.0
            cov[:, i] = 0.0
            cov[i, i] = LONGITUDINAL_RMS[i - 4] ** 2
    d = cov.diagonal().clamp_min(1e-300).sqrt()
    c = cov / (d[:, None] * d[None, :])
    w, v = torch.linalg.eigh(0.5 * (c + c.T))
    c = (v * w.clamp_min(0.02)) @ v.T
    e = c.diagonal().sqrt()
    return c / (e[:, None] * e[None, :]) * (d[:, None] * d[None, :])


def beam_from_spec(beam: Mapping[str, Any], where: str = "beam") -> Tensor:
    """Covariance ``(6, 6)`` of ``{"rms": [6 values], "corr": 6x6 (optional)}``
    or ``{"cov": 6x6}`` [Bmad units].

    Raises:
        ValueError: naming the field for a wrong shape, a non-positive rms or
            a covariance that is not positive definite.
    """
    try:
        if "cov" in beam:
            cov = torch.tensor(beam["cov"], dtype=torch.float64)
        else:
            rms = torch.tensor(beam["rms"], dtype=torch.float64)
            corr = torch.tensor(
                beam.get("corr", torch.eye(6).tolist()), dtype=torch.float64
            )
            if rms.shape != (6,) or not bool((rms > 0).all()):
                raise ValueError(
                    f"{where}.rms: expected 6 values > 0; got {beam['rms']!r}"
                )
            cov = corr * rms[:, None] * rms[None, :]
    except (KeyError, TypeError) as err:
        raise ValueError(
            f"{where}: expected {{'rms': [6 values], 'corr': 6x6}} or {{'cov': 6x6}} "
            f"({err})"
        ) from None
    if cov.shape != (6, 6) or not bool(torch.isfinite(cov).all()):
        raise ValueError(f"{where}: the covariance must be a finite 6x6 matrix.")
    cov = 0.5 * (cov + cov.T)
    if not float(torch.linalg.eigvalsh(cov).min()) > 0:
        raise ValueError(f"{where}: the covariance is not positive definite.")
    return cov


def layouts_from_spec(spec: Mapping[str, Any]) -> tuple[list[ScanLayout], Tensor]:
    """Layouts and prior beam of a design spec (no images).

    The spec (JSON) holds ``p0c`` [eV], optional ``species``, ``beam`` (see
    :func:`beam_from_spec`) and ``scans``: ``{NAME: {"beamline": [element
    dicts, one Screen with shape, pixel_size and center], "knobs":
    {"ELEMENT.param": [low, high, n], ...}}}``; each scan's settings are the
    grid of its knobs (``n`` values from ``low`` to ``high`` each, every
    combination). ``"settings"`` with ``"names"`` gives explicit rows instead.

    Raises:
        ValueError: one line naming the field that is missing or wrong: no
            knobs, a grid of fewer than one value, settings rows that do not
            match the names, or a scan whose every setting puts the prior
            beam off its screen (:data:`MIN_ON_SCREEN`).
    """
    for key in ("p0c", "beam", "scans"):
        if key not in spec:
            raise ValueError(f"design spec: missing {key!r}")
    cov = beam_from_spec(spec["beam"])
    if not isinstance(spec["scans"], Mapping) or not spec["scans"]:
        raise ValueError("design spec: 'scans' must map scan names to scans")
    out = []
    for name, scan in spec["scans"].items():
        where = f"design spec: scans.{name}"
        try:
            line = Beamline.from_spec(scan["beamline"])
        except (KeyError, TypeError, ValueError) as err:
            raise ValueError(f"{where}.beamline: {err}") from None
        if "settings" in scan:
            names = list(scan.get("names", []))
            try:
                settings = torch.tensor(scan["settings"], dtype=torch.float64)
            except (TypeError, ValueError) as err:
                raise ValueError(
                    f"{where}.settings: not rows of numbers ({err})"
                ) from None
            if settings.dim() == 1 and len(names) == 1:  # one knob: a list of values
                settings = settings[:, None]
        else:
            knobs = scan.get("knobs", {})
            if not isinstance(knobs, Mapping) or not knobs:
                raise ValueError(
                    f"{where}: no knobs; give the scanned parameters, e.g. "
                    '"knobs": {"Q1.k1": [-10, 10, 7]}, or "names" and "settings"'
                )
            names = list(knobs)
            grids = []
            for k, v in knobs.items():
                if not (isinstance(v, list | tuple) and len(v) in (1, 2, 3)):
                    raise ValueError(f"{where}.knobs.{k}: expected [low, high, n]")
                lo, hi = float(v[0]), float(v[-1] if len(v) < 3 else v[1])
                n = v[2] if len(v) == 3 else (1 if lo == hi else KNOB_POINTS)
                if isinstance(n, bool) or not isinstance(n, int) or n < 1:
                    raise ValueError(
                        f"{where}.knobs.{k}: n must be a whole number >= 1; got {n!r}"
                    )
                grids.append(torch.linspace(lo, hi, n, dtype=torch.float64))
            rows = list(itertools.product(*[g.tolist() for g in grids]))
            settings = torch.tensor(rows, dtype=torch.float64).reshape(-1, len(names))
        try:
            fwd = ScreenForwardModel(
                line, names, float(spec["p0c"]), species=spec.get("species", "electron")
            )
            if (
                settings.dim() != 2
                or not len(settings)
                or settings.shape[1] != len(names)
            ):
                raise ValueError(
                    f"settings must be rows of {len(names)} value(s), one per "
                    f"name in {names}; got shape {tuple(settings.shape)}."
                )
            fwd.check_settings(settings)
        except (TypeError, ValueError) as err:
            raise ValueError(f"{where}: {err}") from None
        frac = _on_screen(fwd, settings, cov)
        if not bool((frac >= MIN_ON_SCREEN).any()):  # the scan measures nothing
            raise ValueError(
                f"{where}: the prior beam misses the screen at every setting (less "
                f"than {MIN_ON_SCREEN:.0%} of it lands on it); check the beam's rms, "
                "the screen's shape and pixel_size, and the knob ranges"
            )
        out.append(ScanLayout(str(name), fwd, settings))
    return out, cov


# ------------------------------------------------------------------ observability
@dataclass
class Observability:
    """What the scans determine (see the module).

    Attributes:
        singular_values: Of the scaled design over the seen entries, relative
            to the largest, descending.
        longitudinal_singular_values: Of its columns with z or pz only (the
            transverse entries held), relative to their largest.
        unseen: One dict per direction below the tolerance: ``singular_value``,
            ``entries`` (``[name, weight]``, largest first), ``words`` (e.g.
            ``"py-z together with z-z"``), ``pair`` (the correlation it
            trades) and ``moves`` (``{quantity: [relative change at each of
            MOVE_PARTIALS or None]}``).
        not_seen: Coordinates no screen sees at all (every entry's column 0).
        entries: ``{entry: {"posterior_std", "prior_std", "determined"}}``
            (correlation units).
        quantities: ``{name: {"value", "relative_std", "prior_relative_std",
            "determined"}}``.
        relative_error: The moment error used.
    """

    singular_values: list[float]
    longitudinal_singular_values: list[float]
    unseen: list[dict]
    not_seen: list[str]
    entries: dict[str, dict]
    quantities: dict[str, dict]
    relative_error: float
    info: Tensor = field(repr=False, default_factory=lambda: torch.zeros(0))

    def determined(self) -> list[str]:
        """Named quantities the scans determine."""
        return [k for k, v in self.quantities.items() if v["determined"]]

    def left_to_prior(self) -> list[str]:
        """Named quantities the prior sets."""
        return [k for k, v in self.quantities.items() if not v["determined"]]

    def summary_line(self) -> str:
        """One line: what is unseen and what that leaves to the prior."""
        parts = []
        if self.not_seen:
            parts.append(f"{' and '.join(self.not_seen)} not seen at all")
        for u in self.unseen:
            parts.append(
                f"{u['words']} unseen (singular value {u['singular_value']:.1e})"
            )
        if not parts:
            return "observability: the scans see every second moment"
        left = self.left_to_prior()
        tail = f"; left to the prior: {', '.join(left)}" if left else ""
        return "observability: " + "; ".join(parts) + tail

    def to_dict(self) -> dict:
        """JSON-ready form."""
        return {
            "singular_values": self.singular_values,
            "longitudinal_singular_values": self.longitudinal_singular_values,
            "unseen": self.unseen,
            "not_seen": self.not_seen,
            "determined": self.determined(),
            "left_to_prior": self.left_to_prior(),
            "entries": self.entries,
            "quantities": self.quantities,
            "relative_error": self.relative_error,
            "summary": self.summary_line(),
        }


def _words(vec: Tensor, names: Sequence[str], share: float = 0.9) -> list[list]:
    order = vec.abs().argsort(descending=True).tolist()
    out, acc = [], 0.0
    for k in order:
        out.append([names[k], round(float(vec[k]), 3)])
        acc += float(vec[k]) ** 2
        if acc >= share or len(out) == 3:
            break
    return out


def _phrase(names: Sequence[str]) -> str:
    """``"py-z together with z-z"``, ``"a together with b and c"``."""
    if len(names) == 1:
        return names[0]
    return f"{names[0]} together with " + " and ".join(names[1:])


def _direction_matrix(vec: Tensor, cols: Sequence[int], sig: Tensor) -> Tensor:
    m = torch.zeros(6, 6, dtype=torch.float64)
    for v, c in zip(vec.tolist(), cols, strict=True):
        i, j = ENTRIES[c]
        m[i, j] = v * float(sig[i] * sig[j])
    return m + m.T - torch.diag(m.diagonal())


def observability(
    layouts: Sequence[ScanLayout] | Sequence[Tensor],
    cov: Tensor,
    *,
    relative_error: float = RELATIVE_ERROR,
    posterior: Tensor | None = None,
    tolerance: float = UNSEEN_TOLERANCE,
    partials: Sequence[float] = MOVE_PARTIALS,
) -> Observability:
    """Which second moments and quantities the scans determine (see the module).

    Args:
        layouts: The scans (or their maps ``(K_s, 7, 7)`` directly).
        cov: The beam's covariance ``(6, 6)`` [Bmad units]: a reconstruction's,
            an image-moment fit's or a prior beam's.
        relative_error: Relative error of each screen second moment.
        posterior: A moment posterior of the entries ``(21, 21)`` [Bmad units]
            to use instead of the prior and the scans' information.
        tolerance: Relative singular value below which a direction is unseen.
        partials: Partial correlations at which the moves are evaluated.

    Returns:
        An :class:`Observability`.
    """
    s = cov.to(torch.float64)
    maps = [x.maps() if isinstance(x, ScanLayout) else x for x in layouts]
    d, _ = scaled_design(moment_design(maps), s)
    info = information_from(d, relative_error, posterior, s)
    norms = d.abs().amax(0)
    ref = float(norms.max()) if norms.numel() else 0.0
    seen = [c for c in range(len(ENTRIES)) if float(norms[c]) > 1e-9 * ref]
    not_seen = [
        COORDINATES[i]
        for i in range(6)
        if all(c not in seen for c, (a, b) in enumerate(ENTRIES) if i in (a, b))
    ]
    sv_all: list[float] = []
    unseen: list[dict] = []
    sig = s.diagonal().clamp_min(1e-300).sqrt()
    qnames = list(QUANTITIES)
    base = {k: float(v) for k, v in quantities(s).items()}
    if seen:
        _, sv, vh = torch.linalg.svd(d[:, seen], full_matrices=True)
        full = torch.zeros(len(seen), dtype=torch.float64)
        full[: sv.shape[0]] = sv
        rel = full / full[0]
        sv_all = rel.tolist()
        names = [ENTRY_NAMES[c] for c in seen]
        for k in reversed(torch.nonzero(rel < tolerance).flatten().tolist()):
            vec = vh[k]
            direction = _direction_matrix(vec, seen, sig)
            pair = traded_pairs(direction[None], s)[0]
            entries = _words(vec, names)
            label = f"{COORDINATES[pair[0]]}-{COORDINATES[pair[1]]}"
            entries.sort(key=lambda e: e[0] != label)  # the traded pair first
            moves: dict[str, list] = {q: [] for q in qnames}
            for moved in _moves(s, direction, pair, partials):
                mq = None if moved is None else quantities(moved)
                for q in qnames:
                    moves[q].append(
                        None
                        if mq is None or base[q] == 0
                        else float(mq[q]) / base[q] - 1.0
                    )
            unseen.append(
                {
                    "singular_value": float(rel[k]),
                    "entries": entries,
                    "words": _phrase([e[0] for e in entries]),
                    "pair": label,
                    "moves": moves,
                }
            )
    lcols = [c for c in seen if max(ENTRIES[c]) >= 4]
    lsv: list[float] = []
    if lcols:
        sv_l = torch.linalg.svdvals(d[:, lcols])
        full = torch.zeros(len(lcols), dtype=torch.float64)
        full[: sv_l.shape[0]] = sv_l
        lsv = (full / full[0]).tolist() if float(full[0]) > 0 else full.tolist()
    wide = info - _prior_precision() * (1.0 - 1e-2)  # the prior 10x wider
    cpost = torch.linalg.inv(info).diagonal().clamp_min(0).sqrt()
    cwide = torch.linalg.inv(wide).diagonal().clamp_min(0).sqrt()
    prior = _prior_precision().diagonal().rsqrt()
    entries_out = {
        n: {
            "posterior_std": float(cpost[c]),
            "prior_std": float(prior[c]),
            "determined": bool(cwide[c] < PRIOR_SENSITIVITY * cpost[c]),
        }
        for c, n in enumerate(ENTRY_NAMES)
    }
    post, post_wide, pstd = _draw_stds(
        s, torch.stack([info, wide, _prior_precision()]), qnames
    )
    qout = {}
    for k, q in enumerate(qnames):
        v = abs(base[q]) or 1e-300
        moved = max(
            (abs(c) for u in unseen for c in u["moves"][q] if c is not None),
            default=0.0,
        )
        qout[q] = {
            "value": base[q],
            "relative_std": float(post[k]) / v,
            "prior_relative_std": float(pstd[k]) / v,
            "largest_move": moved,
            "determined": bool(post_wide[k] < PRIOR_SENSITIVITY * post[k])
            and moved <= MOVE_LIMIT,
        }
    return Observability(
        sv_all, lsv, unseen, not_seen, entries_out, qout, float(relative_error), info
    )


def information_from(
    scaled: Tensor,
    relative_error: float,
    posterior: Tensor | None,
    cov: Tensor,
) -> Tensor:
    """Current information ``(21, 21)`` in correlation units: the prior plus the
    scans', or the inverse of a moment posterior (Bmad units, entries
    :data:`ENTRIES`, or the 10 of a 4D reconstruction: the rest from the prior)."""
    if posterior is None:
        return information(scaled, relative_error) + _prior_precision()
    sig = cov.to(torch.float64).diagonal().clamp_min(1e-300).sqrt()
    p = posterior.to(torch.float64)
    sub = pair_indices(4) if p.shape[0] == 10 else ENTRIES
    idx = [ENTRIES.index(e) for e in sub]
    col = torch.stack([sig[i] * sig[j] for i, j in sub])
    pc = p / (col[:, None] * col[None, :])
    w, v = torch.linalg.eigh(0.5 * (pc + pc.T))
    floor = 1e-12 * float(w.abs().max())
    inv = (v / w.clamp_min(floor)) @ v.T
    info = _prior_precision()
    ii = torch.tensor(idx)
    info[ii[:, None], ii[None, :]] = inv
    return info


# ------------------------------------------------------------------ knobs
@dataclass(frozen=True)
class Knob:
    """A candidate parameter and its range: ``ELEMENT.param=LOW:HIGH[:N]``."""

    name: str
    low: float
    high: float
    points: int = KNOB_POINTS

    def values(self) -> list[float]:
        """The grid of values tried."""
        if self.low == self.high or self.points == 1:
            return [self.low]
        return torch.linspace(
            self.low, self.high, self.points, dtype=torch.float64
        ).tolist()


_NUM = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
_KNOB = re.compile(
    rf"^([A-Za-z_][\w\-]*\.[A-Za-z_]\w*)=({_NUM})(?::({_NUM}))?(?::(\d+))?$"
)


def parse_knob(text: str) -> Knob:
    """``"SCAN_TDC.voltage=-4e6:4e6"`` (optionally ``:N`` grid points) -> :class:`Knob`.

    Raises:
        ValueError: one line for any other syntax or a range with LOW > HIGH.
    """
    m = _KNOB.match(text.strip())
    if m is None:
        raise ValueError(
            f"knob {text!r}: expected ELEMENT.param=LOW:HIGH (e.g. "
            "SCAN_TDC.voltage=-4e6:4e6), optionally :N grid points, or "
            "ELEMENT.param=VALUE"
        )
    lo = float(m.group(2))
    hi = float(m.group(3)) if m.group(3) is not None else lo
    n = int(m.group(4)) if m.group(4) is not None else KNOB_POINTS
    if lo > hi:
        raise ValueError(f"knob {text!r}: LOW {lo:g} is above HIGH {hi:g}")
    if n < 1:
        raise ValueError(f"knob {text!r}: N must be >= 1")
    return Knob(m.group(1), lo, hi, n)


def _current_value(fwd: ScreenForwardModel, name: str) -> float:
    elem, param = name.split(".", 1)
    spec = next(e for e in fwd.beamline.to_spec() if e["name"] == elem)
    return float(spec.get(param, 0.0))


def _extended(
    layout: ScanLayout, knobs: Sequence[Knob]
) -> tuple[ScreenForwardModel, Tensor]:
    """The layout's forward model with every knob a scanned name, and its
    distinct settings in those names (knobs at their current values)."""
    fwd = layout.forward
    names = list(fwd.names) + [k.name for k in knobs if k.name not in fwd.names]
    ext = ScreenForwardModel(fwd.beamline, names, fwd.p0c, species=fwd.species)
    base = layout.settings.to(torch.float64)
    extra = [
        torch.full((base.shape[0], 1), _current_value(fwd, n), dtype=torch.float64)
        for n in names[len(fwd.names) :]
    ]
    rows = torch.cat([base, *extra], 1) if extra else base
    if rows.shape[0] == 0:
        rows = torch.tensor(
            [[_current_value(fwd, n) for n in names]], dtype=torch.float64
        )
    return ext, torch.unique(rows, dim=0)


def _applicable(layout: ScanLayout, knob: Knob) -> bool:
    return knob.name.split(".", 1)[0] in layout.forward.beamline.element_names


def check_knobs(layouts: Sequence[ScanLayout], knobs: Sequence[Knob]) -> None:
    """Refuse knobs no scan has, parameters elements lack, values beyond limits
    and knobs that move nothing (one-line ``ValueError`` each)."""
    for knob in knobs:
        where = [x for x in layouts if _applicable(x, knob)]
        if not where:
            elements = sorted(
                {e for x in layouts for e in x.forward.beamline.element_names}
            )
            raise ValueError(
                f"knob {knob.name!r}: no element {knob.name.split('.')[0]!r} in the "
                f"beamline of any scan (elements: {', '.join(elements)})"
            )
        moved = 0.0
        scale = 0.0
        for x in where:
            try:
                ext, rows = _extended(x, [knob])
                col = ext.names.index(knob.name)
                ends = []
                values = [knob.low, knob.high, 0.5 * (knob.low + knob.high)]
                if knob.low == knob.high:  # one value: against the current one
                    values.append(_current_value(x.forward, knob.name))
                for v in values:
                    r = rows.clone()
                    r[:, col] = v
                    ends.append(ext.transfer_maps(r)[:, :6, :6])
            except ValueError as err:
                raise ValueError(f"knob {knob.name!r}: {err}") from None
            for other in ends[1:]:
                moved = max(moved, float((ends[0] - other).abs().max()))
            scale = max(scale, float(ends[0].abs().max()))
        if not moved > 1e-12 * scale:
            raise ValueError(
                f"knob {knob.name!r} moves nothing: the maps to every screen are the "
                f"same from {knob.low:g} to {knob.high:g} (and at the beamline's "
                "value), so no image would change"
            )


def _on_screen(
    fwd: ScreenForwardModel, rows: Tensor, cov: Tensor, n: int = 2000
) -> Tensor:
    """Fraction of a Gaussian sample of ``cov`` that lands on the screen ``(K,)``."""
    g = torch.Generator().manual_seed(0)
    lc = torch.linalg.cholesky(cov.to(torch.float64))
    x = torch.randn(n, 6, generator=g, dtype=torch.float64) @ lc.T
    at = fwd.track_to_screen(x, rows)  # (K, N, 6)
    xs, ys = fwd.screen.pixel_centers(dtype=torch.float64)
    psx, psy = fwd.screen.pixel_size
    inside = (
        (at[..., 0] >= float(xs[0]) - psx / 2)
        & (at[..., 0] <= float(xs[-1]) + psx / 2)
        & (at[..., 2] >= float(ys[0]) - psy / 2)
        & (at[..., 2] <= float(ys[-1]) + psy / 2)
        & torch.isfinite(at).all(-1)
    )
    return inside.double().mean(-1)


def _subsets(k: int, limit: int) -> list[list[int]]:
    full = list(range(k))
    if k > limit:
        full = sorted({round(i * (k - 1) / (limit - 1)) for i in range(limit)})
    out = [full]
    if len(full) > 3:
        out.append(sorted({full[round(i * (len(full) - 1) / 2)] for i in range(3)}))
    return out


@dataclass
class _Candidate:
    scan: str
    names: list[str]
    rows: Tensor
    info: Tensor


def recommend(
    layouts: Sequence[ScanLayout],
    cov: Tensor,
    knobs: Sequence[Knob],
    *,
    targets: Sequence[str] = DEFAULT_TARGETS,
    relative_error: float = RELATIVE_ERROR,
    posterior: Tensor | None = None,
    max_images_per_scan: int = MAX_IMAGES_PER_SCAN,
    max_added: int = 4,
    min_gain: float = 0.01,
) -> dict:
    """Ranked added settings that most reduce the targets' posterior std per image.

    Args:
        layouts: The scans so far.
        cov: Beam covariance ``(6, 6)`` [Bmad units] (scales rows and
            unknowns, tracked for the on-screen check).
        knobs: Candidate knobs (:func:`parse_knob`).
        targets: Quantities of :data:`QUANTITIES` whose std is reduced.
        relative_error: Relative error of each screen second moment.
        posterior: A reconstruction's moment posterior ``(P, P)`` [Bmad units]
            (today's information); default the prior plus the scans.
        max_images_per_scan: Most added images per scan.
        max_added: Most added settings groups.
        min_gain: Stop when the best candidate reduces the summed relative
            std (in units of today's) by less than this per image.

    Returns:
        ``{"unseen", "baseline_std", "recommended": [{"scan", "names",
        "values", "n_images", "expected_std", "gain_per_image"}], "excluded"}``
        with ``expected_std`` the targets' relative posterior std after this and
        every earlier recommendation, and ``all_std`` every quantity's.

    Raises:
        ValueError: for an unknown target, a knob no scan has, a parameter
            its element lacks, a knob that moves nothing, or a knob whose
            whole range puts the beam off the screen.
    """
    bad = [t for t in targets if t not in QUANTITIES]
    if bad:
        raise ValueError(
            f"unknown quantity {bad[0]!r}; choose from {', '.join(QUANTITIES)}"
        )
    check_knobs(layouts, knobs)
    s = cov.to(torch.float64)
    obs = observability(layouts, s, relative_error=relative_error, posterior=posterior)
    info0 = obs.info
    qnames = list(QUANTITIES)
    tsel = [qnames.index(t) for t in targets]
    vals = torch.tensor([abs(obs.quantities[q]["value"]) or 1e-300 for q in qnames])
    base_std = _draw_stds(s, info0, qnames) / vals
    cands: list[_Candidate] = []
    excluded: list[str] = []
    on_values: dict[str, set] = {}
    had_rows: set[str] = set()
    for layout in layouts:
        mine = [k for k in knobs if _applicable(layout, k)]
        if not mine:
            continue
        ext, base = _extended(layout, mine)
        cols = [ext.names.index(k.name) for k in mine]
        combos = list(itertools.product(*[k.values() for k in mine]))
        all_rows = []
        for combo in combos:
            r = base.clone()
            for c, v in zip(cols, combo, strict=True):
                r[:, c] = v
            r = torch.unique(r, dim=0)
            # a setting the scan has already measured adds nothing new
            new = ~(r[:, None, :] == base[None, :, :]).all(-1).any(-1)
            all_rows.append(r[new])
        stacked = torch.cat(all_rows)
        if stacked.shape[0] == 0:
            continue
        had_rows.update(k.name for k in mine)
        frac = _on_screen(ext, stacked, s)
        d, _ = scaled_design(moment_design([ext.transfer_maps(stacked)]), s)
        per_row = d.reshape(-1, 3, d.shape[-1])
        w = _row_weights(3, relative_error)
        row_info = torch.einsum("kra,r,krb->kab", per_row, w, per_row)
        start = 0
        for combo, r in zip(combos, all_rows, strict=True):
            idx = list(range(start, start + r.shape[0]))
            start += r.shape[0]
            ok = [i for i in idx if float(frac[i]) >= MIN_ON_SCREEN]
            if ok:
                for k in mine:
                    on_values.setdefault(k.name, set()).add(
                        float(stacked[ok[0], ext.names.index(k.name)])
                    )
            if len(ok) < len(idx):
                label = ", ".join(
                    f"{k.name}={v:g}" for k, v in zip(mine, combo, strict=True)
                )
                excluded.append(
                    f"{layout.name}: {label}: {len(idx) - len(ok)} of {len(idx)} "
                    "settings put the beam off the screen"
                )
            for sub in _subsets(len(ok), max_images_per_scan):
                pick = [ok[i] for i in sub]
                if pick:
                    cands.append(
                        _Candidate(
                            layout.name, ext.names, stacked[pick], row_info[pick].sum(0)
                        )
                    )
    for knob in knobs:  # a knob whose every candidate is off the screen
        if knob.name not in had_rows:
            raise ValueError(
                f"knob {knob.name}={knob.low:g}:{knob.high:g} adds no setting: the "
                "scans have measured every one already"
            )
        if knob.name not in on_values:
            raise ValueError(
                f"knob {knob.name}={knob.low:g}:{knob.high:g} puts the beam off the "
                f"screen at every value (less than {MIN_ON_SCREEN:.0%} of it lands "
                "on the screen)"
            )
    info = info0.clone()
    used: dict[str, int] = {}
    picked: list[dict] = []
    chosen: set[int] = set()
    cur = base_std.clone()
    for _ in range(max_added):
        live = [
            i
            for i, c in enumerate(cands)
            if i not in chosen
            and used.get(c.scan, 0) + c.rows.shape[0] <= max_images_per_scan
        ]
        if not live:
            break
        stack = torch.stack([info + cands[i].info for i in live])
        new = _draw_stds(s, stack, qnames) / vals  # (L, Q)
        gain = ((cur[tsel] - new[:, tsel]) / base_std[tsel]).sum(-1)
        per_img = gain / torch.tensor([float(cands[i].rows.shape[0]) for i in live])
        best = int(per_img.argmax())
        if not float(per_img[best]) > min_gain:
            break
        c = cands[live[best]]
        chosen.add(live[best])
        info = info + c.info
        cur = new[best]
        used[c.scan] = used.get(c.scan, 0) + c.rows.shape[0]
        picked.append(
            {
                "scan": c.scan,
                "names": list(c.names),
                "values": c.rows.tolist(),
                "n_images": int(c.rows.shape[0]),
                "expected_std": {t: float(cur[qnames.index(t)]) for t in targets},
                "gain_per_image": float(per_img[best]),
                "all_std": {q: float(cur[k]) for k, q in enumerate(qnames)},
            }
        )
    return {
        "unseen": [
            {k: u[k] for k in ("words", "pair", "singular_value", "entries", "moves")}
            for u in obs.unseen
        ],
        "not_seen": obs.not_seen,
        "targets": list(targets),
        "baseline_std": {q: float(base_std[k]) for k, q in enumerate(qnames)},
        "recommended": picked,
        "excluded": excluded,
        "relative_error": float(relative_error),
    }


def singular_values_with(
    layouts: Sequence[ScanLayout], cov: Tensor, added: Sequence[dict]
) -> tuple[list[float], list[float]]:
    """Relative singular values (all seen entries; longitudinal block) of the
    scans plus recommended settings (``recommend(...)["recommended"]``)."""
    maps = [x.maps() for x in layouts]
    by_name = {x.name: x for x in layouts}
    for a in added:
        fwd = by_name[a["scan"]].forward
        ext = ScreenForwardModel(fwd.beamline, a["names"], fwd.p0c, species=fwd.species)
        maps.append(ext.transfer_maps(torch.tensor(a["values"], dtype=torch.float64)))
    obs = observability(maps, cov, partials=())
    return obs.singular_values, obs.longitudinal_singular_values


# ------------------------------------------------------ sequential quad design
#: Gauss-Legendre nodes and weights on (0, 1) for the screen-edge tail integrals.
_GL_NODES = 96


@functools.cache
def _gauss_legendre() -> tuple[Tensor, Tensor]:
    xn, wn = np.polynomial.legendre.leggauss(_GL_NODES)
    return (
        torch.tensor(0.5 * (xn + 1.0), dtype=torch.float64),
        torch.tensor(0.5 * wn, dtype=torch.float64),
    )


def tail_variance(c: Tensor, kurtosis: Tensor | float = 3.0) -> Tensor:
    """Share of a projected variance beyond ``c`` rms on one side of the centroid.

    ``int_c^inf x^2 f(x) dx`` for the unit-variance profile ``f`` with the
    given kurtosis: a Gaussian for a kurtosis of 3 or less, else a Student t
    with ``nu = 4 + 6 / (kurtosis - 3)`` degrees of freedom (the same
    kurtosis). A screen edge ``c`` rms from the centroid hides this share of the
    beam's variance from the image (a Gaussian: 1.1 % at 3.1 rms; kurtosis
    4.4: 5 %).

    Shapes: ``c`` and ``kurtosis`` broadcast -> their broadcast shape.
    """
    c = torch.as_tensor(c, dtype=torch.float64)
    k = torch.as_tensor(kurtosis, dtype=torch.float64)
    c, k = torch.broadcast_tensors(c, k)
    w, wt = _gauss_legendre()
    cc = c.clamp(1e-3, 1e3)[..., None]  # beyond 1000 rms: no tail left
    heavy = (k > 3.0 + 1e-6)[..., None]
    nu = (4.0 + 6.0 / (k - 3.0).clamp_min(1e-6)).clamp_max(1e6)[..., None]
    s = ((nu - 2.0) / nu).sqrt()  # scale of unit variance

    def density(x: Tensor) -> Tensor:
        gauss = -0.5 * x**2 - 0.5 * math.log(2 * math.pi)
        student = (
            torch.lgamma((nu + 1) / 2)
            - torch.lgamma(nu / 2)
            - 0.5 * torch.log(nu * math.pi)
            - torch.log(s)
            - (nu + 1) / 2 * torch.log1p((x / s) ** 2 / nu)
        )
        return torch.exp(torch.where(heavy, student, gauss))

    # beyond c (x = c / w, w in (0, 1]), or a half minus the part within c
    outer = cc[..., 0] ** 3 * (density(cc / w) / w**4 * wt).sum(-1)
    inner = cc[..., 0] ** 3 * (density(cc * w) * w**2 * wt).sum(-1)
    out = torch.where(c > 1.0, outer, 0.5 - inner)
    return torch.where(c > 1e-3, out, torch.full_like(out, 0.5)).clamp(0.0, 0.5)


def image_kurtosis(
    images: Tensor, xs: Tensor, ys: Tensor, point_spread: Sequence[float] = (0.0, 0.0)
) -> Tensor:
    """Kurtosis ``<u^4> / <u^2>^2`` of the beam behind each image, x and y.

    From the image's marginal profiles: the fourth cumulant of the image is the
    beam's (a Gaussian point spread adds none), its variance the beam's plus
    the point spread's (``point_spread``, rms [m] in x and y). 3 for a Gaussian
    beam; it sets the shot noise of a measured variance,
    ``<xx> sqrt((kurtosis - 1) / N)`` for ``N`` particles.

    Shapes: ``images (K, H, W)``, ``xs (W,)``, ``ys (H,)`` -> ``(K, 2)``.
    """
    w = images.to(torch.float64)
    total = w.sum((-2, -1)).clamp_min(1e-300)
    out = []
    for prof, pos, ps in (
        (w.sum(-2), xs, point_spread[0]),
        (w.sum(-1), ys, point_spread[1]),
    ):
        p = prof / total[:, None]
        pos = pos.to(torch.float64)
        d = pos[None, :] - (p * pos).sum(-1, keepdim=True)
        m2 = (p * d**2).sum(-1)
        m4 = (p * d**4).sum(-1)
        beam2 = (m2 - ps**2).clamp_min(1e-300)
        out.append(3.0 + (m4 - 3.0 * m2**2) / beam2**2)
    return torch.stack(out, -1)


def _moment_sd(
    level: Tensor,
    r: float,
    floor: float,
    kurtosis: Tensor | None,
    half_width: Tensor | None,
    tails: Tensor | None,
) -> Tensor:
    """Error of a screen variance ``level`` (``(2, ...)``, x and y first):
    shot noise ``r level sqrt((kurtosis - 1) / 2)`` (``r level`` for a
    Gaussian beam), the floor, and, with ``half_width (2,)`` [m] from the
    centroid, the variance the screen edges hide (:func:`tail_variance` on
    both sides for the kurtosis ``tails (2,)`` of the beam's tails)."""
    shape = 1.0 if kurtosis is None else ((kurtosis - 1.0) / 2.0).clamp_min(0).sqrt()
    sd = r * level * shape + floor
    if half_width is not None:
        ones = [1] * (level.ndim - 1)
        hw = half_width.reshape(2, *ones)
        kk = 3.0 if tails is None else tails.reshape(2, *ones)
        c = hw / level.clamp_min(1e-300).sqrt()
        sd = sd + 2.0 * level * tail_variance(c, kk)
    return sd + 1e-300


def _kept(level: Tensor, half_width: Tensor | None, tails: Tensor | None) -> Tensor:
    """Share of a beam variance ``level`` (``(2, ...)``) that a screen with
    edges ``half_width (2,)`` from the centroid shows: one less the
    :func:`tail_variance` of both sides (1 for an unbounded screen)."""
    if half_width is None:
        return torch.ones_like(level)
    ones = [1] * (level.ndim - 1)
    kk = 3.0 if tails is None else tails.reshape(2, *ones)
    c = half_width.reshape(2, *ones) / level.clamp_min(1e-300).sqrt()
    return (1.0 - 2.0 * tail_variance(c, kk)).clamp_min(1e-3)


def _tails(kurtosis: Tensor | None) -> Tensor | None:
    """Kurtosis of the beam's tails per plane: the median over the images
    ``(K, 2) -> (2,)`` (an image the screen clips shows too little of them)."""
    if kurtosis is None:
        return None
    return kurtosis.to(torch.float64).median(0).values


#: Posterior draws that stand for a fit that is no physical beam (``S11 S22 <=
#: S12^2`` in a plane, possible from three settings) in the design criterion.
UNPHYSICAL_DRAWS = 32


def _physical(th: Tensor) -> Tensor:
    return (
        (th[..., 0] > 0)
        & (th[..., 2] > 0)
        & (th[..., 0] * th[..., 2] > th[..., 1] ** 2)
    )


def _physical_draws(th: Tensor, cov: Tensor, draws: int, seed: int) -> Tensor:
    """``(S11, S12, S22)`` per plane ``(D, 2, 3)`` the design criterion is
    averaged over: the fit (``draws`` 0), or ``draws`` physical draws of its
    posterior (drawn until there are enough, up to 64 times as many; too few
    are repeated). A plane whose fit is no physical beam gets
    :data:`UNPHYSICAL_DRAWS` of them even with ``draws`` 0; where none of its
    draws is physical either, its correlation is shrunk until its emittance^2
    is the posterior std of the emittance^2 (the scale the data cannot tell
    from zero)."""
    fit_ok = _physical(th)  # (2,)
    if draws <= 0 and bool(fit_ok.all()):
        return th[None]
    n = draws if draws > 0 else UNPHYSICAL_DRAWS
    gen = torch.Generator().manual_seed(seed)
    z = torch.randn(64 * n, 2, 3, generator=gen, dtype=torch.float64)
    w, v = torch.linalg.eigh(0.5 * (cov + cov.transpose(-1, -2)))
    lc = v * w.clamp_min(0).sqrt()[:, None, :]
    d = th[None] + torch.einsum("pab,dpb->dpa", lc, z)
    ok = _physical(d)  # (64 n, 2)
    out = th[None].repeat(n, 1, 1)
    for p in range(2):
        if draws <= 0 and bool(fit_ok[p]):
            continue  # (the fit itself, repeated)
        idx = ok[:, p].nonzero()[:, 0]
        if idx.numel() > 0:
            out[:, p] = d[idx[torch.arange(n) % idx.numel()], p]
            continue
        s11, s12, s22 = (float(v) for v in th[p])
        g = torch.tensor([s22, -2 * s12, s11], dtype=torch.float64)
        e2_sd = float((g @ cov[p] @ g).clamp_min(0).sqrt())
        s11, s22 = abs(s11) + 1e-300, abs(s22) + 1e-300
        e2 = max(e2_sd, 1e-6 * s11 * s22)
        s12 = math.copysign(math.sqrt(max(s11 * s22 - e2, 0.0)), s12)
        out[:, p] = torch.tensor([s11, s12, s22], dtype=torch.float64)
    return out


def _interp(x: Tensor, xp: Tensor, fp: Tensor) -> Tensor:
    """Linear interpolation of ``fp`` at ``xp`` to ``x``, constant beyond."""
    order = torch.argsort(xp)
    xp, fp = xp[order], fp[order]
    if xp.shape[0] == 1:
        return fp.expand(x.shape[0]).clone()
    i = torch.searchsorted(xp, x).clamp(1, xp.shape[0] - 1)
    x0, x1 = xp[i - 1], xp[i]
    t = ((x - x0) / (x1 - x0).clamp_min(1e-300)).clamp(0.0, 1.0)
    return fp[i - 1] + t * (fp[i] - fp[i - 1])


def quad_scan_posterior(
    maps: Tensor,
    moments: Tensor,
    *,
    relative_error: float | None = None,
    floor: float = 0.0,
    kurtosis: Tensor | None = None,
    half_width: Sequence[float] | None = None,
) -> dict[str, Tensor]:
    """Classic rms quadrupole-scan fit per plane with its Gaussian posterior.

    ``<xx>_k = R11^2 S11 + 2 R11 R12 S12 + R12^2 S22`` (and y with ``R33,
    R34``) by weighted least squares, errors ``r <xx>_k + floor`` with
    ``<xx>_k`` the fitted moment (three reweighted passes). Where given, each
    image's shot noise follows its beam's kurtosis (``r <xx>_k sqrt((kurtosis_k
    - 1) / 2)``, the same as ``r <xx>_k`` for a Gaussian). Screen edges
    ``half_width`` from the centroid hide part of each variance: the fit
    expects each image to show one less :func:`tail_variance` (both sides) of
    the fitted variance, for the median kurtosis of the plane's images (an
    image the edges clip shows too little of the tails to judge them itself);
    what that expectation misses is left to the residuals and so to ``r``.

    Args:
        maps: First-order maps ``(K, 6, 6)`` (or ``(K, 7, 7)``).
        moments: Measured screen ``(<xx>, <yy>)`` ``(K, 2)`` [m^2] (the
            point spread's variance already removed).
        relative_error: ``r``; None fits it to the residuals (pooled over both
            planes, ``2 K - 6`` degrees of freedom; 1 % where there are none).
        floor: Absolute error floor [m^2] (e.g. a fraction of a pixel^2).
        kurtosis: Each image's beam kurtosis ``(K, 2)`` (:func:`image_kurtosis`);
            None: Gaussian.
        half_width: Distance from the beam's centroid to the screen edges in x
            and y [m]; None: an unbounded screen.

    Returns:
        ``theta (2, 3)`` (``S11, S12, S22`` per plane), ``cov (2, 3, 3)``,
        ``emit (2,)``, ``emit_std (2,)`` [m] and ``relative_error`` (scalar).
    """
    m = maps.to(torch.float64)
    y = moments.to(torch.float64)
    rows = []
    for a, b in ((0, 1), (2, 3)):
        r1, r2 = m[:, a, a], m[:, a, b]
        rows.append(torch.stack([r1**2, 2 * r1 * r2, r2**2], -1))
    a_pl = torch.stack(rows)  # (2, K, 3)
    yy = y.T  # (2, K)
    k = y.shape[0]
    kt = None if kurtosis is None else kurtosis.to(torch.float64).T
    tails = _tails(kurtosis)
    hw = None if half_width is None else torch.tensor(half_width, dtype=torch.float64)

    def solve(r: float) -> tuple[Tensor, Tensor, Tensor]:
        # weights from the fitted moments (iterated), not the measured ones:
        # weighting by the data favours the low fluctuations (a bias)
        level = yy.abs()
        for _ in range(3):
            # the clipped share is expected (keep), its misfit left to r
            sd = _moment_sd(level, r, floor, kt, None, None)
            keep = _kept(level, hw, tails)  # the share the screen shows
            aw = a_pl * (keep / sd)[..., None]
            th = torch.linalg.lstsq(aw, (yy / sd)[..., None]).solution[..., 0]
            fit = (a_pl @ th[..., None])[..., 0]
            level = torch.where(fit > 0, fit, yy.abs())
        res = (yy - keep * fit) / sd
        return th, torch.linalg.pinv(aw.transpose(-1, -2) @ aw), res

    r = 0.01 if relative_error is None else float(relative_error)
    th, c, res = solve(r)
    if relative_error is None and 2 * k > 6:
        for _ in range(5):
            scale = float((res.square().sum() / (2 * k - 6)).sqrt())
            r = max(r * scale, 1e-6)
            th, c, res = solve(r)
    emit2 = th[:, 0] * th[:, 2] - th[:, 1] ** 2
    emit = emit2.clamp_min(1e-300).sqrt()
    g = torch.stack([th[:, 2], -2 * th[:, 1], th[:, 0]], -1) / (2 * emit[:, None])
    var = torch.einsum("pa,pab,pb->p", g, c, g)
    return {
        "theta": th,
        "cov": c,
        "emit": emit,
        "emit_std": var.clamp_min(0).sqrt(),
        "relative_error": torch.tensor(r),
    }


def propose_quad_settings(
    map_of: Callable[[Tensor], Tensor],
    maps: Tensor,
    moments: Tensor,
    candidates: Tensor,
    *,
    n: int = 1,
    planes: Sequence[int] = (0, 1),
    relative_error: float | None = None,
    floor: float = 0.0,
    min_separation: float = 0.0,
    joint: bool = True,
    measured: Tensor | None = None,
    draws: int = 0,
    seed: int = 0,
    kurtosis: Tensor | None = None,
    half_width: Sequence[float] | None = None,
) -> Tensor:
    """The next quadrupole strength(s) that minimise the emittances' posterior std.

    Fits the measurements so far (:func:`quad_scan_posterior`), then picks the
    ``n`` candidates (together, or one at a time) that minimise the summed
    relative variance of the emittances of ``planes`` once they are measured,
    their moments predicted by the fit and their errors those of
    :func:`quad_scan_posterior` (``r <xx> + floor``; with ``kurtosis``, the
    kurtosis of a candidate interpolated linearly in strength between the
    measured ones, the nearest one's beyond them). With ``half_width`` a
    candidate's moment is the share the screen would show, and the variance
    its edges would hide is added to the candidate's error as well: the
    design keeps away from the edges rather than rely on that share.
    Run in a loop (propose, measure the first, fit again) it is a sequential
    design with look-ahead.

    Args:
        map_of: Strengths ``(C,)`` -> first-order maps ``(C, 6, 6)`` (e.g.
            ``lambda k: forward.transfer_maps(k[:, None])``).
        maps: Maps of the settings measured so far ``(K, 6, 6)``.
        moments: Their measured ``(<xx>, <yy>)`` ``(K, 2)`` [m^2].
        candidates: Strengths to choose from ``(C,)``.
        n: How many to propose.
        planes: 0 (x), 1 (y) or both.
        relative_error: As in :func:`quad_scan_posterior`.
        floor: Absolute error floor [m^2].
        min_separation: Proposals closer than this to each other or to a
            ``measured`` strength are skipped (0: repeats allowed).
        joint: Choose the ``n`` strengths together (every combination, where
            there are at most :data:`JOINT_LIMIT`); else one at a time.
        measured: The strengths measured so far ``(K,)`` (for
            ``min_separation``).
        draws: Average the criterion over this many draws of the fit's
            posterior (0: at the fit itself), physical beams only: a design
            that stays good where the few measurements so far leave the beam
            uncertain. A fit that is no physical beam is replaced by such
            draws (:data:`UNPHYSICAL_DRAWS` at least).
        seed: Seed of those draws.
        kurtosis: Each measured image's beam kurtosis ``(K, 2)``
            (:func:`image_kurtosis`; interpolated over ``measured``, their
            mean without it); None: Gaussian.
        half_width: As in :func:`quad_scan_posterior`.

    Returns:
        The proposed strengths ``(n,)`` in order.
    """
    post = quad_scan_posterior(
        maps,
        moments,
        relative_error=relative_error,
        floor=floor,
        kurtosis=kurtosis,
        half_width=half_width,
    )
    th = post["theta"]
    r = float(post["relative_error"])
    cand = candidates.to(torch.float64)
    cm = map_of(cand).to(torch.float64)
    rows = []
    for a, b in ((0, 1), (2, 3)):
        r1, r2 = cm[:, a, a], cm[:, a, b]
        rows.append(torch.stack([r1**2, 2 * r1 * r2, r2**2], -1))
    a_c = torch.stack(rows)  # (2, C, 3)
    info = torch.linalg.pinv(post["cov"])  # (2, 3, 3)
    ths = _physical_draws(th, post["cov"], draws, seed)  # (D, 2, 3)
    pred = torch.einsum("pca,dpa->dpc", a_c, ths).abs()  # (D, 2, C)
    kc = None
    if kurtosis is not None:
        kt = kurtosis.to(torch.float64)
        if measured is None:
            kc = kt.mean(0)[:, None].expand(2, cand.shape[0])
        else:
            kc = torch.stack(
                [_interp(cand, measured.to(cand), kt[:, p]) for p in (0, 1)]
            )
        kc = kc[:, None, :]  # (2, 1, C)
    hw = None if half_width is None else torch.tensor(half_width, dtype=torch.float64)
    sd = _moment_sd(pred.transpose(0, 1), r, floor, kc, hw, _tails(kurtosis))
    sd = sd.transpose(0, 1)
    keep = _kept(pred.transpose(0, 1), hw, _tails(kurtosis)).transpose(0, 1)
    aw = a_c[None] * (keep / sd)[..., None]  # (D, 2, C, 3)
    add = torch.einsum("dpca,dpcb->dpcab", aw, aw)
    emit = (ths[..., 0] * ths[..., 2] - ths[..., 1] ** 2).clamp_min(1e-300).sqrt()
    g = torch.stack([ths[..., 2], -2 * ths[..., 1], ths[..., 0]], -1)
    g = g / (2 * emit[..., None])  # (D, 2, 3)

    def score_of(total: Tensor) -> Tensor:  # total (D, 2, *M, 3, 3) -> (*M,)
        c = torch.linalg.pinv(total)
        var = torch.einsum("dpa,dp...ab,dpb->dp...", g, c, g)
        var = var / emit.reshape(*emit.shape, *[1] * (var.ndim - 2)) ** 2
        return var[:, list(planes)].sum(1).mean(0)

    if measured is not None and min_separation > 0:
        far = (cand[:, None] - measured.to(cand)[None, :]).abs().amin(-1)
        keep = far > min_separation
        if int(keep.sum()) >= n:
            cand, add = cand[keep], add[:, :, keep]
    n_c = cand.shape[0]
    if joint and math.comb(n_c + n - 1, n) <= JOINT_LIMIT:
        combos = torch.combinations(torch.arange(n_c), n, with_replacement=True)
        combos = combos.reshape(-1, n)
        score = score_of(info[None, :, None] + add[:, :, combos].sum(3))
        if min_separation > 0 and n > 1:
            vals = cand[combos]
            gaps = (vals[:, :, None] - vals[:, None, :]).abs()
            gaps = torch.where(torch.eye(n, dtype=torch.bool), torch.inf, gaps)
            score = torch.where(gaps.amin((-2, -1)) <= min_separation, torch.inf, score)
        return cand[combos[int(score.argmin())]]
    taken: list[float] = []
    acc = info[None].expand(add.shape[0], -1, -1, -1)  # (D, 2, 3, 3)
    for _ in range(n):
        score = score_of(acc[:, :, None] + add)
        for t in taken:
            score = torch.where((cand - t).abs() <= min_separation, torch.inf, score)
        best = int(score.argmin())
        taken.append(float(cand[best]))
        acc = acc + add[:, :, best]
    return cand.new_tensor(taken)


def observability_line(
    maps: Sequence[Tensor],
    cov: Tensor,
    posterior: Tensor | None = None,
    relative_error: float = RELATIVE_ERROR,
) -> str:
    """:meth:`Observability.summary_line` of a reconstruction's scans and beam.

    Args:
        maps: Each scan's affine maps of its training settings ``(K_s, 7, 7)``.
        cov: The beam's covariance ``(6, 6)``; rows of coordinates a 4D
            reconstruction does not generate (zero) get
            :data:`LONGITUDINAL_RMS`, and the matrix is made positive definite.
        posterior: The reconstruction's moment posterior (``theta_cov``).
        relative_error: Relative error of each screen second moment.

    Returns:
        One line (``"observability: ..."``); ``"observability: not computed
        (...)"`` for a covariance that is not finite.
    """
    c = cov.to(torch.float64).clone()
    if not bool(torch.isfinite(c).all()) or c.shape != (6, 6):
        return "observability: not computed (the covariance is not finite)"
    for i in (4, 5):
        if not float(c[i, i]) > 0:
            c[i, :] = 0.0
            c[:, i] = 0.0
            c[i, i] = LONGITUDINAL_RMS[i - 4] ** 2
    d = c.diagonal().clamp_min(1e-300).sqrt()
    r = c / (d[:, None] * d[None, :])
    w, v = torch.linalg.eigh(0.5 * (r + r.T))
    if float(w.min()) < 1e-6:
        r = (v * w.clamp_min(1e-6)) @ v.T
        e = r.diagonal().sqrt()
        c = r / (e[:, None] * e[None, :]) * (d[:, None] * d[None, :])
    post = (
        posterior if posterior is not None and posterior.shape[0] in (10, 21) else None
    )
    return observability(
        list(maps), c, posterior=post, relative_error=relative_error
    ).summary_line()
