"""poses/class_evidence.py: a copy's chosen pose judged against its class's other copies, against known poses."""

import math

import numpy as np
import pytest
import torch

from splatreplace_ns.poses.candidates import yaw_rotation
from splatreplace_ns.poses.class_evidence import CLASS_EVIDENCE, chosen_poses, class_agreement
from splatreplace_ns.poses.config import RegistrationConfig
from splatreplace_ns.poses.instance import InstanceGaussians


def _template_points():
    """A box of grid points (N, 3), mapped onto itself by a half turn about its vertical axis, whose colour is not:
    red where x > 0, blue elsewhere, so that only colour tells a half-turn flip."""
    axes = np.linspace(-0.5, 0.5, 10), np.linspace(-0.25, 0.25, 6), np.linspace(0.0, 0.6, 7)
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    rgb = np.where(pts[:, :1] > 0, [[0.9, 0.1, 0.1]], [[0.1, 0.1, 0.9]])
    return pts, rgb


def _copy(pts, rgb, world_from_template: np.ndarray, iid: int) -> InstanceGaussians:
    """The template's points placed in the world by ``world_from_template`` [4, 4]."""
    world = pts @ world_from_template[:3, :3].T + world_from_template[:3, 3]
    n = len(pts)
    return InstanceGaussians(means=world, quats=np.tile([1.0, 0, 0, 0], (n, 1)), scales=np.full((n, 3), 0.02),
                             opacities=np.ones(n), colors=rgb, id=iid)


def _placement(yaw_deg: float, offset) -> np.ndarray:
    T = yaw_rotation(torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), math.radians(yaw_deg),
                     torch.zeros(3, dtype=torch.float64)).numpy()
    T[:3, 3] += offset
    return T


def _class_of_four(flip_copy: int = 0):
    """Copies 1 (the template) to 4 of one class placed at known poses, and a registration whose chosen poses are the
    true ones, except copy ``flip_copy``'s, which is turned by half a turn about its centre."""
    pts, rgb = _template_points()
    placements = {1: _placement(0, [0, 0, 0]), 2: _placement(40, [3, 0, 0]), 3: _placement(130, [0, 3, 0]),
                  4: _placement(250, [3, 3, 0])}
    instances = {i: _copy(pts, rgb, T, i) for i, T in placements.items()}
    registration = {}
    for i, T in placements.items():
        pose = np.linalg.inv(T)  # template ≈ pose · copy
        if i == flip_copy:
            centre = torch.as_tensor(instances[i].centres().mean(axis=0))
            pose = pose @ yaw_rotation(torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), math.pi, centre).numpy()
        registration[i] = {"template": 1, "proposed_transform": None if i == 1 else pose.tolist(),
                           "image_choice": None if i == 1 else {"chosen": 0}}
    return instances, registration


def test_right_poses_agree_and_a_flip_is_told_by_colour():
    cfg = RegistrationConfig(min_solid_points=10)
    instances, registration = _class_of_four(flip_copy=3)
    classes = {i: "box" for i in instances}
    out = class_agreement(instances, registration, classes, cfg)
    assert set(out) == {1, 2, 3, 4}
    for i in (2, 4):  # right poses: every point lands on a point of each other copy, and (mostly) on its colour
        assert out[i]["class_fitness"] > 0.95
        assert out[i]["class_colour_margin"] > 0.3
    # the flip fits the shape as well as a right pose, but the class's colours prefer its half turn
    assert out[3]["class_fitness"] > 0.95
    assert out[3]["class_colour_margin"] < 0.0
    assert out[3]["class_colour"] < out[2]["class_colour"]


