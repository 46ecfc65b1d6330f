"""Sequential design of quadrupole scans against evenly spaced settings (no training).

For each of ``--seeds`` synthetic 4D beams (half Gaussian, half non-Gaussian:
a 10 % halo twice as wide, or a cubic x-px distortion; random Twiss
parameters) a quadrupole (0.1 m) + drift (2 m) scan is imaged on a 200 x 200
screen of 80 um pixels: each image is the cloud-in-cell deposit (1 pixel
point spread) of a fresh draw of ``--particles`` particles of the beam, so
images carry shot noise. The estimator is the classic rms fit (second moments
of the images, the point spread's variance removed, weighted least squares on
the transfer matrices, error scale fitted to the residuals;
``reconstruction.design.quad_scan_posterior``). Each image's error (the default
``--error-model image``): shot noise from its beam's kurtosis
(``image_kurtosis``) and a floor of a quarter pixel rms; the fit expects the
share of each variance the screen's edges (8 mm from the beam's centroid) let
through (``tail_variance`` for the plane's median kurtosis), and the design
also adds the hidden part to a candidate's error. ``--error-model moments``:
``r <xx> + floor`` alone.

- ``designed``: 3 settings (k1 = -5, 0, 5 1/m^2: the middle half of the
  range), then one at a time: ``propose_quad_settings`` proposes the remaining
  strengths jointly from the fit so far, the first is measured, and the fit
  is repeated, up to ``--designed`` settings.
- ``even``: ``--even`` settings evenly spaced over the same range.

Proposals keep 1 1/m^2 from each other and from measured strengths. Each beam
is scanned ``--repeats`` times with fresh images (noise realisations).
Reported per arm: the median over beams, realisations and planes of the
emittance's relative posterior std and of its absolute relative error against
the rms emittance of the beam's distribution (2 million particles). The last
line is the JSON summary.

Usage: ``python benchmarks/design.py [--seeds 10] [--first-seed 0] [--designed 5]
[--even 10] [--error-model image|moments]``
"""

from __future__ import annotations

import argparse
import itertools
import statistics

import torch
from _meta import add_store_flag, emit, git_commit

from diffaccel.dynamics import Beamline
from diffaccel.dynamics.images import cic_image
from diffaccel.reconstruction import ScreenForwardModel
from diffaccel.reconstruction.design import (
    image_kurtosis,
    propose_quad_settings,
    quad_scan_posterior,
)
from diffaccel.reconstruction.uncertainty import image_moments

K1 = (-10.0, 10.0)
SCREEN = (200, 200)
PIXEL = 80e-6
BLUR = 1.0  # pixels
#: Absolute error floor of a screen variance [m^2]: a quarter pixel rms.
FLOOR = (0.25 * PIXEL) ** 2
#: Distance from the beam's centroid (the screen's centre) to its edges [m].
HALF_WIDTH = (SCREEN[1] / 2 * PIXEL, SCREEN[0] / 2 * PIXEL)
#: Proposed strengths differ from each other and from measured ones by more
#: than this [1/m^2] (a twentieth of the range).
SEPARATION = 1.0


def beamline() -> ScreenForwardModel:
    line = Beamline.from_spec(
        [
            {"type": "Quadrupole", "name": "Q", "length": 0.1, "k1": 0.0},
            {"type": "Drift", "name": "D", "length": 2.0},
            {
                "type": "Screen",
                "name": "S",
                "shape": list(SCREEN),
                "pixel_size": [PIXEL, PIXEL],
                "center": [0.0, 0.0],
            },
        ]
    )
    return ScreenForwardModel(line, ["Q.k1"], 43.36e6, blur_pixels=BLUR)


