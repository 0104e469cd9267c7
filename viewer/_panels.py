"""The viewer's side panel as typed objects: one small dataclass per folder holding its viser handles.

``ViewerApp.gui`` is a :class:`Panels`; a folder whose data is missing (no cloud.ply, no model, ...)
stays None, so ``app.gui.flight is None`` says the workspace has no frames.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, TypeVar

if TYPE_CHECKING:
    from viser import (
        GuiButtonHandle,
        GuiCheckboxHandle,
        GuiDropdownHandle,
        GuiHtmlHandle,
        GuiImageHandle,
        GuiMarkdownHandle,
        GuiNumberHandle,
        GuiSliderHandle,
        GuiVector3Handle,
    )


@dataclass
class LayerToggles:
    """The "Layers" folder: one checkbox per layer that has something to show (None otherwise)."""

    cloud: GuiCheckboxHandle | None = None
    slice: GuiCheckboxHandle | None = None
    flight: GuiCheckboxHandle | None = None
    plan: GuiCheckboxHandle | None = None
    corridor: GuiCheckboxHandle | None = None
    eval: GuiCheckboxHandle | None = None

    def of(self, layer: str) -> GuiCheckboxHandle | None:
        """The checkbox of ``layer`` (one of ``LAYERS``)."""
        toggle: GuiCheckboxHandle | None = getattr(self, layer)
        return toggle


@dataclass
class CloudPanel:
    """The "Point cloud" folder."""

    color: GuiDropdownHandle
    """Colour by "height" or "ESDF"."""
    size: GuiSliderHandle
    """Point size, metres."""


@dataclass
class SlicePanel:
    """The "ESDF slice" folder."""

    axis: GuiDropdownHandle
    position: GuiSliderHandle
    """Metres along ``axis``."""
    value: GuiDropdownHandle
    """Signed distance or obstacle cost."""
    cmap: GuiDropdownHandle
    raw: GuiCheckboxHandle
    """Show esdf_raw (unsmoothed)."""
    vmin: GuiNumberHandle
    vmax: GuiNumberHandle
    auto: GuiButtonHandle
    """Recompute the colour range from the slice."""
    colorbar: GuiImageHandle
    info: GuiMarkdownHandle


@dataclass
class FlightPanel:
    """The "Flight" folder."""

    frame: GuiSliderHandle
    """Index of the selected frame."""
    play: GuiCheckboxHandle
    fps: GuiSliderHandle
    frustum_every: GuiSliderHandle
    depth: GuiImageHandle
    """The selected frame's depth image."""
    info: GuiMarkdownHandle


@dataclass
class PlanPanel:
    """The "Plan (live)" folder."""

    click_goal: GuiCheckboxHandle
    goal: GuiVector3Handle
    """World goal, metres."""
    corridor_width: GuiNumberHandle
    """Corridor half-width, metres; 0 = off."""
    button: GuiButtonHandle
    info: GuiMarkdownHandle
    speed_colorbar: GuiImageHandle


@dataclass
class EvalPanel:
    """The "Evaluation" folder."""

    world: GuiDropdownHandle
    pair: GuiDropdownHandle
    """"all" or a pair index."""
    legend: GuiHtmlHandle
    table: GuiMarkdownHandle


@dataclass
class Panels:
    """Every GUI handle of the viewer, by folder; a folder whose data is missing stays None."""

    status: GuiMarkdownHandle | None = None
    """What was loaded and what is missing."""
    message: GuiMarkdownHandle | None = None
    """The last library message (errors of callbacks, click feedback)."""
    layers: LayerToggles = field(default_factory=LayerToggles)
    cloud: CloudPanel | None = None
    slice: SlicePanel | None = None
    flight: FlightPanel | None = None
    plan: PlanPanel | None = None
    eval: EvalPanel | None = None


P = TypeVar("P")


def built(panel: P | None) -> P:
    """``panel``, which the calling callback's layer guarantees was built (a bug otherwise)."""
    if panel is None:
        raise RuntimeError("viewer callback ran for a panel that was never built")
    return panel


__all__ = ["CloudPanel", "EvalPanel", "FlightPanel", "LayerToggles", "Panels", "PlanPanel", "SlicePanel", "built"]
