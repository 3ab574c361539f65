"""One folder per log format: `reader` (`sniff` and `read` -> Flight; helper modules where reading has
several jobs) and `writer` (the same format written, for the simulator and the tests).

  nanobench/        NanoBench CSV: Vicon + onboard logs resampled onto one 10 ms host grid
  crazyflie_usd/    Crazyflie uSD-card binary logs (firmware usddeck, versions 1 and 2)
  mcap/             MCAP recordings: ROS 2 bags and JSON-encoded channels
  vicon_cfclient/   a Vicon Nexus/Tracker CSV export with the cfclient CSV log of the same flight

`crazyflie_variables` names the firmware's log variables that uSD, cfclient and MCAP logs share.
`ingest.read_flights` picks the reader from each file's content.
"""
