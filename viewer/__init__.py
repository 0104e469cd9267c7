"""The viser web viewer (``mapkit view``); a thin layer over library functions in :mod:`mapkit.viz`.

>>> from mapkit.viewer import ViewerApp, ViewerConfig          # doctest: +SKIP
>>> with ViewerApp(ViewerConfig(workspace="ws", port=0)) as app:  # doctest: +SKIP
...     print(app.url)
...     app.gui.slice.axis.value = "x"
"""

from mapkit.viewer._app import LAYERS, ViewerApp, ViewerConfig, ViewerError
from mapkit.viewer._browser import BrowserError, find_chromium, screenshot
from mapkit.viewer._panels import CloudPanel, EvalPanel, FlightPanel, LayerToggles, Panels, PlanPanel, SlicePanel

__all__ = ["LAYERS", "BrowserError", "CloudPanel", "EvalPanel", "FlightPanel", "LayerToggles", "Panels", "PlanPanel",
           "SlicePanel", "ViewerApp", "ViewerConfig", "ViewerError", "find_chromium", "screenshot"]
