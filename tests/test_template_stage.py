"""The whole splat-replace run on the tiny scene: segmentation → registration hook → shared templates →
fine-tuning, then reloading the checkpoint the way ``ns-eval`` does.

Registration itself is tested in test_register_*.py; here the hook returns the ground-truth transforms so
that the template stage is exercised on known poses.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch._dynamo.utils import counters

from splatreplace_ns.method.pipeline import SplatReplacePipeline
from splatreplace_ns.method.train import make_trainer_config, run_training
from splatreplace_ns.tools.bench import oracle
from splatreplace_ns.tools.sim import make_scene

FINETUNE = 120
RUN_STATS = {}


def ground_truth_registration(self, instances, classes, config):
    """Stands in for the registration hook: T = P_template · P_instance⁻¹ from the parsed GT poses."""
    return oracle.ground_truth_registration(instances, classes, oracle.dataset_poses(self.datamanager))


@pytest.fixture(scope="module")
def replaced(tmp_path_factory):
    data = tmp_path_factory.mktemp("tiny") / "tiny"
    make_scene("tiny", data, n_train=12)
    config = make_trainer_config(data, tmp_path_factory.mktemp("runs"), 400, 250, FINETUNE)
    config.pipeline.model.warmup_length = 100
    config.pipeline.datamanager.contrastive_uniform_samples = 1024
    config.pipeline.datamanager.contrastive_mask_samples = 512
    patch = pytest.MonkeyPatch()
    patch.setattr(SplatReplacePipeline, "register_instances", ground_truth_registration)
    torch._dynamo.reset()  # forget what earlier tests compiled: a compile during this run counts below
    frames_before = counters["frames"]["total"]
    try:
        trainer = run_training(config)
    finally:
        patch.undo()
    RUN_STATS["compiled_frames"] = counters["frames"]["total"] - frames_before
    return data, config, trainer


def test_a_whole_run_compiles_nothing(replaced):
    """torch.compile'd helpers (nerfstudio's get_viewmat) cost 9 s per process on a CPU with an empty compile
    cache and minutes on a GPU machine (a CPU and a CUDA build); no stage of the method may call one."""
    assert RUN_STATS["compiled_frames"] == 0


def test_instances_are_replaced_by_one_shared_template(replaced):
    _, config, trainer = replaced
    pipeline = trainer.pipeline
    model = pipeline.model
    assert model.stage == "finetune"
    table = model.instance_table
    assert sorted(table.ids.tolist()) == [1, 2, 3] and table.classes == ["crate"]
    assert sorted(table.slot.tolist()) == [0, 1, 2]
    classes = model.gauss_params["template_class"][:, 0].round().long()
    n_template = int((classes == 1).sum())
    assert n_template > 30
    scene = model.composed_scene()
    # each crate renders the whole template: background + 3 copies
    assert len(scene.means) == int((classes == 0).sum()) + 3 * n_template
    # fine-tuning moved the per-instance offsets and poses away from their initial values
    assert model.gauss_params["sh_offsets"].abs().sum() > 0
    assert model.instance_pose_delta.abs().sum() > 0
    assert torch.isfinite(model.instance_pose_delta).all()
    assert model.instance_colour_gain.shape == (3, 3) and not model.instance_colour_gain.any()  # off by default
    # the instances' copies of the template lie where the crates are (within the crate's size)
    poses = {int(i["id"]): i["transform_matrix"] for i in pipeline.datamanager.train_dataparser_outputs.metadata["instances"]}
    for iid in (1, 2, 3):
        centre = scene.means[scene.instance_id == iid].detach().median(dim=0).values
        scale = poses[iid][:3, :3].norm(dim=0).mean()
        assert (centre - poses[iid][:3, 3]).norm() < 1.0 * scale, iid


def test_replaced_scene_renders_and_survives_the_checkpoint(replaced, tmp_path):
    from nerfstudio.utils.eval_utils import eval_setup

    _, config, trainer = replaced
    pipeline = trainer.pipeline
    pipeline.eval()
    camera = pipeline.datamanager.eval_dataset.cameras[0:1].to(pipeline.device)
    with torch.no_grad():
        before = pipeline.model.get_outputs(camera)["rgb"]
    assert torch.isfinite(before).all()
    metrics = pipeline.get_average_eval_image_metrics()
    assert np.isfinite(metrics["psnr"]) and metrics["psnr"] > 12
    assert np.isfinite(metrics["psnr_masked"])
    # bench masks scores every run inside the scene's ground-truth masks; here those are the dataset's own
    from splatreplace_ns.tools.bench.masks import test_view_psnr_in_gt_masks

    assert test_view_psnr_in_gt_masks(pipeline, replaced[0]) == pytest.approx(metrics["psnr_masked"], abs=1e-3)
    pipeline.eval()
    # ns-eval's report scores the replaced scene's instances against the ground-truth masks
    assert metrics["segmentation"]["miou"] > 0.4, metrics["segmentation"]

    _, loaded, _, _ = eval_setup(config.get_base_dir() / "config.yml", test_mode="test")
    assert loaded.model.stage == "finetune"
    loaded.model.step = pipeline.model.step  # the SH degree in use follows the step
    with torch.no_grad():
        after = loaded.model.get_outputs(camera.to(loaded.device))["rgb"]
    assert torch.allclose(before, after, atol=1e-5)


def test_export_ply_and_instanced_file_render_the_replaced_scene(replaced, tmp_path):
    from plyfile import PlyData

    from splatreplace_ns.export import ExportCommand
    from splatreplace_ns.render import rasterize
    from splatreplace_ns.template.export import load_instanced, render_difference
    from splatreplace_ns.render import world_to_camera

    _, config, trainer = replaced
    model = trainer.pipeline.model
    model.eval()
    rows = ExportCommand(config.get_base_dir() / "config.yml", tmp_path).main()
    assert [r["gaussians"] for r in rows][-1] == model.num_points
    camera = trainer.pipeline.datamanager.eval_dataset.cameras[0:1]
    viewmat = world_to_camera(camera.camera_to_worlds)[0]
    K = camera.get_intrinsics_matrices()[0]
    W, H = int(camera.width), int(camera.height)

    def render(means, quats, log_scales, logit_opac, sh):
        return rasterize(means, quats, torch.exp(log_scales), torch.sigmoid(logit_opac).reshape(-1), sh, viewmat, K,
                         W, H, sh_degree=3, backend="torch").image

    with torch.no_grad():
        scene = model.composed_scene()
        expected = render(scene.means, scene.quats, scene.log_scales, scene.logit_opacities, scene.sh)
        # nerfstudio's exporter leaves out Gaussians below opacity 1/255 (its logit as the exporter rounds it)
        kept = scene.logit_opacities.reshape(-1) >= -5.5373
        expected_ply = render(scene.means[kept], scene.quats[kept], scene.log_scales[kept],
                              scene.logit_opacities[kept], scene.sh[kept])

    # standard 3DGS PLY, read back with plyfile
    ply = PlyData.read(str(tmp_path / "splat.ply"))["vertex"]
    n = ply.count
    assert n == int(kept.sum())

    def cols(*names):
        return torch.tensor(np.stack([np.asarray(ply[name]) for name in names], axis=-1), dtype=torch.float32)

    rest_names = sorted((p.name for p in ply.properties if p.name.startswith("f_rest_")), key=lambda s: int(s[7:]))
    rest = cols(*rest_names).reshape(n, 3, -1).transpose(1, 2)  # channel-major in the file
    sh = torch.cat((cols("f_dc_0", "f_dc_1", "f_dc_2")[:, None], rest), dim=1)
    from_ply = render(cols("x", "y", "z"), cols("rot_0", "rot_1", "rot_2", "rot_3"), cols("scale_0", "scale_1", "scale_2"),
                      cols("opacity"), sh)
    assert torch.allclose(from_ply, expected_ply, atol=2e-3)

    # compact instanced file, loaded and composed
    inst = load_instanced(tmp_path / "instanced.npz")
    composed = inst.compose()
    from_npz = render(composed.means, composed.quats, composed.log_scales, composed.logit_opacities, composed.sh)
    assert (from_npz - expected).abs().max() < 5e-3  # float16 offsets, the ones under 0.5/255 of colour dropped
    check = render_difference(model, tmp_path / "instanced.npz", trainer.pipeline.datamanager.eval_dataset.cameras)
    assert check["views"] == 1
    assert check["max_abs"] == pytest.approx(float((from_npz.clamp(0, 1) - expected.clamp(0, 1)).abs().max()), abs=1e-6)
    assert (tmp_path / "instanced.npz").stat().st_size < (tmp_path / "splat.ply").stat().st_size

    with pytest.raises(ValueError, match="not an instanced file"):
        (tmp_path / "bad.npz").write_bytes(b"not a zip")
        load_instanced(tmp_path / "bad.npz")


def test_rendered_instance_ids_follow_the_replaced_instances(replaced):
    _, _, trainer = replaced
    pipeline = trainer.pipeline
    dataset = pipeline.datamanager.eval_dataset
    ious = []
    for idx in range(len(dataset)):
        gt = dataset.get_data(idx, image_type="uint8")["instance_mask"][..., 0].long()
        ours = pipeline.model.render_instance_ids(dataset.cameras[idx : idx + 1].to(pipeline.device)).cpu()
        for iid in (1, 2, 3):
            a, b = ours == iid, gt == iid
            if b.sum() > 20:
                ious.append(float((a & b).sum()) / float((a | b).sum()))
    assert ious and float(np.mean(ious)) > 0.6, ious


def test_a_copy_colour_gain_is_rendered_stored_and_exported(replaced, tmp_path):
    from splatreplace_ns.render.sh import SH_C0
    from splatreplace_ns.template.export import instanced_arrays, load_instanced, save_instanced

    _, _, trainer = replaced
    model = trainer.pipeline.model
    saved, step = model.instance_colour_gain.detach().clone(), model.step
    model.config.copy_colour_gain = True
    try:
        with torch.no_grad():
            model.instance_colour_gain.copy_(torch.tensor([[0.2, 0.0, -0.3], [0.0, 0.0, 0.0], [-0.1, 0.1, 0.0]]))
            scene = model.composed_scene()
        row = list(model.instance_table.ids.tolist()).index(1)
        dc = scene.sh[scene.instance_id == 1][:, 0]
        model.config.copy_colour_gain = False
        with torch.no_grad():
            plain_dc = model.composed_scene().sh[scene.instance_id == 1][:, 0]
        model.config.copy_colour_gain = True
        gain = torch.exp(model.instance_colour_gain.detach()[row])
        # the DC colour (C0 · dc + 0.5) of instance 1's copy is its plain colour times the gain
        assert torch.allclose(SH_C0 * dc + 0.5, (SH_C0 * plain_dc + 0.5) * gain, atol=1e-5)
        # a state dict carries the gains into a model that has none yet
        state = {k: v.clone() if torch.is_tensor(v) else v for k, v in model.state_dict().items()}
        model.instance_colour_gain = torch.nn.Parameter(torch.zeros(0, 3))
        model.load_state_dict(state)
        assert torch.equal(model.instance_colour_gain.detach(), state["instance_colour_gain"])
        # the instanced file stores them and composes the same colours
        save_instanced(tmp_path / "gain.npz", instanced_arrays(model, colour_tolerance=0.0))
        composed = load_instanced(tmp_path / "gain.npz").compose()
        assert torch.allclose(composed.sh, scene.sh.detach(), atol=2e-3)  # float16 offsets
    finally:
        model.config.copy_colour_gain = False
        model.instance_colour_gain = torch.nn.Parameter(saved)
        model.step = step


def test_files_of_the_deleted_world_shading_are_refused_and_its_checkpoints_load(replaced, tmp_path):
    """The shading in world coordinates was deleted after measurement: an exported file that holds it would
    render other colours without it, so it is refused with the reason; a checkpoint's zero-sized entry and its
    optimizer's state are dropped on load."""
    from splatreplace_ns.template.export import instanced_arrays, load_instanced, save_instanced

    _, _, trainer = replaced
    model = trainer.pipeline.model
    arrays = instanced_arrays(model, colour_tolerance=0.0)
    arrays["class_shading"] = np.zeros((len(model.instance_table.classes), 4, 3), np.float32)
    save_instanced(tmp_path / "shaded.npz", arrays)
    with pytest.raises(ValueError, match="class_shading"):
        load_instanced(tmp_path / "shaded.npz").compose()

    state = {k: v.clone() if torch.is_tensor(v) else v for k, v in model.state_dict().items()}
    state["class_shading"] = torch.zeros(0, 4, 3)
    step = model.step
    try:
        model.load_state_dict(state)
    finally:
        model.step = step  # loading sets the step: later tests see the run as it was
    assert not hasattr(model, "class_shading")
    assert torch.equal(model.means.detach(), state["gauss_params.means"])
    optimizers = trainer.optimizers
    saved = {name: opt.state_dict() for name, opt in optimizers.optimizers.items()}
    extra = torch.optim.Adam([torch.nn.Parameter(torch.zeros(1))]).state_dict()
    optimizers.load_optimizers({**saved, "class_shading": extra})  # an earlier version's checkpoint
    with pytest.raises(KeyError):
        optimizers.optimizers["class_shading"]
