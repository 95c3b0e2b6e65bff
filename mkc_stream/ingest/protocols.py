"""Serial protocol names (``--protocol``) and the decoder each one makes."""
from __future__ import annotations

from .binary import BinaryDecoder
from .csvlines import CsvDecoder
from .decoder import Decoder
from .motioncal import MotionCalDecoder
from .vectornav import VectorNavDecoder

PROTOCOLS = {
    "motioncal": "PJRC MotionCal 'Raw:'/'Uni:' lines (the kind of the first sample line is kept)",
    "motioncal-raw": "MotionCal 'Raw:' integer lines only",
    "motioncal-uni": "MotionCal 'Uni:' float lines only",
    "csv": "recording-format CSV lines, header first (docs/spec/recording.md)",
    "binary": "the mkc binary frame (sync word, seq, device time, CRC-16; docs/live-and-recording.md)",
    "vectornav": "VectorNav $VNYMR / $VNIMU ASCII with checksum",
}
ALIASES = {"vn": "vectornav", "vnymr": "vectornav", "vnimu": "vectornav", "mkc": "binary"}


def make_decoder(protocol: str, columns: list[str] | None = None) -> Decoder:
    """A fresh decoder for ``protocol`` (a name of PROTOCOLS or an alias)."""
    name = ALIASES.get(protocol, protocol)
    if name == "motioncal":
        return MotionCalDecoder()
    if name in ("motioncal-raw", "motioncal-uni"):
        return MotionCalDecoder("Raw" if name.endswith("raw") else "Uni")
    if name == "csv":
        return CsvDecoder(columns)
    if name == "binary":
        return BinaryDecoder()
    if name == "vectornav":
        return VectorNavDecoder()
    raise ValueError(f"unknown protocol {protocol!r}; choose one of {', '.join(PROTOCOLS)}")
