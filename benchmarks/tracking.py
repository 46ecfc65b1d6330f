"""Benchmark: quad scan tracking + screen images, diffaccel vs cheetah.

Workload: N particles (float32), K quadrupole settings, Quadrupole(0.1 m) +
Drift(1 m) + 100 x 100 screen (1 mm pixels), images by cloud-in-cell and by
Gaussian KDE (bandwidth one pixel). Forward = track + image; forward+backward adds
``image.square().sum().backward()`` to the particles.

Variants: ``ours_*`` exact chromatic tracking, ``Beamline.screen_images`` (the
images straight from the tracked columns); ``ours_linear_*`` the same lattice
through ``Beamline.linearized`` (one affine 7x7 map per setting);
``cheetah_*`` cheetah 0.8.4 with its default linear quadrupole;
``cheetah_dkd_*`` cheetah's exact chromatic ``drift_kick_drift`` quadrupole.
``ratio_vs_cheetah_*`` compare like with like (linear vs linear);
``ratio_vs_cheetah_cic_exact`` exact vs exact; ``ratio_exact_vs_cheetah_linear_*``
our exact tracking against cheetah's linear one. Prints one JSON object on the
last line.

``--device cuda`` runs both codes on the GPU (the same particles, drawn on the
CPU and copied; every timing synchronises the device before and after, so it is
the whole forward(+backward)); ``peak_device_mb`` is torch's peak allocation.
``--fit-n 10000000`` then also runs our linear KDE and cloud-in-cell
forward+backward once with that many particles (x ``--k`` settings) and records
whether it fits in the device's memory and the peak (target: 10^7 x 20).

Usage: python benchmarks/tracking.py [--n 100000] [--k 20] [--repeats 5]
       [--cheetah-kde-repeats 1] [--no-cheetah-kde] [--threads T]
       [--device cpu|cuda] [--fit-n N]
"""

from __future__ import annotations

import argparse
import os
import platform
import resource
import statistics
import time
from collections.abc import Callable

import torch
from _meta import add_store_flag, emit, git_commit

from diffaccel.dynamics import Beamline

P0C = 43.36e6  # [eV]
SHAPE = (100, 100)
PIXEL = 1e-3  # [m]


def _beam(n: int, device: torch.device) -> torch.Tensor:
    g = torch.Generator().manual_seed(0)
    scale = torch.tensor([1e-3, 1e-4, 1e-3, 1e-4, 1e-3, 1e-3])
    return (torch.randn(n, 6, generator=g) * scale).to(device)


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _time_once(fn: Callable[[], object], device: torch.device) -> float:
    _sync(device)
    t0 = time.perf_counter()
    fn()
    _sync(device)
    return time.perf_counter() - t0


def _summary(times: list[float]) -> dict[str, float | list[float]]:
    return {
        "median_s": statistics.median(times),
        "min_s": min(times),
        "max_s": max(times),
        "all_s": times,
    }


def _ours(
    beam: torch.Tensor, k1: torch.Tensor, method: str, backward: bool, linear: bool
):
    spec = [
        {"type": "Quadrupole", "name": "Q1", "length": 0.1, "k1": 0.0},
        {"type": "Drift", "name": "D1", "length": 1.0},
        {"type": "Screen", "name": "SCREEN"},
    ]
    line = Beamline.from_spec(spec).with_screen("SCREEN", SHAPE, (PIXEL, PIXEL))
    line = line.to(beam.device)

    def run() -> torch.Tensor:
        p = beam.clone().requires_grad_(backward)
        if linear:
            lin = line.with_params({"Q1.k1": k1}).linearized(P0C)
            image = lin.screen_images(p, P0C, method=method)["SCREEN"]
        else:
            settings = k1.unsqueeze(-1)
            image = line.screen_images(p, P0C, settings, ["Q1.k1"], method=method)[
                "SCREEN"
            ]
        if backward:
            image.square().sum().backward()
        return image

    return run


