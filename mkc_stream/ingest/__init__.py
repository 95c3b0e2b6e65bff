"""Live ingestion: one sample type, sources (serial, CAN, files), pure decoders, pacing, recording.

    from mkc_stream.ingest import open_source, Paced
    with open_source("/dev/ttyACM0", protocol="motioncal") as src:
        for sample in src: ...

Modules, one job each: :mod:`.sample` (the Sample type), :mod:`.source` (the source protocol),
:mod:`.opener` (``open_source``), :mod:`.pacing`, :mod:`.threaded`, :mod:`.serial_source`,
:mod:`.protocols` and the decoders :mod:`.motioncal`, :mod:`.csvlines`, :mod:`.binary`,
:mod:`.vectornav`; CAN: :mod:`.canframe`, :mod:`.candecoder`, :mod:`.dbc`, :mod:`.can_source`;
files: :mod:`.logs`; :mod:`.recorder`; :mod:`.live` (the run loop); :mod:`.emulator` (a device
emulator for tests without hardware). Importing this package does not import python-can,
pyserial or numba.
"""
from .opener import open_log, open_source
from .pacing import FakeClock, Paced
from .protocols import PROTOCOLS, make_decoder
from .sample import Sample
from .source import Source, SourceError, SourceLost

__all__ = ["FakeClock", "PROTOCOLS", "Paced", "Sample", "Source", "SourceError", "SourceLost",
           "make_decoder", "open_log", "open_source"]
