"""diffaccel.data: file formats, data containers, preprocessing, synthetic data.

Readers and writers validate what they touch and raise :class:`FormatError`
naming the offending field. Coordinates in memory are always Bmad
(x, px, y, py, z, pz); foreign conventions are converted at the file boundary.
"""

from diffaccel.data.errors import FormatError
from diffaccel.data.quad_scan import (
    FORMAT_VERSION,
    QuadScanDataset,
    read_quad_scan,
    write_quad_scan,
)

__all__ = [
    "FORMAT_VERSION",
    "FormatError",
    "QuadScanDataset",
    "read_quad_scan",
    "write_quad_scan",
]
