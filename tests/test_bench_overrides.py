"""``PATH=VALUE`` overrides of a trainer config (``splatreplace bench suite --overrides``) and the named
registration variants (rows of ``bench register``, values of ``bench suite --registration``)."""

from __future__ import annotations

from dataclasses import fields

import pytest

from splatreplace_ns.tools.bench.overrides import apply_overrides, parse_like
from splatreplace_ns.method.config import splat_replace_trainer_config
from splatreplace_ns.poses.config import RegistrationConfig
from splatreplace_ns.poses.variants import PAPER_REGISTRATION, REGISTRATION_VARIANTS, registration_variant


def test_overrides_set_typed_values_deep_in_the_config():
    config = splat_replace_trainer_config(10, 10, 10)
    apply_overrides(config, ["pipeline.revert.enabled=False", "pipeline.revert.max_views=4", "pipeline.revert.margin_db=2",
                             "pipeline.registration.up_axis=[0, 1, 0]", "pipeline.registration.select=inliers"])
    assert config.pipeline.revert.enabled is False and config.pipeline.revert.max_views == 4
    assert config.pipeline.revert.margin_db == 2.0 and isinstance(config.pipeline.revert.margin_db, float)
    assert config.pipeline.registration.up_axis == (0, 1, 0) and config.pipeline.registration.select == "inliers"
    apply_overrides(config, ["pipeline.revert.enabled=true"])
    assert config.pipeline.revert.enabled is True


@pytest.mark.parametrize("item, message", [
    ("pipeline.revert.enabled", "is not PATH=VALUE"),
    ("=3", "is not PATH=VALUE"),
    ("pipeline.revert.enable=True", "pipeline.revert has no field 'enable'; its fields: enabled"),
    ("pipelin.revert.enabled=True", "the config has no field 'pipelin'"),
    ("pipeline.revert=True", "a group of settings"),
    ("pipeline.revert.enabled=maybe", "expected True or False"),
    ("pipeline.revert.max_views=2.5", "pipeline.revert.max_views=2.5: invalid literal"),
    ("pipeline.registration.up_axis=3", "expected a JSON list"),
])
def test_bad_overrides_say_what_is_wrong(item, message):
    config = splat_replace_trainer_config(10, 10, 10)
    before = config.pipeline.revert.enabled, config.pipeline.revert.max_views
    with pytest.raises(ValueError, match=message.replace("[", r"\[").replace(".", r"\.")):
        apply_overrides(config, [item])
    assert (config.pipeline.revert.enabled, config.pipeline.revert.max_views) == before


def test_parse_like_keeps_none_fields_open():
    assert parse_like("3", None, "x") == 3 and parse_like("model.onnx", None, "x") == "model.onnx"


def test_the_paper_variant_is_section_4_2_as_written():
    base = RegistrationConfig(select="photometric", multistart_turns=12, upright=True)
    paper = registration_variant("paper", base)
    assert paper.select == "inliers" and paper.multistart_turns == 0 and paper.icp and not paper.upright
    assert paper.min_fitness == 0 and paper.min_opacity == 0 and paper.method == "ours"
    # the matcher and the view sphere are the defaults' (the paper's MASt3R has no offline weights)
    assert (paper.robust_matcher, paper.n_azimuth, paper.top_k) == (base.robust_matcher, base.n_azimuth, base.top_k)
    assert set(PAPER_REGISTRATION) <= {f.name for f in fields(RegistrationConfig)}


def test_each_variant_changes_only_what_it_names():
    base = RegistrationConfig()
    assert registration_variant("ours", base) == base
    names = {f.name for f in fields(RegistrationConfig)}
    for name, changes in REGISTRATION_VARIANTS.items():
        variant = registration_variant(name, base)
        changed = {n for n in names if getattr(variant, n) != getattr(base, n)}
        assert changed <= set(changes), (name, changed)
        assert set(changes) <= names
    with pytest.raises(ValueError, match="unknown registration variant 'nope'; choose from ours, paper"):
        registration_variant("nope", base)


def test_bench_register_rows_are_the_variants():
    from splatreplace_ns.tools.bench.register import BenchRegisterConfig
    from splatreplace_ns.tools.bench.register_rows import row_configs

    cfg = BenchRegisterConfig()
    rows = dict(row_configs(cfg, ("ours", "paper", "no_virtual_views")))
    assert rows["paper"] == registration_variant("paper", cfg.registration)
    assert rows["no_virtual_views"].method == "no_virtual_views"
