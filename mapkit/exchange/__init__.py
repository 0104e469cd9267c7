"""Open mapkit's data in the tools robotics people already use: Foxglove (MCAP) and Rerun (.rrd)."""

from mapkit.exchange._foxglove import ExchangeError, FoxgloveConfig, FoxgloveSummary, export_foxglove
from mapkit.exchange._rerun import RerunConfig, RerunSummary, export_rerun, open_in_rerun

__all__ = ["ExchangeError", "FoxgloveConfig", "FoxgloveSummary", "RerunConfig", "RerunSummary", "export_foxglove",
           "export_rerun", "open_in_rerun"]
