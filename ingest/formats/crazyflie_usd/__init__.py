"""Crazyflie uSD-card binary logs."""
