"""Learning-rate schedules follow the run's stage lengths, on the command line as in-process; overrides reach into
the optimizers."""

import copy
import math

import pytest
import torch

from splatreplace_ns.method.config import SplatReplaceTrainer, splat_replace_method, splat_replace_trainer_config
from splatreplace_ns.tools.bench.overrides import apply_overrides


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
    assert cli_rates["means"][1] == pytest.approx(math.sqrt(1.6e-4 * 1.6e-6))  # half-way: the geometric mean
    assert cli_rates["means"][-1] == pytest.approx(1.6e-6)  # held through fine-tuning
    assert from_cli.optimizers["camera_opt"]["scheduler"].max_steps == 1001  # its 1000-step warm-up, then decay
    assert from_cli.max_num_iterations == 450


def test_an_override_reaches_into_the_optimizers(tmp_path):
    config = splat_replace_trainer_config(300, 50, 100)
    apply_overrides(config, ["optimizers.features_rest.optimizer.lr=0.0025"])
    assert config.optimizers["features_rest"]["optimizer"].lr == 0.0025


def test_override_into_a_dict_names_its_keys_when_wrong():
    config = splat_replace_trainer_config(300, 50, 100)
    with pytest.raises(ValueError, match="means"):
        apply_overrides(config, ["optimizers.positions.scheduler.lr_final=1e-5"])
