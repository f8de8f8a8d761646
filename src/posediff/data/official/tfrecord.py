"""TFRecord files and ``tf.train.Example`` records, read (and written, for fixtures) without TensorFlow.

A TFRecord file is a sequence of records, each ``uint64 length``, ``uint32 masked_crc32c(length)``,
``length`` bytes of data, ``uint32 masked_crc32c(data)`` (little-endian). :class:`TFRecordFile` scans
the headers once (checking every length's checksum, so a truncated or overwritten file is refused
with its name and the record's offset) and then reads any record by index. The data checksum is
checked only on request (``verify=True``): it costs a pure-Python pass over every byte, and the
payloads posediff reads (PNG images) carry checksums of their own.

A ``tf.train.Example`` is a protocol buffer ``Example{Features features = 1}``,
``Features{map<string, Feature> feature = 1}``, ``Feature{oneof: BytesList bytes_list = 1;
FloatList float_list = 2; Int64List int64_list = 3}``; :func:`parse_example` decodes its wire format
into ``{name: list[bytes] | np.ndarray(float32) | np.ndarray(int64)}`` (packed and unpacked repeated
fields both), :func:`encode_example` is the inverse.
"""

from __future__ import annotations

import functools
import os
import struct
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np


class TFRecordError(ValueError):
    """A TFRecord file or an Example record posediff cannot read (one line, naming the file)."""


# ----------------------------------------------------------------------------- CRC-32C (Castagnoli)
@functools.cache
def _crc_table() -> tuple[int, ...]:
    table = []
    for n in range(256):
        c = n
        for _ in range(8):
            c = (c >> 1) ^ 0x82F63B78 if c & 1 else c >> 1
        table.append(c)
    return tuple(table)


def crc32c(data: bytes) -> int:
    """CRC-32C of ``data`` (pure Python: for headers and small records)."""
    table = _crc_table()
    crc = 0xFFFFFFFF
    for b in data:
        crc = table[(crc ^ b) & 0xFF] ^ (crc >> 8)
    return crc ^ 0xFFFFFFFF


def masked_crc32c(data: bytes) -> int:
    """TFRecord's masked checksum: ``((crc >> 15) | (crc << 17)) + 0xa282ead8`` (mod 2³²)."""
    crc = crc32c(data)
    return (((crc >> 15) | (crc << 17)) + 0xA282EAD8) & 0xFFFFFFFF


