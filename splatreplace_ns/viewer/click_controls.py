"""One click at a time in nerfstudio's viewer: the controls both click flows share.

A button arms exactly one click in the 3D view (a registered click callback blocks the camera controls,
so it is removed after the click); a text field names the class of the next click; an undo button, a
list and a status line; a confirm button that releases whoever waits. Subclasses say what a click, an
undo and a confirmation do. An ``nn.Module`` only so that the viewer's scan of the pipeline finds it.

Waiting inside ``ns-train``: the trainer holds its ``train_lock`` through every training step and its
callbacks, and nerfstudio's viewer takes the same lock to render and to run any GUI button's callback. A
wait for clicks that kept the lock would freeze the viewer and block the very button that ends the wait,
so :meth:`ClickControls._wait` lets go of the lock the waiting thread holds; clicks in the 3D view take it
while they render, so that they never render at the same time as the viewer does.
"""

from __future__ import annotations

import contextlib
import threading
from typing import Callable, Optional

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
        self.render_lock: Optional[threading.Lock] = None
        """The lock the viewer renders under (the trainer's ``train_lock``); clicks render under it too."""

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
        with self.render_lock if self.render_lock is not None else contextlib.nullcontext():
            return self.on_click(click)

    def on_click(self, click: ViewerClick):
        raise NotImplementedError

    def undo(self) -> None:
        raise NotImplementedError

    def confirm(self) -> None:
        raise NotImplementedError

    def _wait(
        self, poll_s: float = 0.2, held_lock: Optional[threading.Lock] = None,
        stop_when: Optional[Callable[[], bool]] = None,
    ) -> bool:
        """Blocks until confirmed (returns True) or until ``stop_when()`` holds (checked every ``poll_s``; returns
        False). ``held_lock``, a lock this thread holds (the training thread holds the trainer's ``train_lock``
        during its callbacks), is released meanwhile: the viewer renders, and runs its buttons' callbacks, only
        under it."""
        if held_lock is not None:
            held_lock.release()
        try:
            while not self._confirmed.wait(poll_s):
                if stop_when is not None and stop_when():
                    return False
            return True
        finally:
            if held_lock is not None:
                held_lock.acquire()
