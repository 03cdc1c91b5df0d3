"""One click at a time in nerfstudio's viewer: the controls both click flows share.

A button arms exactly one click in the 3D view (a registered click callback blocks the camera controls,
so it is removed after the click); a text field names the class of the next click; an undo button, a
list and a status line; a confirm button that releases whoever waits; a "View through image" list that puts the
view at a training image's camera (its pose and field of view), so that what a person clicks there lies at the
same pixel as in that image. Subclasses say what a click, an undo and a confirmation do. An ``nn.Module`` only
so that the viewer's scan of the pipeline finds it.

nerfstudio's viewer puts the elements it finds in a folder named after the pipeline's attribute (e.g.
``mask_click_controls``), in alphabetical order; when it sets its ``ViewerControl`` objects up, right after,
the elements are moved into a folder with the panel's title, in the order a person uses them.

Waiting inside ``ns-train``: the trainer holds its ``train_lock`` through every training step and its
callbacks, and nerfstudio's viewer takes the same lock to render and to run any GUI button's callback. A
wait for clicks that kept the lock would freeze the viewer and block the very button that ends the wait,
so :meth:`ClickControls._wait` lets go of the lock the waiting thread holds; clicks in the 3D view take it
while they render, so that they never render at the same time as the viewer does.
"""

from __future__ import annotations

import contextlib
import math
import threading
from pathlib import Path
from typing import Callable, Dict, List, Optional

import numpy as np
from torch import nn

from nerfstudio.viewer.viewer_elements import (
    ViewerButton, ViewerClick, ViewerControl, ViewerDropdown, ViewerElement, ViewerParameter, ViewerText,
)

FREE_VIEW = "(free view)"
"""The "View through image" entry that leaves the view where it is."""


class _PanelControl(ViewerControl):
    """The controls' ``ViewerControl``: nerfstudio's viewer sets it up once it has installed every GUI element it
    found, which is when the panel gets its title and order (``ClickControls.arrange_panel``)."""

    def __init__(self, on_setup: Callable[[object], None]):
        self._on_setup = on_setup

    def _setup(self, viewer) -> None:
        super()._setup(viewer)
        self._on_setup(viewer)


class ClickControls(nn.Module):
    """Viewer elements for one click per item, with undo, a list, a status line and a confirm button, in a panel
    titled ``title``."""

    def __init__(self, title: str, arm_label: str, undo_label: str, confirm_label: str, list_label: str,
                 status_label: str, status: str):
        super().__init__()
        self._confirmed = threading.Event()
        self.title = title
        self.viewer_control = _PanelControl(self.arrange_panel)
        self.view_image = ViewerDropdown("View through image", FREE_VIEW, [FREE_VIEW],
                                         cb_hook=lambda element: self.look_through(element.value),
                                         hint="puts the view at this training image's camera")
        self.arm_button = ViewerButton(arm_label, cb_hook=lambda _: self.arm_click())
        self.class_name = ViewerText("Class of next click", default_value="object")
        self.undo_button = ViewerButton(undo_label, cb_hook=lambda _: self.undo())
        self.confirm_button = ViewerButton(confirm_label, cb_hook=lambda _: self.confirm())
        self.listing = ViewerText(list_label, default_value="(none)", disabled=True)
        self.status = ViewerText(status_label, default_value=status, disabled=True)
        self.render_lock: Optional[threading.Lock] = None
        """The lock the viewer renders under (the trainer's ``train_lock``); clicks render under it too."""
        self._viewer = None
        self._image_cameras: Dict[str, int] = {}

    def panel_elements(self) -> List[ViewerElement]:
        """The panel's elements, in the order a person uses them."""
        return [self.view_image, self.class_name, self.arm_button, self.undo_button, self.confirm_button,
                self.listing, self.status]

    def arrange_panel(self, viewer) -> None:
        """Moves the elements nerfstudio's viewer installed into a folder titled ``self.title``, in the order of
        :meth:`panel_elements`, and lists the training images under "View through image"."""
        self._viewer = viewer
        self._image_cameras = _training_images(viewer)
        # a viewer that connects starts from its own view, whatever image the list names
        viewer.viser_server.on_client_connect(lambda _: setattr(self.view_image, "value", FREE_VIEW))
        self.view_image.options = [FREE_VIEW] + list(self._image_cameras)
        elements = self.panel_elements()
        if any(e.gui_handle is None for e in elements):  # not installed by this viewer: nothing to arrange
            if self.view_image.gui_handle is not None:
                self.view_image.set_options(self.view_image.options)
            return
        gui = viewer.viser_server.gui
        containers = gui._container_handle_from_id  # viser keeps no public way from an element to its folder
        old_folder = containers[elements[0].gui_handle._impl.parent_container_id]
        parent = containers[old_folder._parent_container_id]
        for element in elements:
            if isinstance(element, ViewerParameter):
                element.default_value = element.value  # a new handle starts from it
            element.remove()
        if not old_folder._children:
            old_folder.remove()
        with parent, gui.add_folder(self.title):
            for element in elements:
                element.install(viewer.viser_server)  # the hooks the viewer wrapped (its lock) stay on the element

    def look_through(self, name: str) -> None:
        """Puts every connected viewer's camera at the camera of training image ``name``: its pose, and its
        vertical field of view (the width shown follows the window's shape)."""
        if self._viewer is None or name not in self._image_cameras:
            return
        from nerfstudio.viewer.viewer import VISER_NERFSTUDIO_SCALE_RATIO

        camera = self._viewer.pipeline.datamanager.train_dataset.cameras[self._image_cameras[name]]
        c2w = camera.camera_to_worlds.reshape(3, 4).double().cpu().numpy()
        rotation = c2w[:, :3] @ np.diag([1.0, -1.0, -1.0])  # OpenGL → OpenCV axes: x right, y down, z forward
        position = c2w[:, 3] * VISER_NERFSTUDIO_SCALE_RATIO
        fov = 2.0 * math.atan(float(camera.height) / (2.0 * float(camera.fy)))
        for client in self._viewer.viser_server.get_clients().values():
            with client.atomic():
                client.camera.fov = fov
                client.camera.position = position
                client.camera.look_at = position + rotation[:, 2]
                client.camera.up_direction = -rotation[:, 1]
            client.flush()  # sent now, ahead of the status line below (which goes to every viewer on its own)
        self._say(f"the view looks through {name}: press '{self.arm_button.name}', then click what it shows")

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


def _training_images(viewer) -> Dict[str, int]:
    """{name shown: index} of the viewer's training images, named by their path under the dataset folder."""
    try:
        dataset = viewer.pipeline.datamanager.train_dataset
        filenames = list(dataset.image_filenames)
        data = Path(viewer.pipeline.datamanager.get_datapath())
    except AttributeError:
        return {}
    root = data.parent if data.suffix == ".json" else data
    names = {}
    for index, filename in enumerate(filenames):
        path = Path(filename)
        try:
            name = path.relative_to(root).as_posix()
        except ValueError:
            name = path.name
        names.setdefault(name, index)
    return names
