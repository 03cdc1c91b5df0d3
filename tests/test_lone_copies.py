"""A class with fewer registered copies than ``min_class_copies`` is left as it was: nothing to share."""

from splatreplace_ns.poses.decision import leave_lone_copies
from splatreplace_ns.poses.config import RegistrationConfig


def _entry(success: bool) -> dict:
    return {"success": success, "message": "registered" if success else "refused"}


def test_a_class_left_with_one_registered_copy_is_not_replaced_and_the_others_are():
    classes = {1: "chair", 2: "chair", 3: "chair", 4: "table", 5: "table", 6: "lamp"}
    registration = {1: _entry(True), 2: _entry(False), 3: _entry(False),  # the chair template copy alone
                    4: _entry(True), 5: _entry(True), 6: _entry(True)}  # two tables; a lamp alone in its class
    alone = leave_lone_copies(registration, classes, min_copies=2)
    assert alone == [1, 6]
    assert [registration[i]["success"] for i in range(1, 7)] == [False, False, False, True, True, False]
    assert "1 registered copy of 'chair'" in registration[1]["message"] and "nothing to share" in registration[6]["message"]
    assert registration[2]["message"] == "refused"  # a refusal keeps its own reason


def test_min_copies_one_replaces_every_registered_instance_as_the_paper_does():
    classes = {1: "chair", 2: "lamp"}
    registration = {1: _entry(True), 2: _entry(False)}
    assert leave_lone_copies(registration, classes, min_copies=1) == []
    assert registration[1]["success"] and RegistrationConfig().min_class_copies == 2
