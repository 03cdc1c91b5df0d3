"""Learning-rate schedules follow the run's stage lengths, on the command line as in-process, and the SH offsets'
rate per degree (``offset_rest_scale``)."""

import copy
import math

import pytest
import torch

from splatreplace_ns.method.config import SplatReplaceTrainer, splat_replace_method, splat_replace_trainer_config
from splatreplace_ns.method.schedules import position_lr
from splatreplace_ns.template.compose import compose_scene, offset_weights
from splatreplace_ns.tools.bench.overrides import apply_overrides


def test_positions_decay_over_the_base_stage_then_hold_then_decay_again_in_fine_tuning():
    kw = dict(lr_init=1.6e-4, lr_final=1.6e-6, base_steps=100, finetune_start=150, finetune_steps=50)
    assert position_lr(0, finetune_lr=0.0, **kw) == pytest.approx(1.6e-4)
    assert position_lr(50, finetune_lr=0.0, **kw) == pytest.approx(math.sqrt(1.6e-4 * 1.6e-6))  # geometric midpoint
    for step in (100, 120, 149, 150, 175, 199, 500):  # frozen as before when fine-tuning has no rate of its own
        assert position_lr(step, finetune_lr=0.0, **kw) == pytest.approx(1.6e-6)
    assert position_lr(149, finetune_lr=1.6e-5, **kw) == pytest.approx(1.6e-6)
    assert position_lr(150, finetune_lr=1.6e-5, **kw) == pytest.approx(1.6e-5)
    assert position_lr(175, finetune_lr=1.6e-5, **kw) == pytest.approx(math.sqrt(1.6e-5 * 1.6e-6))
    assert position_lr(200, finetune_lr=1.6e-5, **kw) == pytest.approx(1.6e-6)


def _scheduled_rates(config, steps):
    """The positions' and the camera optimiser's rates at ``steps``, from the schedulers nerfstudio would build."""
    rates = {}
    for name in ("means", "camera_opt"):
        entry = config.optimizers[name]
        param = torch.nn.Parameter(torch.zeros(1))
        optimizer = torch.optim.SGD([param], lr=entry["optimizer"].lr)
        scheduler = entry["scheduler"].setup().get_scheduler(optimizer, entry["optimizer"].lr)
        values = []
        for step in range(max(steps) + 1):
            if step in steps:
                values.append(optimizer.param_groups[0]["lr"])
            optimizer.step()
            scheduler.step()
        rates[name] = values
    return rates


def test_the_registered_method_and_an_in_process_config_schedule_alike(tmp_path):
    """`ns-train splat-replace --pipeline.base-iterations 300` edits the registered config (built for 30000 base
    steps); a config built in-process for 300 steps is the same run. Both decay the positions over 300 steps."""
    from_cli = copy.deepcopy(splat_replace_method.config)
    from_cli.pipeline.base_iterations, from_cli.pipeline.contrastive_iterations = 300, 50
    from_cli.pipeline.finetune_iterations = 100
    in_process = splat_replace_trainer_config(300, 50, 100)
    for config in (from_cli, in_process):
        config.output_dir = tmp_path
        SplatReplaceTrainer(config)
    steps = [0, 150, 299, 300, 349, 350, 449]
    cli_rates, own_rates = _scheduled_rates(from_cli, steps), _scheduled_rates(in_process, steps)
    assert cli_rates == own_rates
    assert cli_rates["means"][3] == pytest.approx(1.6e-6)  # the end of the base stage, not 1 % of the way to it
    assert from_cli.optimizers["camera_opt"]["scheduler"].max_steps == 1001  # its 1000-step warm-up, then decay
    assert from_cli.max_num_iterations == 450


def test_positions_get_a_fine_tuning_rate_from_an_override(tmp_path):
    config = splat_replace_trainer_config(300, 50, 100)
    apply_overrides(config, ["optimizers.means.scheduler.finetune_lr=1.6e-5"])
    config.output_dir = tmp_path
    SplatReplaceTrainer(config)
    rates = _scheduled_rates(config, [349, 350, 449])["means"]
    assert rates[0] == pytest.approx(1.6e-6) and rates[1] == pytest.approx(1.6e-5)
    assert rates[2] == pytest.approx(1.6e-5 * (1.6e-6 / 1.6e-5) ** (99 / 100))


def test_override_into_a_dict_names_its_keys_when_wrong():
    config = splat_replace_trainer_config(300, 50, 100)
    with pytest.raises(ValueError, match="means"):
        apply_overrides(config, ["optimizers.positions.scheduler.finetune_lr=1e-5"])


def test_offsets_above_degree_zero_are_scaled_and_the_dc_offset_is_not():
    torch.manual_seed(0)
    n, K = 5, 4
    args = dict(means=torch.randn(n, 3), quats=torch.randn(n, 4), log_scales=torch.randn(n, 3),
                logit_opacities=torch.randn(n), sh=torch.randn(n, K, 3), sh_offsets=torch.randn(n, 1, K, 3),
                gauss_class=torch.ones(n, dtype=torch.long), instance_class=torch.tensor([1]),
                instance_slot=torch.tensor([0]), instance_ids=torch.tensor([7]), pose_q=torch.tensor([[1.0, 0, 0, 0]]),
                pose_R=torch.eye(3)[None], pose_t=torch.zeros(1, 3), lam=0.8)
    full, scaled, shared = (compose_scene(**args, offset_rest_scale=s) for s in (1.0, 0.05, 0.0))
    expected_dc = 0.8 * args["sh"][:, 0] + 0.2 * args["sh_offsets"][:, 0, 0]
    for scene in (full, scaled, shared):
        assert torch.allclose(scene.sh[:, 0], expected_dc)
    assert torch.allclose(shared.sh[:, 1:], 0.8 * args["sh"][:, 1:])
    assert torch.allclose(scaled.sh[:, 1:], 0.8 * args["sh"][:, 1:] + 0.2 * 0.05 * args["sh_offsets"][:, 0, 1:])
    assert offset_weights(K, 0.05, args["sh"]).flatten().tolist() == pytest.approx([1.0, 0.05, 0.05, 0.05])
