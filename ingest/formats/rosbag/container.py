"""A ROS bag opened with rosbags: its connections as channels (see formats.mcap.channels.Channel) with the
messages of the pose/acceleration candidates kept, and a decoder per channel.

ROS 1 bags compress chunks (bz2, lz4).  Like the MCAP container, a chunk may expand to its declared size
only, and all chunks together to at most MAX_EXPANSION x the file's size, so that a decompression bomb is
refused before it expands.

A ROS 2 .db3 is an SQLite file, and SQLite computes what it yields: a ``messages.data`` that is a virtual
generated column ``zeroblob(N)``, or a view, makes a 24-kB file yield gigabytes.  So before rosbags reads
it, every table rosbags reads must be a table (no view) and the bytes its values yield - as SQLite computes
them, counted with ``length()`` (which measures a zeroblob without building it) row by row - must stay
within the same budget as a ROS 1 bag's chunks; one value may not exceed MAX_VALUE_BYTES (SQLite's own
length limit refuses it before it is built), and the check's SQL has a bounded number of steps.  The
messages rosbags then yields are counted again as they arrive."""
from __future__ import annotations

import bz2
import contextlib
import functools
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

from ...flight import IngestError
from ..mcap.container import MAX_DECOMPRESSED_BYTES, MAX_EXPANSION
from ..mcap.schemas import EXTRA_TYPES, MSG_TEXT, is_candidate_schema

SQLITE_MAGIC = b"SQLite format 3\x00"
# the tables of a rosbag2 .db3 that rosbags reads (the others are never queried)
ROS2_TABLES = ("messages", "topics", "schema", "metadata", "message_definitions")
MAX_VALUE_BYTES = 64 << 20        # one message (or any value of those tables): a camera frame is ~6 MB
MAX_SQL_STEPS = 2_000_000_000     # SQLite virtual-machine steps of the size check (~ a minute of CPU at most)
ROS1_MAGIC = b"#ROSBAG V2.0\n"
# what rosbags needs in a file's name to pick its reader
SUFFIX = {"ros1": ".bag", "ros2": ".db3"}


@dataclass
class BagChannel:
    """One connection of a bag, with the messages kept from it (only for candidate types)."""
    id: int
    topic: str
    message_encoding: str       # "cdr" (ROS 2) or "ros1"
    schema_name: str            # the message type, pkg/msg/Type
    count: int = 0
    messages: list[tuple[int, bytes]] = field(default_factory=list)    # (receive time ns, payload)
    connection: Any = None      # rosbags' Connection

    def describe(self) -> str:
        """One line for messages: topic (type, encoding, message count)."""
        return f"{self.topic} ({self.schema_name or 'no type'}, {self.message_encoding}, {self.count} messages)"


def kind(path: Path) -> str | None:
    """"ros1", "ros2" (an SQLite file: a rosbag2 .db3) or None, from the file's first bytes."""
    try:
        with open(path, "rb") as handle:
            head = handle.read(len(SQLITE_MAGIC))
    except OSError:
        return None
    if head.startswith(ROS1_MAGIC):
        return "ros1"
    return "ros2" if head == SQLITE_MAGIC else None


