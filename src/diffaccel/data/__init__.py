"""diffaccel.data: file formats, data containers, preprocessing, synthetic data.

Readers and writers validate what they touch and raise :class:`FormatError`
naming the offending field. Coordinates in memory are always Bmad
(x, px, y, py, z, pz); foreign conventions are converted at the file boundary.
"""

from diffaccel.data.atomic import (
    atomic_write,
    atomic_write_bytes,
    atomic_write_json,
    atomic_write_text,
    clean_json,
)
from diffaccel.data.errors import FormatError
from diffaccel.data.magnet_csv import (
    DEFAULT_INPUT_COLUMN,
    DEFAULT_OUTPUT_COLUMN,
    MagnetHistory,
    append_columns,
    iter_magnet_csv,
    read_magnet_csv,
    write_csv_atomic,
)
from diffaccel.data.particles_io import read_openpmd_particles, write_openpmd_particles
from diffaccel.data.preprocessing import (
    average_shots,
    center_centroids,
    crop_to_beam,
    median_filter,
    normalize,
    pool,
    subtract_background,
    threshold,
)
from diffaccel.data.quad_scan import (
    FORMAT_VERSION,
    QuadScanDataset,
    read_quad_scan,
    write_quad_scan,
)
from diffaccel.data.result_folder import (
    ResultFolder,
    ResultFolderError,
    partial_folder,
    result_folder,
)
from diffaccel.data.scans import (
    SINGLE_SCAN_NAME,
    MultiScanDataset,
    parse_selection,
    read_scans,
    write_scans,
)
from diffaccel.data.synthetic import (
    AWA6D_BEAMLINES,
    DEFAULT_BEAMLINE,
    PRESETS,
    make_synthetic_awa6d,
    make_synthetic_quad_scan,
    sample_preset_beam,
)

__all__ = [
    "AWA6D_BEAMLINES",
    "DEFAULT_BEAMLINE",
    "DEFAULT_INPUT_COLUMN",
    "DEFAULT_OUTPUT_COLUMN",
    "FORMAT_VERSION",
    "PRESETS",
    "SINGLE_SCAN_NAME",
    "FormatError",
    "MagnetHistory",
    "MultiScanDataset",
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
    "median_filter",
    "normalize",
    "parse_selection",
    "partial_folder",
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
