"""Open mapkit's data in the tools robotics people already use (Foxglove)."""

from mapkit.exchange._foxglove import ExchangeError, FoxgloveConfig, FoxgloveSummary, export_foxglove

__all__ = ["ExchangeError", "FoxgloveConfig", "FoxgloveSummary", "export_foxglove"]
