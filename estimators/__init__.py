"""State estimators (KF, UKF, MHE) that run a whole sequence given a model object and arrays."""
