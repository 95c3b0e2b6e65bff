"""The recording format's shared rules: one definition each, for the file reader and the live ingest.

:mod:`mkc_stream.io.recording` (the format's reader and writer) and :mod:`mkc_stream.ingest`
(decoders, recorder, gap counter) both apply them. They live here, in a module that imports
nothing, because the reader imports numpy and importing the ingest package must not (nor should
the reader pull in the ingest package): see docs/spec/recording.md for the format itself.
"""
from __future__ import annotations

#: the columns every recording has, in the order a recorder writes them
REQUIRED = ("t", "mx", "my", "mz")

#: a gap is a time step larger than GAP_FACTOR times the nominal period (the median positive step)
GAP_FACTOR = 2.5

#: with host receive times, steps shorter than this are delivery jitter, not gaps (seconds)
HOST_TIME_MIN_GAP_S = 0.1
