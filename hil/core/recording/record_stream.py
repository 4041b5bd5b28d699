"""The byte stream from a session's loop process to its writer process.

The loop process batches records and writes each batch as one frame to a pipe: a 4-byte
little-endian length, then the pickled list of records. A record is either a message,
``(channel_key, log_time_ns, message)``, or a control tuple whose first item is a string:

* ``("topic", key, name, json_schema, encoding)``: register a channel (``json`` or ``cdr``);
* ``("metadata", name, {str: str})`` and ``("attachment", name, data, media_type, t_ns)``;
* ``("drops", t_ns, {topic: total_dropped})``: the loop dropped messages (backlog full);
* ``("row", key, (value, ...))``: a row of a column topic's next message
  (:class:`~hil.core.recording.recorder.ColumnTopic`), a value for each column;
* ``("message", key, log_time_ns, fields, column_names)``: that message, ``fields`` and the
  rows since the last one as the columns named (``fields`` None: a row was lost, the rows
  are let go);
* ``("close",)``: the session ended normally; write the summary and stop.

The stream is ordered, so a topic is always registered before its first message. When the
loop process dies, the pipe's end of file tells the writer to finish the file all the same.

A numpy array in a message travels as its raw bytes, dtype and shape: numpy's own pickling
(``__reduce_ex__``) costs 2-3 times as much, and the loop pays it every tick.
"""

from __future__ import annotations

import copyreg
import io
import pickle
import struct
from collections.abc import Iterator
from functools import cache
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import numpy as np

_LENGTH = struct.Struct("<I")
MAX_FRAME_BYTES = 1 << 30


def array_from_bytes(data: bytes, dtype: str, shape: tuple[int, ...]) -> np.ndarray:
    """The array :func:`_reduce_array` took apart (read-only: it shares ``data``)."""
    import numpy as np  # here: the writer process starts without numpy until an array comes

    return np.frombuffer(data, dtype=dtype).reshape(shape)


def _reduce_array(array: np.ndarray) -> str | tuple[Any, ...]:
    if array.dtype.hasobject:  # pointers, not data: numpy's own way
        return array.__reduce_ex__(pickle.HIGHEST_PROTOCOL)
    return array_from_bytes, (array.tobytes(), array.dtype.str, array.shape)


@cache
def _dispatch_table() -> dict[type, Any]:
    """How the records' objects are pickled: plain numpy arrays (exact type) as bytes."""
    import numpy as np

    return {**copyreg.dispatch_table, np.ndarray: _reduce_array}


def encode_frame(records: list[Any]) -> bytes:
    """One frame holding ``records`` in order."""
    buffer = io.BytesIO()
    buffer.write(b"\0" * _LENGTH.size)
    pickler = pickle.Pickler(buffer, protocol=pickle.HIGHEST_PROTOCOL)
    pickler.dispatch_table = _dispatch_table()
    pickler.dump(records)
    frame = buffer.getbuffer()
    _LENGTH.pack_into(frame, 0, len(frame) - _LENGTH.size)
    del frame  # release the view before reading the buffer out
    return buffer.getvalue()


class FrameDecoder:
    """Reassembles frames from arbitrary chunks of the stream."""

    def __init__(self) -> None:
        self._buffer = bytearray()

    def feed(self, data: bytes) -> Iterator[list[Any]]:
        """Append ``data``; yield the record lists of every frame now complete."""
        self._buffer.extend(data)
        buffer = self._buffer
        start = 0
        try:
            while len(buffer) - start >= _LENGTH.size:
                (length,) = _LENGTH.unpack_from(buffer, start)
                if length > MAX_FRAME_BYTES:
                    raise ValueError(f"record stream out of step: frame of {length} bytes")
                end = start + _LENGTH.size + length
                if len(buffer) < end:
                    break
                records = pickle.loads(buffer[start + _LENGTH.size:end])
                start = end
                yield records
        finally:
            del buffer[:start]

    @property
    def pending_bytes(self) -> int:
        """Bytes of an incomplete frame (lost if the stream ends now)."""
        return len(self._buffer)
