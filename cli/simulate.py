"""`mapkit simulate` (placeholder until the simulator lands)."""
