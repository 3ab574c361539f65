"""Vicon Nexus/Tracker CSV export + cfclient CSV log (two files, two clocks, one flight) -> Flight; plus
writers of both for the simulator and the tests.

Modules: `csv_text` (reading the text both share), `vicon` (the export: one segment's pose), `cfclient`
(the log: accelerometer and optional channels), `reader` (`read_pair`: both on the Vicon clock, one
Flight), `writer` (`write_vicon_csv`, `write_cfclient_csv`).

Vicon export (one or more sections separated by a blank line; the first *segment pose* section is read):
    Segments                                   section title
    100                                        capture rate, Hz
    ,,cf1:cf1,,,,,                             subject:segment name above its first column
    Frame,Sub Frame,RX,RY,RZ,TX,TY,TZ          global pose of each segment (more segments -> more columns)
    ,,rad,rad,rad,mm,mm,mm                     units (optional): rotation rad|deg, position mm|cm|m
    1,0,0.01,-0.02,1.57,12.3,-45.6,32.1        data; blank pose cells = the segment was occluded
RX/RY/RZ is the helical axis (rotation vector, body -> world), Nexus' default for segments.  Time on the
Vicon clock: (Frame - first frame)/rate (+ Sub Frame/(sub frames per frame · rate), normally 0).

cfclient log (cfclient/utils/logdatawriter.py: one file per log block, one row per log packet):
    Timestamp,acc.x,acc.y,acc.z[,gyro.x,...]   Timestamp: ms since the Crazyflie booted; acc: g, body frame

The clocks share nothing; `ingest.clock` estimates the offset (t_vicon = t_cfclient_s + clock_offset_s)
by cross-correlating the specific-force magnitude seen by both.  An ambiguous alignment (score below
reader.MIN_CLOCK_SCORE or a side lobe nearly as high, e.g. a hover) is reported in meta["warnings"] and
meta["quality"].  Resampling, rotation into the world and the flying-window cut: `ingest.align.build_flight`.
"""
