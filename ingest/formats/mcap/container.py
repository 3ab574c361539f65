"""The MCAP container read front to back: every schema, channel and (for pose/acceleration candidates)
message, with the damage it meets (a cut-off file, chunks that do not decompress or fail their CRC)
turned into warnings, and decompression bombs refused before they expand."""
from __future__ import annotations

import io
import struct
from collections import Counter, defaultdict
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import lz4.frame
import zstandard
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, Message, Schema
from mcap.stream_reader import StreamReader, get_chunk_data_stream

from ...flight import IngestError, existing_file
from .schemas import is_candidate_schema

MAGIC = b"\x89MCAP0\r\n"

# A single chunk bigger than this is a damaged size field, not a recording (rosbag2 writes ~1 MiB chunks).
MAX_CHUNK_BYTES = 256 << 20
# Decompression budget of a whole file (a "zip bomb" guard): what its chunks may expand to in total is at
# most MAX_EXPANSION x the file's size (sensor data compresses 2-10x; zeros compress 10^5x) and never more
# than MAX_DECOMPRESSED_BYTES.  Checked against each chunk's declared size BEFORE it is decompressed, so
# a bomb is refused in the time it takes to read its headers, and the parsing work (pure Python, per
# record) stays proportional to what the uploader sent.
MAX_EXPANSION = 100
MAX_DECOMPRESSED_BYTES = 4 << 30
# Payloads of messages whose channel is not declared yet are kept (the declaration may come later, in
# the summary) only up to this many bytes; past it they are counted and dropped.
MAX_PENDING_BYTES = 32 << 20
# A message record's fixed fields: channel id (2), sequence (4), log and publish times (8 + 8).
MESSAGE_HEADER_BYTES = 22

# What the mcap reader raises on damaged framing (cut-off reads, bad lengths, bad UTF-8, CRC mismatch,
# corrupt compressed data; lz4 reports corruption as RuntimeError).
FRAMING_ERRORS = (McapError, struct.error, ValueError, EOFError, OverflowError, RuntimeError)


@dataclass
class McapChannel:
    """One channel of the file with the messages kept from it (only for channels that may be read)."""
    id: int
    topic: str
    message_encoding: str
    schema: Schema | None
    count: int = 0
    messages: list[tuple[int, bytes]] = field(default_factory=list)    # (log_time ns, payload)

    @property
    def schema_name(self) -> str:
        """The schema's name, "" when the channel has no schema."""
        return self.schema.name if self.schema is not None else ""

    def describe(self) -> str:
        """One line for messages: topic (schema, message encoding, message count)."""
        return f"{self.topic} ({self.schema_name or 'no schema'}, {self.message_encoding}, {self.count} messages)"


@dataclass
class McapContent:
    """What `scan` found in a file.

    Attributes
    ----------
    channels : list of McapChannel
        Every declared channel, sorted by (topic, id); messages are kept only for pose/acceleration candidates.
    warnings : list of str
        The damage met (file cut off, chunks skipped, messages on undeclared channels).
    """
    channels: list[McapChannel]
    warnings: list[str]


class _ClampedFile(io.BufferedReader):
    """A buffered file whose reads are clamped to the bytes that are left, so that a damaged length field
    (up to 2^64) reads to the end of the file instead of allocating its claimed size.  `position` counts
    the bytes handed out."""

    def __init__(self, raw: io.RawIOBase, size: int):
        super().__init__(raw)
        self.size, self.position = size, 0

    def read(self, length: int | None = -1) -> bytes:
        left = self.size - self.position
        data = super().read(left if length is None or length < 0 else min(length, left))
        self.position += len(data)
        return data


class DecompressionLimit(ValueError):
    """A file whose chunks would expand past the decompression budget (see MAX_EXPANSION)."""


