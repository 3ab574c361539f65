"""NanoBench CSV (Vicon + Crazyflie onboard logs on one 10 ms host grid): `reader.read` -> Flight,
`writer.write` for the simulator and the tests."""
