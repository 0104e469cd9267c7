"""The viser web viewer (``mapkit view``); a thin layer over library functions in ``mapkit``."""
