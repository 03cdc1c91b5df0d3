"""The viewer's "Select instances" controls.

"Select instances" arms one click in the 3D view; the clicked ray becomes an instance (highlighted,
listed, undoable). "Confirm instances" ends the selection and lets training continue. The pipeline
owns an instance of this; nerfstudio's viewer finds the elements on it.
"""

from __future__ import annotations

import threading
from typing import Callable, Optional

import torch

from nerfstudio.viewer.viewer_elements import ViewerClick

from splatreplace_ns.instances.from_clicks import SelectionError
from splatreplace_ns.viewer.click_controls import ClickControls



class InstanceSelectionControls(ClickControls):
    """The segmentation stage's click controls; the pipeline's selection does the work.

    ``pipeline``: the ``SplatReplacePipeline`` that owns these controls (not imported here: the viewer sits below
    the method)."""

    def __init__(self, pipeline):
        super().__init__("Instance selection", "Select instances", "Undo last instance", "Confirm instances",
                         "Instances", "Selection status", "waits for the segmentation stage")
        self._pipeline = [pipeline]  # a list keeps the pipeline out of this module's children

    @property
    def _owner(self):
        # private on purpose: nerfstudio's viewer walks every public attribute of the pipeline's modules for
        # its GUI elements, and a public way back to the pipeline sends that walk round in a circle
        return self._pipeline[0]

    @staticmethod
    def _listing(items, not_replaced=(), pose_probability=None) -> str:
        # instances labelled otherwise than by clicks (ground truth) carry no Gaussian count
        chance = pose_probability or {}
        return "; ".join(
            f"{i['id']}: {i.get('class', 'object')}" + (f" ({i['num_gaussians']} G)" if "num_gaussians" in i else "")
            + (" (not replaced)" if int(i["id"]) in not_replaced else "")
            + (f" (pose right: {chance[int(i['id'])]:.0%})" if int(i["id"]) in chance else "")
            for i in items
        ) or "(none)"

    def show_selected(self, instances, not_replaced=(), pose_probability=None) -> None:
        """A run loaded after its segmentation (``ns-viewer``, a resumed run), or after its registration: its
        instances, listed, those left as they were (``not_replaced`` ids) marked, and with ``pose_probability``
        ({id: p}) the chance each chosen pose is right (``splatreplace_ns.poses.pose_probability``)."""
        self.listing.value = self._listing(instances, {int(i) for i in not_replaced},
                                           {int(k): float(v) for k, v in (pose_probability or {}).items()})
        self._say(f"{len(instances)} instances were selected when this run was trained")

    def _refresh(self) -> None:
        selection = self._owner.selection
        items = selection.summary() if selection else []
        self.listing.value = self._listing(items)
        model = self._owner.model
        model.highlight = (selection.labels() > 0) if (selection and items) else None

    def arm_click(self) -> None:
        if self._owner.selection is None:
            self._say("selection opens when training reaches the segmentation stage")
            return
        super().arm_click()

    def on_click(self, click: ViewerClick) -> Optional[int]:
        """Adds the clicked instance; a bad click only changes the status message."""
        selection = self._owner.selection
        if selection is None:
            self._say("selection opens when training reaches the segmentation stage")
            return None
        try:
            with torch.no_grad():
                query = self._owner.query_from_ray(click.origin, click.direction)
            instance = selection.add(query, self.class_name.value or "object", f"viewer click {len(selection.instances) + 1}")
        except SelectionError as err:
            self._say(str(err))
            return None
        self._refresh()
        self._say(f"added instance {instance.id} ({instance.cls}, {instance.num_gaussians} Gaussians)")
        return instance.id

    def undo(self) -> None:
        selection = self._owner.selection
        removed = selection.undo() if selection else None
        self._refresh()
        self._say(f"removed instance {removed.id}" if removed else "nothing to undo")

    def confirm(self) -> None:
        selection = self._owner.selection
        if selection is None or not selection.instances:
            self._say("select at least one instance before confirming")
            return
        self._say(f"confirmed {len(selection.instances)} instances; training continues")
        self._confirmed.set()

    def wait_for_confirm(
        self, poll_s: float = 0.2, held_lock: Optional[threading.Lock] = None,
        stop_when: Optional[Callable[[], bool]] = None,
    ) -> bool:
        """Blocks the training thread until "Confirm instances" is pressed (True) or ``stop_when()`` holds
        (False; see ``_wait``, also for ``held_lock``)."""
        self._confirmed.clear()
        self._say("click 'Select instances', then one pixel per instance; 'Confirm instances' when done")
        confirmed = self._wait(poll_s, held_lock, stop_when)
        self._owner.model.highlight = None
        if not confirmed:
            self._say("clicks.json appeared: the instances are selected from it")
        return confirmed
