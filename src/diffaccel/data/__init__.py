"""diffaccel.data: file formats, data containers, preprocessing, synthetic data.

Readers and writers validate what they touch and raise :class:`FormatError`
naming the offending field. Coordinates in memory are always Bmad
(x, px, y, py, z, pz); foreign conventions are converted at the file boundary.
"""

from typing import Any

from diffaccel.data.atomic import (
    atomic_write,
    atomic_write_bytes,
    atomic_write_json,
    atomic_write_text,
    clean_json,
)
from diffaccel.data.errors import FormatError, OptionError
from diffaccel.data.magnet_stream import (
    DEFAULT_INPUT_COLUMN,
    DEFAULT_OUTPUT_COLUMN,
    DEFAULT_RUN_COLUMN,
    DEFAULT_TIME_COLUMN,
    append_columns,
    iter_magnet_csv,
)
from diffaccel.data.result_folder import (
    ResultFolder,
    ResultFolderError,
    partial_folder,
    result_folder,
)

# name -> module of the torch/h5py parts, loaded on first use of the name (PEP
# 562), so that commands that only stream CSV files (``hysteresis predict``) do
# not import torch and h5py (~2 s)
_LAZY = {
    "MagnetHistory": "magnet_csv",
    "read_magnet_csv": "magnet_csv",
    "write_csv_atomic": "magnet_csv",
    "particle_group": "particles_io",
    "read_openpmd_particles": "particles_io",
    "write_openpmd_particles": "particles_io",
    "average_shots": "preprocessing",
    "center_centroids": "preprocessing",
    "crop_to_beam": "preprocessing",
    "median_filter": "preprocessing",
    "normalize": "preprocessing",
    "pool": "preprocessing",
    "subtract_background": "preprocessing",
    "threshold": "preprocessing",
    "FORMAT_VERSION": "quad_scan",
    "QuadScanDataset": "quad_scan",
    "read_quad_scan": "quad_scan",
    "write_quad_scan": "quad_scan",
    "SINGLE_SCAN_NAME": "scans",
    "MultiScanDataset": "scans",
    "parse_selection": "scans",
    "read_scans": "scans",
    "write_scans": "scans",
    "AWA6D_BEAMLINES": "synthetic",
    "DEFAULT_BEAMLINE": "synthetic",
    "PRESETS": "synthetic",
    "make_synthetic_awa6d": "synthetic",
    "make_synthetic_quad_scan": "synthetic",
    "make_synthetic_rf6d": "synthetic",
    "RF6D_BEAMLINES": "synthetic",
    "sample_preset_beam": "synthetic",
}


def __getattr__(name: str) -> Any:
    """Load the torch/h5py names on first access (PEP 562)."""
    if name not in _LAZY:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    from diffaccel.data import (
        magnet_csv,
        particles_io,
        preprocessing,
        quad_scan,
        scans,
        synthetic,
    )

    modules = {
        "magnet_csv": magnet_csv,
        "particles_io": particles_io,
        "preprocessing": preprocessing,
        "quad_scan": quad_scan,
        "scans": scans,
        "synthetic": synthetic,
    }
    value = getattr(modules[_LAZY[name]], name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))


__all__ = [
    "AWA6D_BEAMLINES",
    "DEFAULT_BEAMLINE",
    "DEFAULT_INPUT_COLUMN",
    "DEFAULT_OUTPUT_COLUMN",
    "DEFAULT_RUN_COLUMN",
    "DEFAULT_TIME_COLUMN",
    "FORMAT_VERSION",
    "PRESETS",
    "RF6D_BEAMLINES",
    "SINGLE_SCAN_NAME",
    "FormatError",
    "MagnetHistory",
    "MultiScanDataset",
    "OptionError",
    "QuadScanDataset",
    "ResultFolder",
    "ResultFolderError",
    "append_columns",
    "atomic_write",
    "atomic_write_bytes",
    "atomic_write_json",
    "atomic_write_text",
    "average_shots",
    "center_centroids",
    "clean_json",
    "crop_to_beam",
    "iter_magnet_csv",
    "make_synthetic_awa6d",
    "make_synthetic_quad_scan",
    "make_synthetic_rf6d",
    "median_filter",
    "normalize",
    "parse_selection",
    "partial_folder",
    "particle_group",
    "pool",
    "read_magnet_csv",
    "read_openpmd_particles",
    "read_quad_scan",
    "read_scans",
    "result_folder",
    "sample_preset_beam",
    "subtract_background",
    "threshold",
    "write_csv_atomic",
    "write_openpmd_particles",
    "write_quad_scan",
    "write_scans",
]