@functools.cache
def default_typestore():
    """The standard ROS 2 Humble types plus the Crazyflie ones learnest knows (for bags without stored
    definitions).  Built once: rosbags only reads it."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    types: dict = {}
    for name in EXTRA_TYPES:
        types.update(get_types_from_msg(MSG_TEXT[name], name))
    store.register(types)
    return store


@contextlib.contextmanager
def _readable_name(path: Path, bag_kind: str) -> Iterator[Path]:
    """The file under a name rosbags accepts (it picks its reader by suffix): the file itself, or a link to it
    in a temporary folder."""
    if path.suffix == SUFFIX[bag_kind]:
        yield path
        return
    with tempfile.TemporaryDirectory(prefix="learnest-bag-") as folder:
        link = Path(folder) / f"bag{SUFFIX[bag_kind]}"
        link.symlink_to(path.resolve())
        yield link


def _capped(decompress: Callable[[bytes, int], bytes], declared: int, budget: list[int],
            data: bytes) -> bytes:
    """A chunk decompressed to at most its declared size (+1 byte, to notice a lie), charged to the budget."""
    budget[0] -= declared
    if budget[0] < 0:
        raise ValueError(f"chunks expand to more than {MAX_EXPANSION}x the file's size: a decompression bomb "
                         f"or not a flight recording")
    out = decompress(data, declared + 1)
    if len(out) != declared:
        raise ValueError(f"chunk decompresses to {len(out)} bytes, its header says {declared}")
    return out


def _bz2(data: bytes, limit: int) -> bytes:
    return bz2.BZ2Decompressor().decompress(data, max_length=limit)


def _lz4(data: bytes, limit: int) -> bytes:
    import lz4.frame

    return lz4.frame.LZ4FrameDecompressor().decompress(data, max_length=limit)


def _cap_ros1_chunks(path: Path, reader) -> None:
    """Replace every compressed chunk's decompressor of a rosbags ROS 1 reader by a capped one."""
    from rosbags.rosbag1.reader import Chunk, Header, RecordType

    budget = [_budget(path)]
    for bag in reader.readers:
        for position, chunk in list(getattr(bag, "chunks", {}).items()):
            bag.bio.seek(position)
            header = Header.read(bag.bio, RecordType.CHUNK)
            compression = header.get_string("compression")
            if compression == "none":
                continue
            decompress = {"bz2": _bz2, "lz4": _lz4}[compression]
            capped = partial(_capped, decompress, header.get_uint32("size"), budget)
            bag.chunks[position] = Chunk(chunk.datasize, chunk.datapos, capped)


@contextlib.contextmanager
def open_bag(path: Path) -> Iterator[tuple[list[BagChannel], Callable[[Path, BagChannel], Callable[[bytes], Any]]]]:
    """(channels with the candidate messages, decoder_for) of a bag, while it is open.

    Raises
    ------
    IngestError
        Not a ROS bag, or rosbags cannot open or read it (the reason is in the message).
    """
    from rosbags.highlevel import AnyReader

    bag_kind = kind(path)
    if bag_kind is None:
        raise IngestError(path, "not a ROS bag (expected a ROS 1 .bag or a ROS 2 sqlite3 .db3 file)")
    what = "ROS 1 bag" if bag_kind == "ros1" else "ROS 2 sqlite3 bag (.db3)"
    with _readable_name(path, bag_kind) as readable:
        try:
            budget = _budget(path)
            if bag_kind == "ros2":
                _check_sqlite_sizes(path, what, budget)
            reader = AnyReader([readable], default_typestore=default_typestore())
            reader.open()
        except IngestError:
            raise
        except Exception as err:   # rosbags on bytes from the file: any error means "cannot be opened"
            raise IngestError(path, f"cannot open the {what}: {_reason(err)}") from None
        try:
            if bag_kind == "ros1":
                _cap_ros1_chunks(path, reader)
            channels = _channels(path, reader, bag_kind, what, budget)
            decoders = {id(c): partial(_deserialize, reader, c.schema_name) for c in channels}
            yield channels, lambda _path, channel: decoders[id(channel)]
        finally:
            with contextlib.suppress(Exception):
                reader.close()


def _budget(path: Path) -> int:
    """Bytes a bag of this file's size may yield: MAX_EXPANSION x its size, at most MAX_DECOMPRESSED_BYTES."""
    return min(MAX_DECOMPRESSED_BYTES, MAX_EXPANSION * path.stat().st_size)


def _too_much(what: str, budget: int) -> str:
    return (f"the {what} yields more than {budget} bytes ({MAX_EXPANSION}x the file's size): a decompression "
            "bomb or not a flight recording")


