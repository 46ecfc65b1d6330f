"""Asking the images where the beam lies along the px-pz unseen direction.

The AWA 6D scans leave the trade of rms pz against the px-pz covariance unseen
in the screens' second moments, and :mod:`~diffaccel.reconstruction.unseen`
places every member at a stated prior point (zero px-pz partial correlation).
A beam whose px-pz partial correlation is not zero (+0.09 to +0.12 or -0.14
on synthetic beams with dispersion-like shapes) is placed 10-38 % off in z
emittance. The image *shapes* still carry that information: members refitted
at points along the direction fit the training images better off the prior
point for those beams.

:func:`probe_members` is that likelihood-ratio test (on by default in 6D,
``ReconstructionConfig.probe_unseen``; ``reconstruct --no-probe`` turns it
off): every placed member is refitted at the prior point and at
``t = +-step`` along its px-pz direction (correlation units, the covariance
plus ``t`` times the direction) with the covariance held (as
:func:`~diffaccel.reconstruction.pipeline.refit_members`; ``t = 0`` is that
refit), and its training-image KL distance computed on
:data:`PROBE_PARTICLES` quasi-random particles. The ensemble moves one step
only if the members' mean KL gain exceeds ``probe_gain``, and keeps stepping
while each further step gains as much (at most ``probe_points`` steps).

Only one side is probed (``probe_away``): the one away from where training
left the members (:func:`trained_points`). A refitted member fits better
toward that point whatever the truth (the shared 6D file's members are
trained 0.045 below the prior point, their refitted KL minimum lies 0.03
below it, the truth at it), so a gain on that side is no evidence; a gain on
the other side is, against the memory. Probed on both sides, beams the prior
places right gain as much as beams it places wrong, and no threshold
separates them.

What it finds, and what it cannot: a beam whose training lands on the far
side of the prior point from the truth moves toward the truth. A beam whose
training lands on the truth's side stays at the prior point. Training from
the maximum-entropy initial guess leaves nearly every beam on the wide-pz
side, so in practice the probe rarely moves a beam; the prior's share of the
result is stated by :mod:`~diffaccel.reconstruction.prior_dependence`.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from collections.abc import Callable, Sequence

import torch
from torch import Tensor

from diffaccel.dynamics.linalg import lstsq
from diffaccel.reconstruction.forward import ScreenForwardModel
from diffaccel.reconstruction.generator import BeamGenerator
from diffaccel.reconstruction.losses import image_distance
from diffaccel.reconstruction.training import (
    ReconstructionConfig,
    StepInfo,
)
from diffaccel.reconstruction.unseen import (
    PLACEMENT_PARTICLES,
    _fold,
    member_moments,
    place_configured,
    traded_pairs,
    transport_map,
    unseen_directions,
)

#: The traded correlation that :func:`probe_members` probes (px-pz).
PROBE_PAIR = (1, 5)
#: The 6D default step of the probe (``ReconstructionConfig.probe_unseen``;
#: correlation units).
PROBE_STEP = 0.05
#: Quasi-random particles of each probe's KL distance (16 384 scatter by
#: about 1e-3 between refitted members, above the gains it compares)...
PROBE_PARTICLES = 200_000
#: ... or this many times the training's particles where that is fewer.
PROBE_FACTOR = 16


def training_kl(
    state: dict,
    config: ReconstructionConfig,
    forwards: Sequence[ScreenForwardModel],
    measured: Sequence[Tensor],
    settings: Sequence[Tensor],
    maps: Sequence[Tensor],
    *,
    n_particles: int | None = None,
    seed: int = 0,
) -> float:
    """KL distance ``sum m log(m / s)`` of the measured training images to a
    member's, averaged over each scan's images and summed over the scans.

    ``n_particles`` quasi-random particles (default :data:`PROBE_PARTICLES`,
    or :data:`PROBE_FACTOR` times ``config.n_particles`` if fewer) drawn with
    ``seed`` (the same base points for every member and call). Images by the
    affine maps where they are exact (:meth:`ScreenForwardModel.linear_maps`),
    else by tracking.
    """
    gen = BeamGenerator(
        config.dims, width=config.width, depth=config.depth, scale=torch.ones(6)
    )
    gen.load_state_dict(state)
    gen.requires_grad_(False)
    with torch.no_grad():
        x = gen(
            n_particles or min(PROBE_PARTICLES, PROBE_FACTOR * config.n_particles),
            generator=torch.Generator().manual_seed(seed),
            quasi_random=True,
        )
        total = 0.0
        for fwd, meas, s, m in zip(forwards, measured, settings, maps, strict=True):
            fwd = fwd.to(x.device)
            linear = fwd.linear_maps(s, monochromatic=False, maps=m)
            pred = (
                fwd.images(x, s.to(x.device))
                if linear is None
                else fwd.images_linear(x, linear)
            )
            pred = pred / pred.sum((-2, -1), keepdim=True).clamp_min(1e-30)
            unit = meas.to(pred)
            unit = unit / unit.sum((-2, -1), keepdim=True)
            total += float(image_distance(pred, unit, "kl").mean())
    return total


@dataclasses.dataclass
class _Point:
    """The members refitted at one point ``t`` and their KL distances."""

    t: float
    states: list[dict]
    kl: list[float]


def probe_members(
    placed: Sequence[dict],
    refit: Callable[[int, dict, Tensor, Callable | None], dict],
    score: Callable[[dict], float],
    config: ReconstructionConfig,
    maps: Sequence[Tensor],
    *,
    progress: Callable[[int], Callable[[StepInfo], None] | None] = lambda k: None,
    trained: Sequence[dict] | None = None,
) -> tuple[list[dict], dict]:
    """Placed members refitted at the point along px-pz the images prefer.

    With ``config.probe_unseen = 0`` (4D, ``reconstruct --no-probe``), or
    where no unseen direction trades px-pz, every member is refitted where it was placed
    (:func:`~diffaccel.reconstruction.pipeline.refit_members`' plain refit)
    and nothing is scored.

    Args:
        placed: Members placed at the prior point
            (:func:`~diffaccel.reconstruction.unseen.place_members`).
        refit: ``refit(k, state, hold, callback)`` -> member ``k``'s state
            refitted from ``state`` with its covariance held at ``hold``.
        score: A refitted member's misfit to the training images
            (:func:`training_kl`).
        config: The run's settings (``probe_unseen`` the step, ``probe_gain``,
            ``probe_points``, the generator's size, the placement's prior).
        maps: Each scan's affine maps of its training settings ``(K_s, 7, 7)``.
        progress: ``progress(i)`` -> the callback of the ``i``-th refit.
        trained: The same members as training left them, before the
            placement. With ``config.probe_away`` the probe looks only on the
            side away from where they were (their mean ``t``), since a
            refitted member's KL favours that side whatever the truth.

    Returns:
        The refitted members placed again at the chosen point (the prior
        point plus ``t`` along each member's px-pz direction), and a record:
        ``t`` (correlation units), ``steps`` (each probed point's ``t``,
        members' KL and mean gain over the point it was compared with),
        ``not_positive_definite`` (the points not tried because some
        member's covariance there is not positive definite: a strongly
        chirped beam near its edge, e.g. +0.05 on a z-pz -0.95 chirp) and, with
        ``trained``, ``trained_t`` (each member's ``t`` before the
        placement).
    """
    moments, directions, bases, indices = [], [], [], []
    for state in placed:
        mu, cov = member_moments(
            state, 6, config.width, config.depth, PLACEMENT_PARTICLES, config.seed
        )
        v = unseen_directions(maps, cov)
        pairs = traded_pairs(v, cov)
        moments.append((mu, cov))
        index = pairs.index(PROBE_PAIR) if PROBE_PAIR in pairs else None
        bases.append(v)
        indices.append(index)
        directions.append(None if index is None else v[index])
    count = itertools.count()
    outside: list[float] = []  # points not tried: past a member's PD edge

    def at(t: float) -> _Point | None:
        targets = []
        for (_, cov), v in zip(moments, directions, strict=True):
            target = cov + t * v
            if float(torch.linalg.eigvalsh(target).min()) <= 0:
                outside.append(t)  # past a strongly chirped beam's edge
                return None
            # rounded to float32 as refit_members does (run-to-run bits)
            targets.append(target.float().double())
        states = []
        for k, (state, (mu, cov), target) in enumerate(
            zip(placed, moments, targets, strict=True)
        ):
            moved = state if t == 0 else _fold(state, transport_map(cov, target), mu)
            states.append(refit(k, moved, target, progress(next(count))))
        return _Point(t, states, [score(s) for s in states])

    def gain(a: _Point, b: _Point) -> float:
        return sum(x - y for x, y in zip(a.kl, b.kl, strict=True)) / len(a.kl)

    def record(p: _Point, ref: _Point) -> dict:
        return {"t": p.t, "kl": p.kl, "mean_gain": gain(ref, p)}

    if config.probe_unseen == 0 or any(v is None for v in directions):
        # no probe (or no px-pz trade): each member refitted where it was placed
        states = [
            refit(k, s, cov.float().double(), progress(k))
            for k, (s, (_, cov)) in enumerate(zip(placed, moments, strict=True))
        ]
        return place_configured(states, config, maps), {"t": 0.0, "steps": []}
    step = config.probe_unseen
    signs = (-1.0, 1.0)
    out: dict = {}
    if trained is not None:
        out["trained_t"] = trained_points(trained, moments, bases, indices, config)
        mean = sum(out["trained_t"]) / len(out["trained_t"])
        if config.probe_away and mean != 0:
            signs = (-math.copysign(1.0, mean),)
    best = at(0.0)
    steps = [record(best, best)]
    sides = [p for p in (at(s * step) for s in signs) if p is not None]
    steps += [record(p, best) for p in sides]
    trial = max(sides, key=lambda p: gain(best, p), default=None)
    while trial is not None and gain(best, trial) > config.probe_gain:
        best = trial
        n = round(abs(best.t) / step) + 1
        if n > config.probe_points:
            break
        trial = at(math.copysign(n * step, best.t))
        if trial is not None:
            steps.append(record(trial, best))
    shift = {PROBE_PAIR: best.t} if best.t else None
    return place_configured(best.states, config, maps, shift), {
        "t": best.t,
        "steps": steps,
        "not_positive_definite": outside,
        **out,
    }


def trained_points(
    trained: Sequence[dict],
    moments: Sequence[tuple[Tensor, Tensor]],
    bases: Sequence[Tensor],
    indices: Sequence[int],
    config: ReconstructionConfig,
) -> list[float]:
    """Each member's ``t`` along its px-pz direction before the placement.

    The trained covariance minus the placed one, regressed on the placed
    member's unseen directions (least squares over the 6x6 entries; the
    directions' correlation units), its px-pz coefficient.
    """
    out = []
    for state, (_, cov), v, i in zip(trained, moments, bases, indices, strict=True):
        _, own = member_moments(
            state, 6, config.width, config.depth, PLACEMENT_PARTICLES, config.seed
        )
        design = v.reshape(v.shape[0], -1).T
        coef = lstsq(design, (own - cov).reshape(-1, 1))
        out.append(float(coef[i]))
    return out
