"""The messages of a cut or damaged MCAP file (a ROS 2 bag's storage) up to the damage.

rosbags opens an MCAP file through its summary at the end, so a file cut short (a logger that lost
power, a copy that stopped) cannot be opened at all. The records before the cut are still there:
MCAP is a sequence of records, opcode (1 byte) + length (uint64 LE) + content
(https://mcap.dev/spec), and messages sit at the top level or in Chunk records whose content is the
same sequence of records, stored uncompressed or compressed. This reader walks them in order:
Schema and Channel records say what each channel carries, Message records are kept until the first
record that is cut or does not parse. A compressed chunk is decompressed with zstandard or lz4
when installed; a cut compressed chunk cannot be read and is counted with its message range.

It offers what rosbag.py uses of rosbags' AnyReader: ``connections`` (topic, msgtype),
``messages(connections=)`` yielding (connection, log time ns, raw CDR) and ``deserialize``.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass

MAGIC = b"\x89MCAP0\r\n"
OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK, OP_DATA_END = 0x03, 0x04, 0x05, 0x06, 0x0F


class Truncated(Exception):
    """A record runs past the end of the data."""


@dataclass(frozen=True)
class Connection:
    id: int
    topic: str
    msgtype: str


def _string(buf, p):
    (n,) = struct.unpack_from("<I", buf, p)
    if p + 4 + n > len(buf):
        raise Truncated
    return bytes(buf[p + 4:p + 4 + n]).decode("utf-8"), p + 4 + n


class McapSalvageReader:
    def __init__(self, path):
        self.path = path
        data = open(path, "rb").read()
        if not data.startswith(MAGIC):
            raise ValueError("not an MCAP file (no magic bytes)")
        self._schemas: dict = {}
        self._channels: dict = {}
        self._messages: list = []            # (channel id, log_time ns, data)
        #: what stopped the walk ("" when the data end record was reached), and what was lost
        self.stopped = ""
        self.lost_chunks = 0
        self._walk(memoryview(data)[len(MAGIC):], top=True)
        self._typestore = None

    # -- the walk --------------------------------------------------------------------------
    def _walk(self, buf, top):
        p = 0
        while p < len(buf):
            if p + 9 > len(buf):
                self.stopped = self.stopped or f"cut inside a record header at byte {p}"
                return
            op = buf[p]
            (n,) = struct.unpack_from("<Q", buf, p + 1)
            body = buf[p + 9:p + 9 + n]
            cut = p + 9 + n > len(buf)
            try:
                if op == OP_CHUNK:
                    self._chunk(body, cut)
                elif cut:
                    raise Truncated
                elif op == OP_SCHEMA:
                    (sid,) = struct.unpack_from("<H", body, 0)
                    name, _ = _string(body, 2)
                    self._schemas[sid] = name
                elif op == OP_CHANNEL:
                    cid, sid = struct.unpack_from("<HH", body, 0)
                    topic, _ = _string(body, 4)
                    self._channels[cid] = (topic, sid)
                elif op == OP_MESSAGE:
                    cid, _seq, log_time, _pub = struct.unpack_from("<HIQQ", body, 0)
                    self._messages.append((cid, log_time, bytes(body[22:])))
                elif op == OP_DATA_END and top:
                    return
            except (Truncated, struct.error, UnicodeDecodeError):
                self.stopped = self.stopped or f"cut or damaged record (opcode {op:#04x}) at byte {p}"
                return
            if cut:
                self.stopped = self.stopped or f"cut inside a chunk at byte {p}"
                return
            p += 9 + n

    def _chunk(self, body, cut):
        start, end, _size, _crc = struct.unpack_from("<QQQI", body, 0)
        compression, q = _string(body, 28)
        (n,) = struct.unpack_from("<Q", body, q)
        records = body[q + 8:q + 8 + n]
        if compression == "":
            self._walk(records, top=False)          # a cut chunk: its records up to the cut
            return
        if cut or q + 8 + n > len(body):
            self.lost_chunks += 1
            raise Truncated
        self._walk(memoryview(_decompress(compression, bytes(records))), top=False)

    # -- what rosbag.py uses ---------------------------------------------------------------
    @property
    def connections(self):
        return [Connection(cid, topic, self._schemas.get(sid, "")) for cid, (topic, sid) in self._channels.items()]

    def messages(self, connections=()):
        ids = {c.id: c for c in connections}
        for cid, log_time, data in self._messages:
            if cid in ids:
                yield ids[cid], log_time, data

    def deserialize(self, raw, msgtype):
        if self._typestore is None:
            from rosbags.typesys import Stores, get_typestore

            self._typestore = get_typestore(Stores.LATEST)
        return self._typestore.deserialize_cdr(raw, msgtype)

    def close(self):
        pass


def _decompress(compression, data):
    try:
        if compression == "zstd":
            import zstandard

            return zstandard.ZstdDecompressor().decompress(data)
        if compression == "lz4":
            import lz4.frame

            return lz4.frame.decompress(data)
    except ImportError:
        pass
    raise Truncated              # a compression this reader cannot undo: the chunk is lost, counted
