"""The messages of a cut or damaged ROS 1 bag up to the damage.

rosbags opens a ROS 1 bag through the index records at its end, so a bag cut short (a recorder
that lost power) cannot be opened at all, although its records before the cut are intact. A ROS 1
bag (format 2.0, http://wiki.ros.org/Bags/Format/2.0) is "#ROSBAG V2.0\\n" then records, each
header length (uint32 LE), header (fields "name=value", each with a uint32 length; "op" the record
type), data length (uint32 LE), data. Chunk records hold the same records, stored uncompressed or
bz2- (or lz4-) compressed; connection records say which topic and type a connection id carries,
message-data records hold one serialised message. This reader walks them in order and keeps every
message up to the first record that is cut or does not parse; a cut compressed chunk is lost and
counted.

It offers what rosbag.py uses of rosbags' AnyReader: ``connections`` (topic, msgtype),
``messages(connections=)`` yielding (connection, receive time ns, raw) and ``deserialize``.
"""
from __future__ import annotations

import bz2
import struct

from .mcap_salvage import Connection, Truncated

MAGIC = b"#ROSBAG V2.0\n"
OP_MSG_DATA, OP_CHUNK, OP_CONNECTION = 0x02, 0x05, 0x07


def _fields(header) -> dict:
    out, p = {}, 0
    while p < len(header):
        (n,) = struct.unpack_from("<I", header, p)
        if p + 4 + n > len(header):
            raise Truncated
        name, _, value = bytes(header[p + 4:p + 4 + n]).partition(b"=")
        out[name.decode("ascii")] = value
        p += 4 + n
    return out


def _ros2_name(ros1_type: str) -> str:
    """sensor_msgs/MagneticField -> sensor_msgs/msg/MagneticField (rosbags' names)."""
    pkg, _, name = ros1_type.partition("/")
    return f"{pkg}/msg/{name}"


class Ros1SalvageReader:
    def __init__(self, path):
        self.path = path
        data = open(path, "rb").read()
        if not data.startswith(MAGIC):
            raise ValueError("not a ROS 1 bag (no '#ROSBAG V2.0' line)")
        self._conns: dict = {}              # id -> (topic, msgtype, definition)
        self._messages: list = []           # (conn id, time ns, data)
        self.stopped = ""
        self.lost_chunks = 0
        self._walk(memoryview(data)[len(MAGIC):])
        self._typestore = None

    def _walk(self, buf):
        p = 0
        while p < len(buf):
            try:
                if p + 4 > len(buf):
                    raise Truncated
                (hl,) = struct.unpack_from("<I", buf, p)
                if p + 8 + hl > len(buf):
                    raise Truncated
                h = _fields(buf[p + 4:p + 4 + hl])
                (dl,) = struct.unpack_from("<I", buf, p + 4 + hl)
                body = buf[p + 8 + hl:p + 8 + hl + dl]
                cut = p + 8 + hl + dl > len(buf)
                op = h.get("op", b"\xff")[0]
                if op == OP_CHUNK:
                    compression = h.get("compression", b"none").decode("ascii")
                    if compression == "none":
                        self._walk(body)        # a cut chunk: its records up to the cut
                    elif cut:
                        self.lost_chunks += 1
                        raise Truncated
                    else:
                        self._walk(memoryview(_decompress(compression, bytes(body))))
                elif cut:
                    raise Truncated
                elif op == OP_CONNECTION:
                    (cid,) = struct.unpack("<I", h["conn"])
                    d = _fields(body)
                    self._conns[cid] = (h["topic"].decode("utf-8"), _ros2_name(d["type"].decode("ascii")),
                                        d.get("message_definition", b"").decode("utf-8"))
                elif op == OP_MSG_DATA:
                    (cid,) = struct.unpack("<I", h["conn"])
                    sec, nsec = struct.unpack("<II", h["time"])
                    self._messages.append((cid, sec * 1_000_000_000 + nsec, bytes(body)))
            except (Truncated, struct.error, KeyError, UnicodeDecodeError, OSError, EOFError):
                self.stopped = self.stopped or f"cut or damaged record at byte {p}"
                return
            if cut:
                self.stopped = self.stopped or f"cut inside a chunk at byte {p}"
                return
            p += 8 + hl + dl

    @property
    def connections(self):
        return [Connection(cid, topic, msgtype) for cid, (topic, msgtype, _) in self._conns.items()]

    def messages(self, connections=()):
        ids = {c.id: c for c in connections}
        for cid, ns, data in self._messages:
            if cid in ids:
                yield ids[cid], ns, data

    def deserialize(self, raw, msgtype):
        if self._typestore is None:
            from rosbags.typesys import Stores, get_typestore

            self._typestore = get_typestore(Stores.ROS1_NOETIC)
        if msgtype not in self._typestore.types:            # a type the store lacks: from the bag's definition
            from rosbags.typesys import get_types_from_msg

            definition = next((d for _, t, d in self._conns.values() if t == msgtype), "")
            self._typestore.register(get_types_from_msg(definition, msgtype))
        return self._typestore.deserialize_ros1(raw, msgtype)

    def close(self):
        pass


def _decompress(compression, data):
    if compression == "bz2":
        return bz2.decompress(data)
    if compression == "lz4":
        try:
            import lz4.frame

            return lz4.frame.decompress(data)
        except ImportError:
            pass
    raise Truncated             # a compression this reader cannot undo: the chunk is lost, counted