def beam(seed: int, n: int, draw: int = 0) -> torch.Tensor:
    """``n`` particles of 4D beam ``seed`` (z = pz = 0), the ``draw``-th fresh
    draw of its distribution; odd seeds are non-Gaussian."""
    gp = torch.Generator().manual_seed(1000 + seed)  # the distribution
    g = torch.Generator().manual_seed(100_000 * (seed + 1) + draw)  # the draw
    out = torch.zeros(n, 6, dtype=torch.float64)
    for p in (0, 2):
        u = torch.rand(3, generator=gp, dtype=torch.float64)
        emit = 0.05e-6 + 0.05e-6 * float(u[0])
        beta = 3.0 + 7.0 * float(u[1])
        alpha = -1.5 + 3.0 * float(u[2])
        a = torch.randn(n, generator=g, dtype=torch.float64)
        b = torch.randn(n, generator=g, dtype=torch.float64)
        if seed % 2 == 1 and p == 0:  # halo: 10 % twice as wide
            wide = torch.rand(n, generator=g) < 0.1
            a = torch.where(wide, 2 * a, a)
            b = torch.where(wide, 2 * b, b)
        x = (emit * beta) ** 0.5 * a
        px = (emit / beta) ** 0.5 * (b - alpha * a)
        if seed % 2 == 1 and p == 2:  # cubic distortion
            px = px + 0.3 * (emit / beta) ** 0.5 * a**3
        out[:, p], out[:, p + 1] = x, px
    return out