def _cheetah(
    beam: torch.Tensor, k1: torch.Tensor, method: str, backward: bool, tracking: str
):
    import cheetah

    device = beam.device

    def run() -> torch.Tensor:
        p = torch.ones(beam.shape[0], 7, device=device)
        p[:, :6] = beam
        p.requires_grad_(backward)
        incoming = cheetah.ParticleBeam(
            p, energy=torch.tensor(P0C, device=device), device=device
        )
        screen = cheetah.Screen(
            resolution=(SHAPE[1], SHAPE[0]),
            pixel_size=torch.tensor((PIXEL, PIXEL), device=device),
            method=method,
            kde_bandwidth=torch.tensor(PIXEL, device=device),
            is_active=True,
            name="SCREEN",
            device=device,
        )
        segment = cheetah.Segment(
            [
                cheetah.Quadrupole(
                    length=torch.tensor(0.1),
                    k1=k1.clone(),
                    tracking_method=tracking,
                    name="Q1",
                ),
                cheetah.Drift(length=torch.tensor(1.0), name="D1"),
                screen,
            ]
        ).to(device)
        segment.track(incoming)
        image = screen.reading
        if backward:
            image.square().sum().backward()
        return image

    return run


def _fit(n: int, k1: torch.Tensor, device: torch.device) -> dict:
    """Our linear KDE and CIC forward+backward once with ``n`` particles."""
    out: dict = {"n_particles": n, "n_settings": int(k1.shape[0])}
    beam = _beam(n, device)
    for method in ("kde", "cic"):
        if device.type == "cuda":
            torch.cuda.empty_cache()
            torch.cuda.reset_peak_memory_stats(device)
        try:
            seconds = _time_once(_ours(beam, k1, method, True, True), device)
            entry: dict = {"fits": True, "seconds": seconds}
        except torch.OutOfMemoryError as err:
            entry = {"fits": False, "error": str(err).splitlines()[0]}
        if device.type == "cuda":
            entry["peak_device_mb"] = torch.cuda.max_memory_allocated(device) / 2**20
        out[method] = entry
    return out


