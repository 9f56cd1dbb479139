"""Registration settings in groups: presets, overlays, presets and transform.json files written before the groups, the CLI."""

from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path

import pytest
import yaml

from sg_nerfstudio.registration.settings import (
    GROUPS, LEGACY_KEYS, PRESETS, PresetError, RegistrationSettings, SettingsRangeError, as_record, load_preset, read_preset_values,
)

BENCH = Path(__file__).resolve().parents[1] / "configs" / "bench"

FAST_CPU_BEFORE_THE_GROUPS = """
steps: 100
lr: 0.01
lr_final: 0.0005
adam_eps: 1.0e-8
objective: teacher-on-render
loss: l1
robust: lts
lts_percentile: 50.0
images_per_step: 0
retrim_every: 4
render_scale: 4.0
near_plane: 0.7
update_centre: look-at
keypoint_weight: 10.0
keypoint_prealign_steps: 1000
prealigned_steps: 40
refine_focal: true
refine_photo_poses: true
refine_distortion: true
camera_fit: adjustment
prealigned_lr: 0.003
refine_steps: 40
refine_teacher: dense-sift
refine_lr: 0.003
refine_anchored: false
seed: 0
"""
"""fast-cpu.yaml as the package shipped it before the groups (flat keys)."""


def flat_settings_of_a_registration_before_the_groups() -> dict:
    """The "settings" of a transform.json written before the groups: every flat field, JSON values."""
    return {
        "steps": 100, "lr": 0.01, "lr_final": 0.0005, "adam_eps": 1e-08, "objective": "teacher-on-render", "loss": "l1",
        "robust": "lts", "lts_percentile": 50.0, "outlier_z": 3.0, "trim_after": 0.0, "images_per_step": 0, "retrim_every": 4,
        "teacher_input_size": None, "render_teacher": None, "render_scale": 4.0, "near_plane": 0.7, "pyramid": [],
        "pyramid_steps": 60, "hypotheses": 0, "hypothesis_deg": 20.0, "hypothesis_scales": [], "hypotheses_kept": 3,
        "level_of_detail": 1.0, "render_budget": 300000, "update_centre": "look-at", "keypoint_weight": 10.0,
        "keypoint_prealign_steps": 1000, "refine_focal": True, "refine_photo_poses": True, "refine_distortion": True,
        "camera_fit": "adjustment", "photo_pose_prior_scale": 1.0, "camera_fit_iterations": 100, "prealigned_steps": 40,
        "prealigned_lr": 0.003, "refine_steps": 40, "refine_teacher": "dense-sift", "refine_lr": 0.003, "refine_anchored": False,
        "seed": 0, "backend": "auto",
    }


def test_every_shipped_preset_loads_and_is_written_in_groups():
    for name in PRESETS:
        _, values = read_preset_values(name)
        assert set(values) <= set(GROUPS) | {"seed", "backend"}, name
        assert all(isinstance(values[group], dict) for group in set(values) & set(GROUPS)), name
        load_preset(name)


def test_a_preset_written_before_the_groups_loads_as_the_same_settings(tmp_path):
    old = tmp_path / "fast-cpu-old.yaml"
    old.write_text(FAST_CPU_BEFORE_THE_GROUPS)
    assert load_preset(old) == load_preset("fast-cpu").changed(hypotheses={"dense_start": False})  # fast-cpu then, before the dense start


def test_a_transform_json_old_or_new_gives_the_settings_it_ran_with(tmp_path):
    identity = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
    old = tmp_path / "old" / "transform.json"
    old.parent.mkdir()
    old.write_text(json.dumps({"matrix": identity, "settings": flat_settings_of_a_registration_before_the_groups()}))
    assert load_preset(old) == load_preset("fast-cpu").changed(hypotheses={"dense_start": False})  # fast-cpu then, before the dense start
    changed = load_preset("wide-cpu").changed(hypotheses={"scales": (0.8, 1.25)}, seed=3)
    new = tmp_path / "transform.json"
    new.write_text(json.dumps({"matrix": identity, "settings": as_record(changed)}))
    assert load_preset(new) == changed