def _check_sqlite_sizes(path: Path, what: str, budget: int) -> None:
    """Refuse (IngestError) a .db3 whose tables rosbags reads are views, or whose values yield more than
    ``budget`` bytes in all or more than MAX_VALUE_BYTES in one, as SQLite computes them (module docstring)."""
    import sqlite3

    try:
        # a URI built by pathlib escapes "#" and "?": a bag named run#1.db3 is opened, read-only, as itself
        connection = sqlite3.connect(Path(path).resolve().as_uri() + "?mode=ro", uri=True)
    except sqlite3.Error as err:
        raise IngestError(path, f"cannot open the {what}: {_reason(err)}") from None
    steps = [0]

    def count_steps() -> int:
        steps[0] += 100_000
        return int(steps[0] > MAX_SQL_STEPS)   # non-zero interrupts the statement

    try:
        connection.setlimit(sqlite3.SQLITE_LIMIT_LENGTH, MAX_VALUE_BYTES)
        connection.set_progress_handler(count_steps, 100_000)
        kinds = dict(connection.execute("SELECT name, type FROM sqlite_master WHERE type IN ('table', 'view')"))
        total = 0
        for table in ROS2_TABLES:
            if table not in kinds:
                continue
            if kinds[table] != "table":
                raise IngestError(path, f"not a {what}: its {table!r} is an SQLite {kinds[table]}, not a table")
            columns = [row[1] for row in connection.execute(f'PRAGMA table_xinfo("{table}")')]
            # a blob's length is read from its header (a zeroblob is never built); text counts in bytes
            sizes = " + ".join(f"""(CASE typeof("{c}") WHEN 'blob' THEN length("{c}") WHEN 'null' THEN 0 """
                               f"""ELSE length(CAST("{c}" AS BLOB)) END)""" for c in columns) or "0"
            for (size,) in connection.execute(f'SELECT {sizes} FROM "{table}"'):
                total += size
                if total > budget:
                    raise IngestError(path, _too_much(what, budget))
    except sqlite3.Error as err:
        text = str(err)
        if "too big" in text:
            text = f"a value larger than {MAX_VALUE_BYTES} bytes"
        elif "interrupted" in text:
            text = f"sizing its tables took more than {MAX_SQL_STEPS} SQLite steps"
        raise IngestError(path, f"cannot read the {what}: {text[:300]}") from None
    finally:
        connection.close()


def _channels(path: Path, reader, bag_kind: str, what: str, budget: int) -> list[BagChannel]:
    encoding = "ros1" if bag_kind == "ros1" else "cdr"
    channels = [BagChannel(i, c.topic, encoding, c.msgtype, c.msgcount, connection=c)
                for i, c in enumerate(reader.connections)]
    by_connection = {c.connection.id: c for c in channels}
    wanted = [c.connection for c in channels if is_candidate_schema(encoding, c.schema_name)]
    if not wanted:
        return sorted(channels, key=lambda c: (c.topic, c.id))
    kept = 0   # bytes of the messages kept: bounded whatever the container claimed before
    try:
        for connection, timestamp, raw in reader.messages(connections=wanted):
            kept += len(raw)
            if kept > budget:
                raise IngestError(path, _too_much(what, budget))
            by_connection[connection.id].messages.append((timestamp, bytes(raw)))
    except IngestError:
        raise
    except Exception as err:   # a damaged file met while reading: nothing half-read is trusted
        raise IngestError(path, f"the {what} is damaged: {_reason(err)}") from None
    return sorted(channels, key=lambda c: (c.topic, c.id))


def _deserialize(reader, type_name: str, raw: bytes):
    return reader.deserialize(raw, type_name)


def _reason(err: Exception) -> str:
    text = str(err) or type(err).__name__
    if "reindex" in text:
        text += " (a recording cut off before its index was written: `rosbag reindex` repairs it)"
    return text[:300]
