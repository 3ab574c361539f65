"""A Vicon CSV export with the cfclient CSV log of the same flight."""
