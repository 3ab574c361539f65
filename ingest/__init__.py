"""Raw flight logs -> canonical Flight."""