def headline(result: dict) -> dict[str, str]:
    """The docs page's figures: forward+backward speed-ups vs cheetah, our time."""
    figures = {}
    acc = result["acceptance"]
    for key, label in (
        (
            "ratio_vs_cheetah_kde",
            "KDE images, forward+backward, speed-up vs cheetah 0.8.4 "
            f"(target >= {acc['min_ratio_kde']:g}x)",
        ),
        (
            "ratio_vs_cheetah_cic",
            f"cloud-in-cell images, speed-up vs cheetah (target >= "
            f"{acc['min_ratio_cic']:g}x)",
        ),
        (
            "ratio_vs_cheetah_cic_exact",
            "exact chromatic CIC vs cheetah drift_kick_drift",
        ),
    ):
        if result.get(key) is not None:
            figures[label] = f"{result[key]:.3g}x"
    n = result["n_particles"]
    size = f"{n // 1000}k" if n % 1000 == 0 else str(n)
    ours = result["timings"]["ours_linear_kde_forward_backward"]["median_s"]
    figures[
        f"diffaccel KDE, {size} particles x {result['n_settings']} settings, "
        "forward+backward"
    ] = f"{ours:.3g} s"
    return figures


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=100_000)
    parser.add_argument("--k", type=int, default=20)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--cheetah-kde-repeats", type=int, default=1)
    parser.add_argument("--cheetah-slow-repeats", type=int, default=3)
    parser.add_argument("--no-cheetah-kde", action="store_true")
    parser.add_argument("--no-cheetah", action="store_true")
    parser.add_argument(
        "--threads",
        type=int,
        default=None,
        help="torch intra-op threads (default: torch's choice). On a machine shared "
        "with other jobs, 1 avoids OpenMP oversubscription stalls.",
    )
    parser.add_argument("--device", default="cpu", help="cpu (default) or cuda")
    parser.add_argument(
        "--fit-n",
        type=int,
        default=0,
        help="also run ours once with this many particles (does it fit?)",
    )
    add_store_flag(parser)
    args = parser.parse_args()
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise SystemExit("--device cuda: torch sees no CUDA device here")

    beam = _beam(args.n, device)
    k1 = torch.linspace(-25.0, 15.0, args.k, device=device)
    timings: dict[str, dict] = {}
    # warm-up (first-call allocations)
    for method in ("cic", "kde"):
        _ours(beam, k1, method, True, False)()
        _ours(beam, k1, method, True, True)()
    # all variants of one measurement alternate within each repeat, so that they
    # see the same machine load
    for method, theirs in (("cic", "cloud-in-cell"), ("kde", "kde")):
        for backward in (False, True):
            tag = "forward_backward" if backward else "forward"
            runs = {
                f"ours_{method}_{tag}": (_ours(beam, k1, method, backward, False), 0),
                f"ours_linear_{method}_{tag}": (
                    _ours(beam, k1, method, backward, True),
                    0,
                ),
            }
            if not args.no_cheetah:
                if method == "cic":
                    runs[f"cheetah_{method}_{tag}"] = (
                        _cheetah(beam, k1, theirs, backward, "linear"),
                        args.repeats,
                    )
                    runs[f"cheetah_dkd_{method}_{tag}"] = (
                        _cheetah(beam, k1, theirs, backward, "drift_kick_drift"),
                        args.cheetah_slow_repeats,
                    )
                elif not args.no_cheetah_kde:
                    runs[f"cheetah_{method}_{tag}"] = (
                        _cheetah(beam, k1, theirs, backward, "linear"),
                        args.cheetah_kde_repeats,
                    )
            samples: dict[str, list[float]] = {key: [] for key in runs}
            for rep in range(args.repeats):
                for key, (run, limit) in runs.items():
                    if limit and rep >= limit:
                        continue
                    samples[key].append(_time_once(run, device))
            for key, values in samples.items():
                timings[key] = _summary(values)

    def ratio(theirs: str, ours: str) -> float | None:
        a = timings.get(f"{theirs}_forward_backward")
        b = timings.get(f"{ours}_forward_backward")
        if a is None or b is None:
            return None
        return a["median_s"] / b["median_s"]

    result = {
        "name": "tracking",
        "workload": "Quadrupole(0.1 m) + Drift(1 m) + Screen(100 x 100, 1 mm)",
        "n_particles": args.n,
        "n_settings": args.k,
        "image_shape": list(SHAPE),
        "dtype": "float32",
        "device": str(device),
        "threads": torch.get_num_threads(),
        "repeats": args.repeats,
        "cheetah_kde_repeats": args.cheetah_kde_repeats,
        "torch": torch.__version__,
        "python": platform.python_version(),
        "git_commit": git_commit(),
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "timings": timings,
        # like for like: linear tracking on both sides (cheetah's default)
        "ratio_vs_cheetah_cic": ratio("cheetah_cic", "ours_linear_cic"),
        "ratio_vs_cheetah_kde": ratio("cheetah_kde", "ours_linear_kde"),
        # like for like: exact chromatic tracking on both sides
        "ratio_vs_cheetah_cic_exact": ratio("cheetah_dkd_cic", "ours_cic"),
        # conservative: our exact tracking against cheetah's linear tracking
        "ratio_exact_vs_cheetah_linear_cic": ratio("cheetah_cic", "ours_cic"),
        "ratio_exact_vs_cheetah_linear_kde": ratio("cheetah_kde", "ours_kde"),
        "acceptance": {"min_ratio_kde": 100.0, "min_ratio_cic": 5.0},
        "load_avg_1min": os.getloadavg()[0],
    }
    if device.type == "cuda":
        result["device_name"] = torch.cuda.get_device_name(device)
        result["peak_device_mb"] = torch.cuda.max_memory_allocated(device) / 2**20
    if args.fit_n:
        result["fit"] = _fit(args.fit_n, k1, device)
    # targets: KDE >= 100x and cloud-in-cell >= 5x cheetah (like for like,
    # forward+backward), in every run: run the script several times
    kde, cic = result["ratio_vs_cheetah_kde"], result["ratio_vs_cheetah_cic"]
    result["met"] = None if kde is None or cic is None else kde >= 100 and cic >= 5
    emit(result, headline=headline, store_result=args.store)


if __name__ == "__main__":
    main()
