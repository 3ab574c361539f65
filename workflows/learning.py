"""What a training on flights starts from and what it says when it learned nothing: the prior a set of flights
calls for and the flights that drive it (`models.inputs`: the Crazyflie prior where they carry motor PWM and
battery voltage), and the note of a version whose residual did not improve held-out prediction
(`models.training.NOT_LEARNED`, read from `estimators.algorithm1`, where the workflows' training lives).  Loads
CasADi (the models): imported when a command trains or reports a training.
"""
from __future__ import annotations

from learnest.estimators.algorithm1 import NOT_LEARNED
from learnest.models.inputs import driven_flights, prior_for_flights

__all__ = ["NOT_LEARNED", "driven_flights", "prior_for_flights"]
