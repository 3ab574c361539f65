"""The closed-loop Crazyflie simulator."""