def test_a_copy_alone_in_its_class_and_a_copy_with_no_chosen_pose():
    cfg = RegistrationConfig(min_solid_points=10)
    instances, registration = _class_of_four()
    registration[4]["image_choice"] = {"chosen": None}  # seen in no view: nothing was chosen, nothing to judge
    classes = {1: "box", 2: "box", 3: "chair", 4: "box"}
    assert set(chosen_poses(registration)) == {1, 2, 3}
    out = class_agreement(instances, registration, classes, cfg)
    assert set(out) == {1, 2, 3}
    assert out[3] == dict.fromkeys(CLASS_EVIDENCE)  # the only chair
    assert out[1]["class_fitness"] > 0.95 and out[2]["class_fitness"] > 0.95


def test_a_copy_of_a_handful_of_gaussians_and_an_empty_one_stay_finite():
    cfg = RegistrationConfig(min_solid_points=10)
    instances, registration = _class_of_four()
    few = instances[2]
    instances[2] = InstanceGaussians(few.means[:3], few.quats[:3], few.scales[:3], few.opacities[:3], few.colors[:3], id=2)
    empty = instances[4]
    instances[4] = InstanceGaussians(empty.means[:0], empty.quats[:0], empty.scales[:0], empty.opacities[:0],
                                     empty.colors[:0], id=4)
    out = class_agreement(instances, registration, {i: "box" for i in instances}, cfg)
    assert set(out) == {1, 2, 3}  # the empty copy is not judged and judges nothing
    assert all(v is not None and np.isfinite(v) for row in out.values() for v in row.values())
    assert out[2]["class_fitness"] == 1.0  # its three points lie on the template's and on copy 3's


def test_empty_registration():
    assert class_agreement({}, {}, {}, RegistrationConfig()) == {}


def test_class_agreement_places_each_copy_on_the_others_by_their_chosen_poses():
    """Three copies of an asymmetric shape (1 the template); copy 2 is posed rightly, copy 3 turned half a turn: 3
    agrees with neither 1 nor 2 in colour, 1 and 2 agree with each other and with nothing of 3's."""
    rng = np.random.default_rng(0)
    half = rng.uniform(-0.5, 0.5, (150, 3)) * [1.0, 0.6, 0.4]
    pts = np.concatenate((half, half * [-1.0, -1.0, 1.0]))  # a shape the half turn about z maps onto itself
    rgb = np.where(pts[:, :1] > 0, [[0.9, 0.1, 0.1]], [[0.1, 0.1, 0.9]])  # red on +x, blue on -x: its texture does not

    def copy(shift):
        return InstanceGaussians(means=pts + shift, quats=np.tile([1.0, 0, 0, 0], (300, 1)), scales=np.full((300, 3), 0.02),
                                 opacities=np.ones(300), colors=rgb)

    instances = {1: copy([0, 0, 0]), 2: copy([3.0, 0, 0]), 3: copy([0, 3.0, 0])}
    right = np.eye(4)
    right[:3, 3] = [-3.0, 0, 0]
    flip = np.diag([-1.0, -1.0, 1.0, 1.0])  # home, then a half turn about z
    to_home = np.eye(4)
    to_home[:3, 3] = [0.0, -3.0, 0.0]
    registration = {1: {"template": 1}, 2: {"template": 1, "proposed_transform": right, "image_choice": {"chosen": 0}},
                    3: {"template": 1, "proposed_transform": flip @ to_home, "image_choice": {"chosen": 0}}}
    agreement = class_agreement(instances, registration, {1: "a", 2: "a", 3: "a"}, RegistrationConfig())
    assert agreement[2]["class_colour"] > 0.45  # right on the template, wrong only against the flipped copy 3
    assert agreement[3]["class_colour"] < 0.1 and agreement[3]["class_fitness"] > 0.9  # the shape fits, not the colours
    assert agreement[1]["class_colour"] == pytest.approx(agreement[2]["class_colour"])
    # turned by half a turn, copy 3 would agree with both others: its margin is below 0; copy 2's is not
    assert agreement[3]["class_colour_margin"] < -0.5 and agreement[2]["class_colour_margin"] >= 0