class _Collector:
    """Schemas, channels and messages as the stream reader meets them.  Schema and channel records
    appear twice (data section and summary): the first copy wins.  ``budget`` is how many bytes the
    chunks may decompress to in total."""

    def __init__(self, budget: int = MAX_DECOMPRESSED_BYTES):
        self.budget, self.decompressed, self.pending_bytes = budget, 0, 0
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.counts: Counter = Counter()
        self.messages: dict[int, list[tuple[int, bytes]]] = defaultdict(list)
        self.damaged_chunks: list[str] = []

    def add(self, record) -> None:
        if isinstance(record, Chunk):
            self._add_chunk(record)
        elif isinstance(record, Schema) and record.id != 0:
            self.schemas.setdefault(record.id, record)
        elif isinstance(record, Channel):
            self.channels.setdefault(record.id, record)
        elif isinstance(record, Message):
            self.counts[record.channel_id] += 1
            if self._may_be_read(record.channel_id, len(record.data)):
                self.messages[record.channel_id].append((record.log_time, record.data))

    def _add_chunk(self, chunk: Chunk) -> None:
        self.decompressed += chunk.uncompressed_size
        if self.decompressed > self.budget:  # not a FRAMING_ERROR: the whole file is refused
            raise DecompressionLimit(
                f"chunks expand to more than {self.budget} bytes (the cap is {MAX_EXPANSION}x the file's size, "
                f"at most {MAX_DECOMPRESSED_BYTES >> 30} GiB): a decompression bomb or not a flight recording")
        try:
            records = _chunk_records(chunk)
        except FRAMING_ERRORS as err:
            self.damaged_chunks.append(f"{type(err).__name__}: {err}"[:200])
            return
        for record in records:
            self.add(record)

    def _may_be_read(self, channel_id: int, size: int) -> bool:
        # Keep payloads of pose/acceleration candidates only (a bag may hold GBs of images).  A channel
        # not declared yet keeps its payloads: its declaration may be in the summary (first chunk damaged).
        channel = self.channels.get(channel_id)
        if channel is None:
            self.pending_bytes += size
            return self.pending_bytes <= MAX_PENDING_BYTES
        schema = self.schemas.get(channel.schema_id)
        return is_candidate_schema(channel.message_encoding, schema.name if schema else "")


def _chunk_records(chunk: Chunk) -> list:
    """The records inside a chunk, after checking its size and CRC (raises FRAMING_ERRORS)."""
    if chunk.uncompressed_size > MAX_CHUNK_BYTES:
        raise ValueError(f"chunk claims {chunk.uncompressed_size} bytes uncompressed")
    data = _decompress(chunk)
    if len(data) != chunk.uncompressed_size:
        raise ValueError(f"chunk decompresses to {len(data)} bytes, its header says {chunk.uncompressed_size}")
    plain = Chunk(compression="", data=data, message_start_time=chunk.message_start_time,
                  message_end_time=chunk.message_end_time, uncompressed_crc=chunk.uncompressed_crc,
                  uncompressed_size=chunk.uncompressed_size)
    return _records_of(plain)


def _records_of(chunk: Chunk) -> list:
    """`mcap.stream_reader.breakup_chunk`, but refusing opcode 0x00 (reserved as invalid by the MCAP
    spec): zeros parse as ~10^6 empty records per 16 MiB in pure Python (seconds of work), and zeros are what a
    bomb's chunk holds.  A record must also fit in its length field (the library's readers trust it only
    for messages, and a message shorter than its 22-byte header would swallow the rest of the chunk);
    bytes past the fields read are skipped (a later spec version's fields), as are unknown opcodes."""
    stream, length = get_chunk_data_stream(chunk, validate_crc=True)
    records: list = []
    while stream.count < length:
        start = stream.count
        opcode, size = stream.read1(), stream.read8()
        if opcode == 0:
            raise ValueError(f"chunk record at byte {start} has opcode 0x00 (invalid)")
        if opcode == Opcode.MESSAGE and size < MESSAGE_HEADER_BYTES:
            raise ValueError(f"message record at byte {start} claims {size} bytes, less than its header")
        if opcode == Opcode.CHANNEL:
            records.append(Channel.read(stream))
        elif opcode == Opcode.MESSAGE:
            records.append(Message.read(stream, size))
        elif opcode == Opcode.SCHEMA:
            records.append(Schema.read(stream))
        else:
            stream.read(size)
        end = start + 9 + size
        if stream.count > end:
            raise ValueError(f"chunk record at byte {start} (opcode 0x{opcode:02x}) ends at byte {stream.count}, "
                             f"its length field says {end}")
        stream.read(end - stream.count)      # fields of a later spec version: skipped, as the spec asks
    return records


