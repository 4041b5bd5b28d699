"""A session's messages as they are read: their bytes in one buffer, and per topic each
message's log time and where its bytes lie, in arrays.

The reader adds each chunk's messages at once (:class:`~hil.core.recording.chunk_messages.
ChunkMessages`: the chunk's content goes into the buffer whole) and the messages read one by one
(a damaged chunk's, or a file without chunks); at the end of a file it names the topic of each
channel. :meth:`MessageStore.finish` gives every topic's messages in log-time order, those
with the same log time in the order they were read.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass

import numpy as np

from hil.core.recording.chunk_messages import ChunkMessages

_Piece = tuple[np.ndarray, np.ndarray, np.ndarray]  # log times, starts, sizes


@dataclass(frozen=True)
class TopicMessages:
    """One topic's messages in log-time order: message ``k`` was logged at ``log_times[k]``
    and is ``buffer[starts[k]:starts[k] + sizes[k]]`` of its session's buffer."""

    log_times: np.ndarray  # uint64
    starts: np.ndarray     # int64
    sizes: np.ndarray      # int64


class MessageStore:
    """Collects a session's messages, file after file."""

    def __init__(self) -> None:
        self.buffer = bytearray()
        self._topics: dict[str, list[_Piece]] = {}
        self._file: dict[int, list[_Piece]] = defaultdict(list)   # by channel id
        self._loose: dict[int, tuple[list[int], list[int], list[int]]] = {}

    def declare(self, topic: str) -> None:
        """A topic of the session, whether or not any message of it is read."""
        self._topics.setdefault(topic, [])

    def add_chunk(self, messages: ChunkMessages) -> None:
        self._close_loose()
        base = len(self.buffer)
        self.buffer += messages.content
        ids = messages.channel_ids
        # the channels present, ascending (np.unique would import numpy.ma: 15 ms a process)
        for channel_id in np.flatnonzero(np.bincount(ids)).tolist():
            mine = ids == channel_id
            self._file[channel_id].append((messages.log_times[mine],
                                           messages.starts[mine] + base, messages.sizes[mine]))

    def add_message(self, channel_id: int, log_time: int, data: bytes) -> None:
        times, starts, sizes = self._loose.setdefault(channel_id, ([], [], []))
        times.append(log_time)
        starts.append(len(self.buffer))
        sizes.append(len(data))
        self.buffer += data

    def end_file(self, topics: dict[int, str]) -> int:
        """The file's messages go to their channels' topics (a channel the file does not
        name: ``<channel ID>``); returns how many it held."""
        self._close_loose()
        count = 0
        for channel_id, pieces in self._file.items():
            topic = topics.get(channel_id, f"<channel {channel_id}>")
            self._topics.setdefault(topic, []).extend(pieces)
            count += sum(piece[0].size for piece in pieces)
        self._file.clear()
        return count

    def finish(self) -> dict[str, TopicMessages]:
        """Every topic's messages, in log-time order (stable)."""
        out = {}
        empty = (np.empty(0, np.uint64), np.empty(0, np.int64), np.empty(0, np.int64))
        for topic, pieces in self._topics.items():
            times, starts, sizes = (np.concatenate(parts) for parts in
                                    zip(*pieces, strict=True)) if pieces else empty
            if times.size > 1 and (times[1:] < times[:-1]).any():
                order = np.argsort(times, kind="stable")
                times, starts, sizes = times[order], starts[order], sizes[order]
            out[topic] = TopicMessages(times, starts, sizes)
        return out

    def _close_loose(self) -> None:
        """The messages read one by one so far, as one piece per channel (so that they keep
        their place before the next chunk's)."""
        for channel_id, (times, starts, sizes) in self._loose.items():
            self._file[channel_id].append((np.array(times, dtype=np.uint64),
                                           np.array(starts, dtype=np.int64),
                                           np.array(sizes, dtype=np.int64)))
        self._loose.clear()
