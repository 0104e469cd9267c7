"""`mapkit info` and `mapkit ingest` (placeholder)."""
