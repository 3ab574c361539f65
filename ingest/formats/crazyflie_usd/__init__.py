"""Crazyflie uSD-card binary logs: what the firmware's usddeck writes to the micro-SD card (versions 1
and 2) -> Flight; plus a writer for the simulator and the tests.

Format (little-endian, no padding; ../shared/data/README.md, "The uSD binary format"):
  header   uint8 0xBC, uint16 version, uint16 number of event types; per event type: uint16 id
           (0xFFFF = "fixedFrequency"), name NUL, uint16 nvars, nvars x "group.name(T)" NUL (T a struct code)
  records  uint16 event id, timestamp (v2 uint64 us, v1 uint32 ms), values packed '<' + types
  trailer  uint32 zlib CRC-32 of every byte before it

Modules: `layout` (the format's constants and an event type's record layout), `decoder` (bytes -> every
event's records as numpy columns, damage kept as warnings), `reader` (`read`: the streams a Flight needs,
handed to `ingest.align.build_flight`), `writer` (`encode`/`write` a log from event streams).
"""