# ----------------------------------------------------------------------------- files
class TFRecordFile:
    """The records of one TFRecord file, by index (the headers scanned once, on construction)."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self._offsets: list[tuple[int, int]] = []  # (data offset, length)
        try:
            size = self.path.stat().st_size
            with self.path.open("rb") as f:
                pos = 0
                while pos < size:
                    header = f.read(12)
                    if len(header) < 12:
                        raise TFRecordError(f"{self.path}: truncated record header at byte {pos}")
                    (length,) = struct.unpack("<Q", header[:8])
                    (crc,) = struct.unpack("<I", header[8:])
                    if masked_crc32c(header[:8]) != crc:
                        raise TFRecordError(
                            f"{self.path}: not a TFRecord file (bad length checksum at byte {pos})"
                        )
                    if pos + 16 + length > size:
                        raise TFRecordError(
                            f"{self.path}: truncated record at byte {pos} ({length} bytes announced, "
                            f"{size - pos - 12} left)"
                        )
                    self._offsets.append((pos + 12, length))
                    pos += 16 + length
                    f.seek(pos)
        except OSError as e:
            raise TFRecordError(f"{self.path}: cannot read ({e.strerror or e})") from None

    def __len__(self) -> int:
        return len(self._offsets)

    def read(self, index: int, *, verify: bool = False) -> bytes:
        """The data of record ``index``; ``verify``: check its checksum too."""
        offset, length = self._offsets[index]
        with self.path.open("rb") as f:
            f.seek(offset)
            data = f.read(length + 4)
        if len(data) < length + 4:
            raise TFRecordError(f"{self.path}: record {index} was truncated after the file was opened")
        if verify and masked_crc32c(data[:length]) != struct.unpack("<I", data[length:])[0]:
            raise TFRecordError(f"{self.path}: record {index} is damaged (data checksum)")
        return data[:length]

    def __iter__(self) -> Iterator[bytes]:
        for i in range(len(self)):
            yield self.read(i)


def write_tfrecord(path: str | os.PathLike[str], records: Sequence[bytes]) -> None:
    """Write ``records`` as a TFRecord file (to a temporary name, then renamed)."""
    from ..._io import atomic_write_bytes

    out = bytearray()
    for data in records:
        header = struct.pack("<Q", len(data))
        out += (
            header + struct.pack("<I", masked_crc32c(header)) + data + struct.pack("<I", masked_crc32c(data))
        )
    atomic_write_bytes(Path(path), bytes(out))


# ----------------------------------------------------------------------------- protobuf wire format
def _varint(buf: bytes, pos: int) -> tuple[int, int]:
    result = shift = 0
    while True:
        if pos >= len(buf):
            raise TFRecordError("truncated varint")
        b = buf[pos]
        pos += 1
        result |= (b & 0x7F) << shift
        if not b & 0x80:
            return result, pos
        shift += 7
        if shift > 63:
            raise TFRecordError("varint longer than 64 bits")


def _fields(buf: bytes) -> Iterator[tuple[int, int, Any]]:
    """``(field number, wire type, value)`` of a message: varints as ints, length-delimited as bytes,
    fixed32 / fixed64 as their raw bytes."""
    pos = 0
    while pos < len(buf):
        key, pos = _varint(buf, pos)
        number, wire = key >> 3, key & 7
        if wire == 0:
            value, pos = _varint(buf, pos)
        elif wire == 2:
            n, pos = _varint(buf, pos)
            if pos + n > len(buf):
                raise TFRecordError("truncated length-delimited field")
            value, pos = buf[pos : pos + n], pos + n
        elif wire == 5:
            value, pos = buf[pos : pos + 4], pos + 4
        elif wire == 1:
            value, pos = buf[pos : pos + 8], pos + 8
        else:
            raise TFRecordError(f"unsupported protobuf wire type {wire}")
        if pos > len(buf):
            raise TFRecordError("truncated field")
        yield number, wire, value


def _signed64(v: int) -> int:
    return v - (1 << 64) if v >= 1 << 63 else v


def _feature(buf: bytes) -> list[bytes] | np.ndarray:
    for kind, _, lst in _fields(buf):
        if kind == 1:  # BytesList
            return [bytes(v) for n, w, v in _fields(lst) if n == 1 and w == 2]
        if kind == 2:  # FloatList: packed (wire 2) or one fixed32 per value (wire 5)
            parts = [np.frombuffer(v, "<f4") for n, w, v in _fields(lst) if n == 1 and w in (2, 5)]
            return np.concatenate(parts).astype(np.float32) if parts else np.zeros(0, np.float32)
        if kind == 3:  # Int64List: packed varints or one varint per value
            values: list[int] = []
            for n, w, v in _fields(lst):
                if n != 1:
                    continue
                if w == 0:
                    values.append(_signed64(v))
                elif w == 2:
                    p = 0
                    while p < len(v):
                        x, p = _varint(v, p)
                        values.append(_signed64(x))
            return np.asarray(values, dtype=np.int64)
    return []  # an empty Feature


def parse_example(buf: bytes) -> dict[str, list[bytes] | np.ndarray]:
    """The features of a serialised ``tf.train.Example`` (module docstring)."""
    out: dict[str, list[bytes] | np.ndarray] = {}
    for n, w, features in _fields(buf):
        if n != 1 or w != 2:
            continue
        for m, w2, entry in _fields(features):
            if m != 1 or w2 != 2:
                continue
            key, value = None, b""
            for k, w3, v in _fields(entry):
                if k == 1 and w3 == 2:
                    key = bytes(v).decode("utf-8")
                elif k == 2 and w3 == 2:
                    value = v
            if key is not None:
                out[key] = _feature(value)
    return out


def _key(number: int, wire: int) -> bytes:
    return _encode_varint((number << 3) | wire)


def _encode_varint(v: int) -> bytes:
    v &= (1 << 64) - 1
    out = bytearray()
    while True:
        b = v & 0x7F
        v >>= 7
        if v:
            out.append(b | 0x80)
        else:
            out.append(b)
            return bytes(out)


def _delimited(number: int, payload: bytes) -> bytes:
    return _key(number, 2) + _encode_varint(len(payload)) + payload


def encode_example(
    features: Mapping[str, bytes | Sequence[bytes] | np.ndarray | Sequence[float] | Sequence[int]],
) -> bytes:
    """A serialised ``tf.train.Example``: ``bytes`` (or a list of them) → BytesList, floating arrays →
    FloatList (float32, packed), integer arrays → Int64List (packed)."""
    entries = b""
    for name, value in features.items():
        if isinstance(value, bytes | bytearray):
            value = [bytes(value)]
        if isinstance(value, list) and value and isinstance(value[0], bytes | bytearray):
            lst = b"".join(_delimited(1, bytes(v)) for v in value)
            feature = _delimited(1, lst)
        else:
            arr = np.asarray(value)
            if np.issubdtype(arr.dtype, np.floating):
                lst = _delimited(1, arr.astype("<f4").tobytes())
                feature = _delimited(2, lst)
            else:
                lst = _delimited(1, b"".join(_encode_varint(int(x)) for x in arr.reshape(-1)))
                feature = _delimited(3, lst)
        entries += _delimited(1, _delimited(1, name.encode("utf-8")) + _delimited(2, feature))
    return _delimited(1, entries)


__all__ = [
    "TFRecordError",
    "TFRecordFile",
    "crc32c",
    "encode_example",
    "masked_crc32c",
    "parse_example",
    "write_tfrecord",
]