@pytest.mark.parametrize("text, error, message", [
    ("optimiser:\n  images_per_step: 2\n", PresetError, r"no setting optimiser\.images_per_step \(images_per_step is now optimiser\.photos_per_step\)"),
    ("optimiser:\n  stepz: 2\n", PresetError, r"no setting optimiser\.stepz; optimiser holds adam_eps, lr, lr_final, photos_per_step, steps"),
    ("stepz: 2\n", PresetError, r"unknown key 'stepz'; expected the groups optimiser, objective"),
    ("steps: 3\noptimiser:\n  steps: 4\n", PresetError, r"sets optimiser\.steps twice \(as steps and as optimiser\.steps\)"),
    ("anchors: 3\n", PresetError, r"anchors must be a mapping of its settings"),
    ("base: no-such-preset\n", PresetError, r"no-such-preset is neither a preset name"),
    ("base: loop.yaml\n", PresetError, r"leads back to itself"),
    ("optimiser:\n  lr: .nan\n", SettingsRangeError, r"optimiser\.lr must be a finite number above 0, got nan"),
    ("anchors:\n  main_steps: 2.5\n", SettingsRangeError, r"anchors\.main_steps must be a whole number of 0 or more, got 2\.5"),
    ("coarse_to_fine:\n  factors: [1]\n", SettingsRangeError, r"coarse_to_fine\.factors must list whole numbers of 2 or more"),
    ("robust:\n  retrim_every: 0\n", SettingsRangeError, r"robust\.retrim_every must be a whole number of 1 or more"),
])
def test_a_wrong_key_or_value_in_a_preset_is_one_sentence_naming_it(tmp_path, text, error, message):
    preset = tmp_path / "loop.yaml"
    preset.write_text(text)
    with pytest.raises(error, match=message):
        load_preset(preset)


def test_changed_replaces_only_the_named_fields():
    base = load_preset("fast-cpu")
    changed = base.changed(optimiser={"steps": 7}, seed=5)
    assert changed.optimiser.steps == 7 and changed.optimiser.lr == base.optimiser.lr and changed.seed == 5
    assert dataclasses.replace(changed, optimiser=base.optimiser, seed=base.seed) == base
    assert base.optimiser.steps == 100  # the original is untouched


def test_every_old_key_names_a_field_of_its_group_and_every_field_has_one():
    fields = {f"{group}.{f.name}" for group, kind in GROUPS.items() for f in dataclasses.fields(kind)}
    assert set(LEGACY_KEYS.values()) == fields
    assert len(set(LEGACY_KEYS.values())) == len(LEGACY_KEYS)


def leaves(values: dict, prefix: str = "") -> dict[str, object]:
    """{"group.field": value} of a preset mapping without `base`."""
    out = {}
    for key, value in values.items():
        if isinstance(value, dict):
            out.update(leaves(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def base_of(path: Path) -> str:
    base = yaml.safe_load(path.read_text())["base"]
    return base if base in PRESETS else str(path.parent / base)


@pytest.mark.parametrize("variant", sorted(BENCH.glob("*.yaml")), ids=lambda path: path.stem)
def test_a_bench_variant_names_its_base_and_changes_only_what_it_is_about(variant):
    values = yaml.safe_load(variant.read_text())
    assert isinstance(values.get("base"), str), f"{variant.name} names no base preset"
    settings, base = load_preset(variant), load_preset(base_of(variant))
    own = leaves({key: value for key, value in values.items() if key != "base"})
    assert own, f"{variant.name} changes nothing"
    record, base_record = leaves(as_record(settings)), leaves(as_record(base))
    for path, value in own.items():
        assert record[path] != base_record[path], f"{variant.name} repeats its base's {path}: {value!r}"
    assert {path for path in record if record[path] != base_record[path]} == set(own), f"{variant.name} differs elsewhere"


def test_no_two_bench_variants_or_presets_are_the_same_settings():
    loaded = {path.stem: load_preset(path) for path in sorted(BENCH.glob("*.yaml"))} | {name: load_preset(name) for name in PRESETS}
    names = list(loaded)
    for i, first in enumerate(names):
        for second in names[i + 1:]:
            assert loaded[first] != loaded[second], f"{first} and {second} are the same settings"


def test_register_meta_help_shows_few_top_level_flags_and_the_groups_under_their_prefix(capsys, monkeypatch):
    from sg_nerfstudio.scripts import register_meta

    monkeypatch.setenv("COLUMNS", "80")  # one column: each option starts its own line
    with pytest.raises(SystemExit):
        register_meta.main(["--help"])
    text = capsys.readouterr().out
    flags = set(re.findall(r"^\W*(--[a-z][a-z0-9.-]*)", text, flags=re.MULTILINE))  # each option's first line
    top = {flag for flag in flags if "." not in flag}
    assert "--load-config" in top and "--seed" in top and 10 <= len(top) <= 25, sorted(top)
    for group in GROUPS:
        prefix = "--" + group.replace("_", "-") + "."
        assert any(flag.startswith(prefix) for flag in flags), group
    assert not {"--steps", "--refine-steps", "--keypoint-weight"} & top


def test_register_meta_reads_a_group_flag_over_the_preset():
    from rich.console import Console

    from sg_nerfstudio.scripts.register_meta import parse_args

    job = parse_args(["--load-config", "c.yml", "--meta-image", "m", "--output-dir", "o", "--config", "fast-cpu",
                      "--camera-fit.no-focal", "--optimiser.steps", "7"], Console(quiet=True))
    expected = load_preset("fast-cpu").changed(camera_fit={"focal": False}, optimiser={"steps": 7})
    assert job.settings == expected
    assert isinstance(job.settings, RegistrationSettings)