def _decompress(chunk: Chunk) -> bytes:
    """Chunk data decompressed in pieces, never more than one byte past the declared size: a corrupt
    frame header cannot make the decompressor allocate what it claims."""
    if chunk.compression == "":
        return chunk.data
    if chunk.compression == "zstd":
        try:
            stream = zstandard.ZstdDecompressor().stream_reader(chunk.data)
            return _read_at_most(stream.read, chunk.uncompressed_size + 1)
        except zstandard.ZstdError as err:
            raise ValueError(f"zstd: {err}") from None
    if chunk.compression == "lz4":
        decompressor = lz4.frame.LZ4FrameDecompressor()
        return decompressor.decompress(chunk.data, max_length=chunk.uncompressed_size + 1)
    raise ValueError(f"unsupported chunk compression {chunk.compression!r}")


def _read_at_most(read: Callable[[int], bytes], limit: int) -> bytes:
    pieces, total = [], 0
    while total < limit:
        piece = read(min(1 << 20, limit - total))
        if not piece:
            break
        pieces.append(piece)
        total += len(piece)
    return b"".join(pieces)


def _check_file(path: Path) -> None:
    if path.is_dir():
        inside = sorted(p.name for p in path.glob("*.mcap"))
        hint = f" (a rosbag2 folder? pass the .mcap file inside: {', '.join(inside)})" if inside else ""
        raise IngestError(path, f"is a directory, not an MCAP file{hint}")
    existing_file(path, "MCAP recording")
    with open(path, "rb") as handle:
        start = handle.read(len(MAGIC))
    if start != MAGIC:
        if MAGIC.startswith(start):
            raise IngestError(path, f"MCAP file cut off inside its magic bytes ({len(start)} bytes long)")
        raise IngestError(path, f"not an MCAP file: starts with {start!r}, expected the MCAP magic {MAGIC!r}")


def scan(path) -> McapContent:
    """Every schema, channel and (for pose/acceleration candidates) message the file holds, read front to
    back.  Damage ends the reading (cut-off file) or skips one chunk; both become warnings."""
    path = Path(path)
    _check_file(path)
    size = path.stat().st_size
    collector, warnings = _Collector(budget=min(MAX_DECOMPRESSED_BYTES, MAX_EXPANSION * size)), []
    with _ClampedFile(io.FileIO(path), size) as clamped:
        reader = StreamReader(clamped, emit_chunks=True, record_size_limit=size)
        try:
            for record in reader.records:
                collector.add(record)
        except DecompressionLimit as err:
            raise IngestError(path, str(err)) from None
        except FRAMING_ERRORS as err:
            detail = f"{type(err).__name__}{': ' + str(err) if str(err) else ''}"[:200]
            warnings.append(f"file cut off or damaged at byte {clamped.position} of {size} ({detail}): "
                            f"kept the {sum(collector.counts.values())} complete messages before it")
    if collector.damaged_chunks:
        warnings.append(f"skipped {len(collector.damaged_chunks)} damaged chunk(s), their messages are lost "
                        f"(first: {collector.damaged_chunks[0]})")
    channels = [McapChannel(channel.id, channel.topic, channel.message_encoding,
                            collector.schemas.get(channel.schema_id), collector.counts[channel.id],
                            collector.messages.get(channel.id, []))
                for channel in collector.channels.values()]
    orphans = sum(n for channel_id, n in collector.counts.items() if channel_id not in collector.channels)
    if orphans:
        warnings.append(f"{orphans} message(s) on undeclared channels ignored")
    return McapContent(sorted(channels, key=lambda c: (c.topic, c.id)), warnings)


def topics(path) -> list[tuple[str, str, str, int]]:
    """[(topic, schema name, message encoding, message count)] for every channel, sorted by topic."""
    return [(c.topic, c.schema_name, c.message_encoding, c.count) for c in scan(path).channels]