class Imager:
    """Images of fresh draws of a beam at any k1, and their moments."""

    def __init__(self, fwd: ScreenForwardModel, seed: int, n: int, first_draw: int):
        self.fwd, self.seed, self.n, self.draw = fwd, seed, n, first_draw
        self.xs, self.ys = fwd.screen.pixel_centers(dtype=torch.float64)

    def moments(self, k1: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(<xx>, <yy>)`` (the point spread's variance removed) and the beam
        kurtosis in x and y of fresh images at ``k1``, each ``(K, 2)``."""
        maps = self.fwd.transfer_maps(k1[:, None])
        out, kurt = [], []
        for m in maps:
            self.draw += 1
            x = beam(self.seed, self.n, self.draw) @ m[:6, :6].T
            scr = self.fwd.screen
            img = cic_image(
                x[None, :, 0],
                x[None, :, 2],
                scr.shape,
                scr.pixel_size,
                scr.center,
                None,
                self.fwd._blur(),
            )
            mom = image_moments(img, self.xs, self.ys)[0]
            bx, by = self.fwd.blur_sigma()
            out.append(torch.stack([mom[2] - bx**2, mom[4] - by**2]))
            kurt.append(image_kurtosis(img, self.xs, self.ys, (bx, by))[0])
        return torch.stack(out), torch.stack(kurt)


def error_model(kind: str, kurtosis: torch.Tensor) -> dict:
    """Keyword arguments of the fit's per-image error model: ``image`` (each
    image's kurtosis, the screen's edges), ``moments`` (``r <xx> + floor``)."""
    if kind == "moments":
        return {}
    return {"kurtosis": kurtosis, "half_width": HALF_WIDTH}


def run_arm(imager: Imager, k1: torch.Tensor, r: float | None, kind: str) -> dict:
    fwd = imager.fwd
    maps = fwd.transfer_maps(k1[:, None])[:, :6, :6]
    mom, kurt = imager.moments(k1)
    return quad_scan_posterior(
        maps, mom, floor=FLOOR, relative_error=r, **error_model(kind, kurt)
    )


def headline(result: dict) -> dict[str, str]:
    """The docs page's figures: median emittance std and error of each arm."""
    figures = {}
    for arm, label in (
        ("designed", "sequentially designed quadrupole settings"),
        ("even", "evenly spaced settings"),
    ):
        a = result[arm]
        figures[f"{a['n_settings']} {label}: median emittance std / error"] = (
            f"{100 * a['median_emit_rel_std']:.2f} % / "
            f"{100 * a['median_emit_abs_rel_err']:.2f} %"
        )
    return figures


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument(
        "--first-seed",
        type=int,
        default=0,
        help="Beams FIRST ... FIRST + SEEDS - 1 (odd ones non-Gaussian).",
    )
    ap.add_argument("--designed", type=int, default=5)
    ap.add_argument("--even", type=int, default=10)
    ap.add_argument("--particles", type=int, default=20_000)
    ap.add_argument(
        "--draws",
        type=int,
        default=32,
        help="Posterior draws the design criterion is averaged over (0: the fit).",
    )
    ap.add_argument(
        "--repeats", type=int, default=10, help="Noise realisations per beam."
    )
    ap.add_argument(
        "--relative-error",
        type=float,
        default=None,
        help="Known relative error of each screen variance (default: fitted to "
        "the residuals).",
    )
    ap.add_argument(
        "--error-model",
        choices=("image", "moments"),
        default="image",
        help="Error of each screen variance in the fit and the design: image "
        "(shot noise from each image's kurtosis, the variance the screen's edges "
        "hide) or moments (r <xx> + floor alone).",
    )
    add_store_flag(ap)
    args = ap.parse_args()
    fwd = beamline()
    cand = torch.linspace(*K1, 61, dtype=torch.float64)

    def map_of(k: torch.Tensor) -> torch.Tensor:
        return fwd.transfer_maps(k[:, None])[:, :6, :6]

    arms: dict[str, dict[str, list]] = {
        a: {"std": [], "err": [], "k1": []} for a in ("designed", "even")
    }
    for seed, rep in itertools.product(
        range(args.first_seed, args.first_seed + args.seeds), range(args.repeats)
    ):
        c = torch.cov(beam(seed, 2_000_000, draw=-1).T)  # the distribution
        truth = torch.stack(
            [torch.linalg.det(c[p : p + 2, p : p + 2]).sqrt() for p in (0, 2)]
        )
        # designed: start, then one proposal at a time from the fit so far
        im = Imager(fwd, seed, args.particles, first_draw=100 * rep)
        k1 = torch.tensor([K1[0] / 2, 0.0, K1[1] / 2], dtype=torch.float64)
        mom, kurt = im.moments(k1)
        while k1.shape[0] < args.designed:
            nxt = propose_quad_settings(
                map_of,
                map_of(k1),
                mom,
                cand,
                n=args.designed - k1.shape[0],
                floor=FLOOR,
                relative_error=args.relative_error,
                measured=k1,
                min_separation=SEPARATION,
                draws=args.draws,
                **error_model(args.error_model, kurt),
            )
            nxt = nxt[:1]  # measure the first of the look-ahead proposal
            k1 = torch.cat([k1, nxt])
            m_new, k_new = im.moments(nxt)
            mom, kurt = torch.cat([mom, m_new]), torch.cat([kurt, k_new])
        post = quad_scan_posterior(
            map_of(k1),
            mom,
            floor=FLOOR,
            relative_error=args.relative_error,
            **error_model(args.error_model, kurt),
        )
        results = {"designed": (post, k1)}
        im = Imager(fwd, seed, args.particles, first_draw=10_000 + 100 * rep)
        ke = torch.linspace(*K1, args.even, dtype=torch.float64)
        results["even"] = (run_arm(im, ke, args.relative_error, args.error_model), ke)
        for arm, (p, ks) in results.items():
            arms[arm]["std"] += (p["emit_std"] / p["emit"]).tolist()
            arms[arm]["err"] += ((p["emit"] / truth - 1).abs()).tolist()
            arms[arm]["k1"].append([round(float(v), 2) for v in ks])
        print(
            f"seed {seed}.{rep}: designed k1 {arms['designed']['k1'][-1]}: std "
            f"{arms['designed']['std'][-2:]} err {arms['designed']['err'][-2:]}; even "
            f"std {arms['even']['std'][-2:]} err {arms['even']['err'][-2:]}"
        )
    out = {"name": "design", "commit": git_commit()}
    for arm, n in (("designed", args.designed), ("even", args.even)):
        out[arm] = {
            "n_settings": n,
            "median_emit_rel_std": statistics.median(arms[arm]["std"]),
            "median_emit_abs_rel_err": statistics.median(arms[arm]["err"]),
            "mean_emit_abs_rel_err": statistics.fmean(arms[arm]["err"]),
        }
    emit(out, headline=headline, store_result=args.store)


if __name__ == "__main__":
    main()
