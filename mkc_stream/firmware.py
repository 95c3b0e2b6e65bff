"""Compatibility name for :mod:`mkc_stream.cport`, the bridge to the C99 reference port (firmware_ref/).

Kept so that existing imports keep working (``from mkc_stream.firmware import CMagCalibrator``, as
firmware_ref/README.md and scripts written before the split use): it re-exports every public name
of mkc_stream.cport, which holds the code (cport/toolchain.py: building; cport/bindings.py: the ctypes
bindings; cport/compare.py: the Python-vs-C cross-check). New code imports mkc_stream.cport.
The golden vectors' location and stored inputs moved out of the package, to tools/golden.py.
"""
from .cport import *  # noqa: F401,F403
from .cport import __all__  # noqa: F401
