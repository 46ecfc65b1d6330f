"""Several scans of one beam (quad-scan format version 2): container, I/O, selections.

A measurement may observe one beam through several beamline states or screens,
e.g. a quadrupole scan with a transverse deflecting cavity off and on, seen on a
screen straight ahead (dipole off) and on one after a spectrometer dipole
(dipole on). Each such scan is a :class:`~diffaccel.data.QuadScanDataset` (its
own beamline ending at one screen, settings, images, calibration); all start at
the same reference point, where the beam is reconstructed.
:class:`MultiScanDataset` holds them by name. A version-1 file is read as one
scan named :data:`SINGLE_SCAN_NAME`.
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import h5py
import torch
from torch import Tensor

from diffaccel.data.atomic import atomic_write
from diffaccel.data.errors import FormatError
from diffaccel.data.quad_scan import (
    QuadScanDataset,
    _check_preprocessing,
    _validate,
    read_file_scans,
    write_root,
    write_scan,
)

__all__ = [
    "MULTI_SCAN_VERSION",
    "SINGLE_SCAN_NAME",
    "MultiScanDataset",
    "parse_selection",
    "read_scans",
    "write_scans",
]

MULTI_SCAN_VERSION = 2
#: Name of the scan of a version-1 file (or of a single ``QuadScanDataset``).
SINGLE_SCAN_NAME = "scan"
_NAME = re.compile(r"^[A-Za-z0-9_.+-]+$")


@dataclass(frozen=True, eq=False)
class MultiScanDataset:
    """Scans of one beam, by name, each with its own beamline, screen and settings.

    Args:
        scans: ``{name: QuadScanDataset}`` in file order
    (creation order where the file tracks it, else by name). Names are non-empty and
            use letters, digits and ``_ . + -``. All scans share ``p0c``,
            ``species`` and ``ground_truth``.
        format_version: Version of the file the scans were read from (1 or 2);
            writers use it to write the same version back.
        metadata: Beam-level provenance (the root ``metadata`` attribute).

    Shapes:
        Scan ``s`` has images ``(K_s, S_s, H_s, W_s)`` and settings
        ``(K_s, P_s)``; any of these may differ between scans.

    Raises:
        FormatError: naming the scan for an empty container, a bad name, or
            scans that disagree on ``p0c``, ``species`` or ``ground_truth``.

    Example:
        >>> from diffaccel.data import make_synthetic_quad_scan
        >>> one = make_synthetic_quad_scan(
        ...     "gaussian", n_particles=100, n_settings=3, screen_shape=(8, 8))
        >>> ms = MultiScanDataset({"a": one, "b": one.subset([0, 1])})
        >>> ms.names, ms.n_images
        (['a', 'b'], 5)
        >>> parse_selection("odd", ms)
        {'a': [1], 'b': [1]}
    """

    scans: dict[str, QuadScanDataset]
    format_version: int = MULTI_SCAN_VERSION
    metadata: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        scans = dict(self.scans)
        object.__setattr__(self, "scans", scans)
        if not scans:
            raise FormatError("scans: expected at least one scan; found none")
        if self.format_version not in (1, MULTI_SCAN_VERSION):
            raise FormatError(
                f"format_version: expected 1 or 2; found {self.format_version!r}"
            )
        if self.format_version == 1 and len(scans) != 1:
            raise FormatError(
                f"format_version 1 holds exactly one scan; found {len(scans)}"
            )
        first_name, first = next(iter(scans.items()))
        for name, scan in scans.items():
            if not isinstance(name, str) or not _NAME.match(name):
                raise FormatError(
                    f"scans: scan name {name!r} must be non-empty and use letters, "
                    "digits and _ . + - only"
                )
            if not isinstance(scan, QuadScanDataset):
                raise FormatError(
                    f"scan {name!r}: expected a QuadScanDataset; found "
                    f"{type(scan).__name__}"
                )
            if scan.p0c != first.p0c or scan.species != first.species:
                raise FormatError(
                    f"scan {name!r}: p0c = {scan.p0c} eV, species {scan.species!r}; "
                    f"scan {first_name!r} has {first.p0c} eV, {first.species!r} "
                    "(all scans observe one beam)"
                )
            a, b = scan.ground_truth, first.ground_truth
            same = (a is None and b is None) or (
                a is not None
                and b is not None
                and (a is b or (a.shape == b.shape and torch.equal(a, b)))
            )
            if not same:
                raise FormatError(
                    f"scan {name!r}: ground_truth differs from scan {first_name!r}'s "
                    "(all scans observe one beam)"
                )
        if not isinstance(self.metadata, dict):
            raise FormatError(f"metadata: expected a dict; found {type(self.metadata)}")
        _check_preprocessing(self.metadata, "metadata")

    @classmethod
    def from_scan(
        cls, scan: QuadScanDataset, name: str = SINGLE_SCAN_NAME
    ) -> MultiScanDataset:
        """One scan as a container (``format_version`` 1, like its file)."""
        return cls({name: scan}, format_version=1, metadata=dict(scan.metadata))

    # ------------------------------------------------------------------ views
    @property
    def names(self) -> list[str]:
        """Scan names in order."""
        return list(self.scans)

    def __iter__(self) -> Iterator[tuple[str, QuadScanDataset]]:
        return iter(self.scans.items())

    def __len__(self) -> int:
        return len(self.scans)

    def __getitem__(self, name: str) -> QuadScanDataset:
        try:
            return self.scans[name]
        except KeyError:
            raise KeyError(f"no scan named {name!r}; scans are {self.names}") from None

    @property
    def p0c(self) -> float:
        """Reference momentum times c [eV]."""
        return next(iter(self.scans.values())).p0c

    @property
    def species(self) -> str:
        """Particle species."""
        return next(iter(self.scans.values())).species

    @property
    def ground_truth(self) -> Tensor | None:
        """Known initial particles ``(N, 6)`` (Bmad), or None."""
        return next(iter(self.scans.values())).ground_truth

    @property
    def n_images(self) -> int:
        """Settings summed over all scans."""
        return sum(s.n_settings for s in self.scans.values())

    def subset(self, selection: Mapping[str, Sequence[int]]) -> MultiScanDataset:
        """The scans restricted to some settings; scans not named are dropped.

        Args:
            selection: ``{scan name: setting indices}`` as from
                :func:`parse_selection`; an empty list drops the scan.

        Raises:
            KeyError: for an unknown scan name.
            IndexError: for an index outside a scan's settings.
        """
        out = {}
        for name, idx in selection.items():
            scan = self[name]
            if len(idx):
                out[name] = scan.subset(list(idx))
        if not out:
            raise ValueError("subset: no setting selected in any scan")
        version = self.format_version if len(out) == 1 else MULTI_SCAN_VERSION
        return MultiScanDataset(out, version, dict(self.metadata))


def _indices(text: str, k: int, where: str) -> list[int]:
    t = text.strip().lower()
    if t == "all":
        return list(range(k))
    if t == "even":
        return list(range(0, k, 2))
    if t == "odd":
        return list(range(1, k, 2))
    if t == "none":
        return []
    try:
        idx = [int(v) for v in t.split(",") if v.strip()]
    except ValueError as err:
        raise ValueError(
            f"{where}: expected all, even, odd, none or a comma-separated list of "
            f"setting indices; got {text!r}"
        ) from err
    bad = [i for i in idx if not 0 <= i < k]
    if not idx or bad or len(set(idx)) != len(idx):
        raise ValueError(
            f"{where}: indices must be distinct and in [0, {k}); got {text!r}"
        )
    return idx


def parse_selection(text: str, dataset: MultiScanDataset) -> dict[str, list[int]]:
    """Training settings of every scan from a short text.

    Forms:
        * ``all`` | ``even`` | ``odd`` | ``0,2,4``: the same rule in every scan
          (listed indices must exist in every scan);
        * ``NAME:RULE;NAME:RULE``, e.g. ``dipole_off:0,1,4,5;dipole_on:even``:
          a rule per scan (``all``, ``even``, ``odd``, ``none`` or a list); scans
          not named are not trained on (all their settings are held out).

    Returns:
        ``{scan name: sorted setting indices}`` for every scan (possibly empty).

    Raises:
        ValueError: naming the scan and rule for an unknown scan, a scan named
            twice, a malformed rule, an index out of range, or a selection with
            no setting at all.
    """
    if not isinstance(text, str) or not text.strip():
        raise ValueError("train indices: expected a rule such as all, even or 0,2,4")
    out: dict[str, list[int]]
    if ":" in text:
        out = {name: [] for name in dataset.names}
        named: set[str] = set()
        for part in (p for p in text.split(";") if p.strip()):
            name, sep, rule = part.partition(":")
            name = name.strip()
            if not sep or name not in dataset.scans:
                raise ValueError(
                    f"train indices: {part.strip()!r} must be SCAN:RULE with SCAN "
                    f"one of {dataset.names}"
                )
            if name in named:
                raise ValueError(
                    f"train indices: scan {name!r} is named twice in {text!r}; give "
                    "one rule per scan"
                )
            named.add(name)
            k = dataset[name].n_settings
            out[name] = _indices(rule, k, f"train indices of scan {name!r}")
    else:
        out = {
            name: _indices(text, scan.n_settings, f"train indices of scan {name!r}")
            for name, scan in dataset
        }
    if not any(out.values()):
        raise ValueError(f"train indices {text!r} select no setting in any scan")
    return {name: sorted(idx) for name, idx in out.items()}


def read_scans(path: str | os.PathLike) -> MultiScanDataset:
    """Read a quad-scan file of any version as scans of one beam.

    Version 1 gives one scan named :data:`SINGLE_SCAN_NAME`; version 2 one scan
    per group of ``/scans``, in file order
    (creation order where the file tracks it, else by name).

    Raises:
        FileNotFoundError: if ``path`` does not exist.
        FormatError: naming the file, the scan and the field that is missing or
            invalid.
    """
    version, scans, metadata = read_file_scans(path, single_name=SINGLE_SCAN_NAME)
    try:
        return MultiScanDataset(scans, version, metadata)
    except FormatError as err:
        raise FormatError(f"{path}: {err}") from err


def write_scans(
    dataset: MultiScanDataset,
    path: str | os.PathLike,
    *,
    overwrite: bool = False,
    format_version: int | None = None,
) -> Path:
    """Write scans as a quad-scan file, atomically.

    Args:
        dataset: The scans.
        path: Destination file.
        overwrite: Replace an existing file.
        format_version: 2 (``/scans/<name>/...``) or 1 (one scan at the root);
            default ``dataset.format_version``.

    Returns:
        The path written.

    Raises:
        FileExistsError: if ``path`` exists and ``overwrite`` is false.
        FormatError: version 1 with several scans, or an invalid scan (named).
    """
    if not isinstance(dataset, MultiScanDataset):
        raise TypeError(f"dataset: expected a MultiScanDataset; got {type(dataset)}")
    version = dataset.format_version if format_version is None else format_version
    if version not in (1, MULTI_SCAN_VERSION):
        raise FormatError(f"format_version: expected 1 or 2; found {version!r}")
    if version == 1 and len(dataset) != 1:
        raise FormatError(
            f"format_version 1 holds one scan; the dataset has {len(dataset)} "
            f"({dataset.names}); write version 2"
        )
    for name, scan in dataset:
        try:
            _validate(scan)
        except FormatError as err:
            raise FormatError(f"scan {name!r}: {err}") from err
    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(
            f"{path} exists; pass overwrite=True (CLI: --force) to replace it"
        )
    path.parent.mkdir(parents=True, exist_ok=True)
    first = next(iter(dataset.scans.values()))
    root: Any = first
    if version == MULTI_SCAN_VERSION:
        # beam-level metadata at the root; per-scan preprocessing steps differ
        root = replace(first, metadata=dict(dataset.metadata))

    def _write(tmp: Path) -> None:
        with h5py.File(tmp, "w") as h5:
            write_root(h5, root, version)
            if version == 1:
                write_scan(h5, first)
            else:
                group = h5.create_group("scans", track_order=True)
                for name, scan in dataset:
                    write_scan(group.create_group(name), scan)

    return atomic_write(path, _write)
