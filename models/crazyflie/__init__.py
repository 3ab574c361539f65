"""The Crazyflie: its input-driven prior (`prior`: motors, battery and attitude to specific force; its
names are re-exported here, so ``from learnest.models import crazyflie as cf`` reads as the prior), the
thrust map, gain and axis, the motors' heating, the specific-force residual, the simulator and the
identification from flights."""
from .prior import *  # noqa: F403
