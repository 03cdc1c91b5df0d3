"""``splatreplace masks --viewer``: one click per instance in nerfstudio's viewer, on the base model.

A click in the 3D view is a ray. The base model's rendered depth along the ray gives the clicked surface
point; the point becomes a pixel click in the training frame that sees it best (visible by rendered depth,
viewed from the direction closest to the click's). The clicks are then written to ``clicks.json`` and
used exactly like hand-written ones, by ``splatreplace masks`` now and by the segmentation stage of
``ns-train splat-replace`` later, so the same clicks make the masks and select the instances.
Every click is checked at once (background, a supporting plane, an instance clicked twice) and a bad one
only changes the status message.
"""

from __future__ import annotations

import json
import threading
from pathlib import Path
from typing import Callable, List, Optional, Sequence

from nerfstudio.viewer.viewer_elements import ViewerClick

from splatreplace_ns.datamanager.clicks import Click
from splatreplace_ns.instances.frames import FrameCameras, FrameRenders
from splatreplace_ns.instances.geometric_config import Clustering
from splatreplace_ns.instances.projection import ClickError
from splatreplace_ns.instances.masks_from_clicks import MaskSettings, mask_click_functions
from splatreplace_ns.viewer.click_controls import ClickControls


class MaskClickControls(ClickControls):
    """Viewer GUI of ``splatreplace masks --viewer``, and of ``ns-train splat-replace`` on a capture without
    masks or clicks.json (there the controls exist from the start, so that the viewer finds them, and are
    connected to the base model when its stage ends).

    Args:
        to_click: (origin, direction, class, index) → the pixel click for a viewer ray; raises ClickError.
        validate: checks the whole list of clicks (e.g. two clicks on one instance); raises ClickError.
        Both None: not connected yet; a click only says when clicking opens.
        closed_status: what the status line says until :meth:`connect`.
    """

    def __init__(
        self,
        to_click: Optional[Callable[[Sequence[float], Sequence[float], str, int], Click]] = None,
        validate: Optional[Callable[[List[Click]], None]] = None,
        closed_status: str = "clicking opens when the base model is trained",
    ):
        connected = to_click is not None and validate is not None
        super().__init__("Click each instance", "Click an instance", "Undo last click", "Write masks", "Clicks",
                         "Status", "press 'Click an instance', then click it" if connected else closed_status)
        self._closed_status = closed_status
        self._to_click = to_click
        self._validate = validate
        self.clicks: List[Click] = []

    @property
    def connected(self) -> bool:
        return self._to_click is not None and self._validate is not None

    def connect(
        self,
        to_click: Callable[[Sequence[float], Sequence[float], str, int], Click],
        validate: Callable[[List[Click]], None],
    ) -> None:
        """Opens clicking, on the trained base model (see :func:`~splatreplace_ns.method.masks_command.mask_click_functions`)."""
        self._to_click, self._validate = to_click, validate
        self._say("press 'Click an instance', then click it; 'Write masks' when every instance has one")

    def arm_click(self) -> None:
        if not self.connected:
            self._say(self._closed_status)
            return
        super().arm_click()

    def _refresh(self) -> None:
        self.listing.value = "; ".join(
            f"{k + 1}: {c.cls} ({Path(c.file_path).name} at {int(c.xy[0])},{int(c.xy[1])})" for k, c in enumerate(self.clicks)
        ) or "(none)"

    def on_click(self, click: ViewerClick) -> Optional[Click]:
        """Adds the clicked instance; a bad click only changes the status message."""
        if not self.connected:
            self._say(self._closed_status)
            return None
        cls = self.class_name.value or "object"
        try:
            new = self._to_click(click.origin, click.direction, cls, len(self.clicks))
            self._validate(self.clicks + [new])
        except (ClickError, ValueError) as err:
            self._say(str(err))
            return None
        self.clicks.append(new)
        self._refresh()
        self._say(f"added instance {len(self.clicks)} ({cls}) at {new.file_path} {[int(v) for v in new.xy]}")
        return new

    def undo(self) -> None:
        removed = self.clicks.pop() if self.clicks else None
        self._refresh()
        self._say(f"removed instance {len(self.clicks) + 1}" if removed else "nothing to undo")

    def confirm(self) -> None:
        if not self.connected:
            self._say(self._closed_status)
            return
        if not self.clicks:
            self._say("click at least one instance before writing the masks")
            return
        self._say(f"writing the masks of {len(self.clicks)} instances")
        self._confirmed.set()

    def wait_for_confirm(
        self, poll_s: float = 0.2, held_lock: Optional[threading.Lock] = None,
        stop_when: Optional[Callable[[], bool]] = None,
    ) -> Optional[List[Click]]:
        """Blocks until "Write masks" is pressed and returns the clicks, or until ``stop_when()`` holds and returns
        None (see ``ClickControls._wait``, also for ``held_lock``)."""
        if not self._wait(poll_s, held_lock, stop_when):
            self._say("clicks.json appeared: the masks are made from it")
            return None
        return list(self.clicks)


def mask_click_controls(
    model, frames: FrameCameras, cfg: MaskSettings, renders: Optional[FrameRenders] = None,
    clustering: Optional[Clustering] = None,
) -> MaskClickControls:
    """The viewer controls of ``splatreplace masks --viewer``, connected to the base model
    (:func:`mask_click_functions`)."""
    return MaskClickControls(*mask_click_functions(model, frames, cfg, renders, clustering))
