"""One click at a time in nerfstudio's viewer: the controls both click flows share.

A button arms exactly one click in the 3D view (a registered click callback blocks the camera controls,
so it is removed after the click); a text field names the class of the next click; an undo button, a
list and a status line; a confirm button that releases whoever waits. Subclasses say what a click, an
undo and a confirmation do. An ``nn.Module`` only so that the viewer's scan of the pipeline finds it.
"""

from __future__ import annotations

import threading

from torch import nn

from nerfstudio.viewer.viewer_elements import ViewerButton, ViewerClick, ViewerControl, ViewerText


class ClickControls(nn.Module):
    """Viewer elements for one click per item, with undo, a list, a status line and a confirm button."""

    def __init__(self, arm_label: str, undo_label: str, confirm_label: str, list_label: str, status_label: str,
                 status: str):
        super().__init__()
        self._confirmed = threading.Event()
        self.viewer_control = ViewerControl()
        self.arm_button = ViewerButton(arm_label, cb_hook=lambda _: self.arm_click())
        self.class_name = ViewerText("Class of next click", default_value="object")
        self.undo_button = ViewerButton(undo_label, cb_hook=lambda _: self.undo())
        self.confirm_button = ViewerButton(confirm_label, cb_hook=lambda _: self.confirm())
        self.listing = ViewerText(list_label, default_value="(none)", disabled=True)
        self.status = ViewerText(status_label, default_value=status, disabled=True)

    @property
    def viewer_running(self) -> bool:
        return getattr(self.viewer_control, "viser_server", None) is not None

    def _say(self, message: str) -> None:
        self.status.value = message

    def arm_click(self) -> None:
        """Listen for exactly one click."""
        self.viewer_control.register_pointer_cb("click", self._on_pointer)
        self._say("click one pixel on an instance")

    def _on_pointer(self, click: ViewerClick):
        if self.viewer_running:
            self.viewer_control.unregister_pointer_cb()
        return self.on_click(click)

    def on_click(self, click: ViewerClick):
        raise NotImplementedError

    def undo(self) -> None:
        raise NotImplementedError

    def confirm(self) -> None:
        raise NotImplementedError

    def _wait(self, poll_s: float = 0.2) -> None:
        while not self._confirmed.wait(poll_s):
            pass
