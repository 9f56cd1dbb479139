"""sg-feature-splat: CPU training reduces both losses, densification keeps tensors aligned, checkpoints round-trip."""

from __future__ import annotations

import shutil

import pytest
import torch

from nerfstudio.utils.eval_utils import eval_setup

from sg_nerfstudio.splat.datamanager import DatasetInputError
from sg_nerfstudio.features import TeacherConfig, TeacherInputError
from sg_nerfstudio.splat.method import SPARSE_VIEWS, short_cpu_schedule
from sg_nerfstudio.splat.training import cpu_config
from conftest import make_config


def window_mean(history, key, start, stop):
    return sum(h[key] for h in history[start:stop]) / (stop - start)


@pytest.mark.parametrize("steps, warmup, stop", [(1500, 250, 600), (3000, 500, 1200), (6000, 500, 2400)])
def test_short_cpu_schedule_densifies_within_the_run(tmp_path, steps, warmup, stop):
    """Densification starts after a sixth of a short run (never later than splatfacto's 500) and ends at 40%."""
    config = short_cpu_schedule(cpu_config(tmp_path, tmp_path, steps, TeacherConfig(name="offline")))
    model = config.pipeline.model
    assert (model.warmup_length, model.stop_split_at, model.resolution_schedule) == (warmup, stop, steps // 6)
    assert model.warmup_length < model.stop_split_at <= steps
    assert model.densify and model.densify_min_views == SPARSE_VIEWS


def test_cpu_method_is_registered_with_the_demo_schedule():
    """`ns-train sg-feature-splat-cpu` needs no page of flags: short schedule, offline teacher, this machine's device."""
    from nerfstudio.plugins.registry import discover_methods

    methods, _ = discover_methods()
    assert {"sg-feature-splat", "sg-feature-splat-cpu"} <= set(methods)
    config = methods["sg-feature-splat-cpu"]
    assert config.max_num_iterations == 3000 and config.pipeline.datamanager.teacher.name == "offline"
    model = config.pipeline.model
    assert (model.resolution_schedule, model.warmup_length, model.stop_split_at) == (500, 500, 1200)
    expected_device = "cuda" if torch.cuda.is_available() else "cpu"
    assert config.machine.device_type == methods["sg-feature-splat"].machine.device_type == expected_device


def test_training_reduces_colour_and_feature_losses(trained):
    _, history, _ = trained
    for key in ("main_loss", "feature_loss"):
        early, late = window_mean(history, key, 0, 20), window_mean(history, key, 280, 300)
        assert late < 0.8 * early, f"{key}: {early:.4f} -> {late:.4f}"


def test_the_dense_sift_teacher_trains_a_128_channel_field(tiny_scene, tmp_path):
    """`--pipeline.datamanager.teacher.name dense-sift`: the model decodes to kornia's 128-d RootSIFT and fits it."""
    from sg_nerfstudio.splat.training import train

    config = make_config(tiny_scene / "reference", tmp_path, 60, TeacherConfig(name="dense-sift", input_size=128, cache_dir=tmp_path / "cache"))
    history = []
    trainer = train(config, lambda step, trainer, losses: history.append(float(losses["feature_loss"].detach())))
    assert trainer.pipeline.model.teacher_feature_dim == 128
    assert all(torch.isfinite(torch.tensor(history))) and window_mean([{"f": v} for v in history], "f", 45, 60) < 0.8 * history[0]


def test_a_training_run_repeats_exactly_and_its_seed_changes_it(tiny_scene, tmp_path):
    """`train` seeds Python's, numpy's and torch's generators from `machine.seed` as ns-train does: the same config
    trains the same Gaussians bit for bit, whatever ran before in the process; another seed trains other ones."""
    from sg_nerfstudio.splat.training import train

    def trained_params(seed: int, run: str) -> dict:
        config = make_config(tiny_scene / "reference", tmp_path / run, 15, TeacherConfig(name="offline", input_size=128, cache_dir=tmp_path / "cache"))
        config.machine.seed = seed
        torch.rand(7)  # the global generators' state before the run must not matter
        return {name: param.detach().clone() for name, param in train(config).pipeline.model.gauss_params.items()}

    first, again, other = trained_params(0, "a"), trained_params(0, "b"), trained_params(1, "c")
    assert all(torch.equal(first[name], again[name]) for name in first)
    assert not torch.equal(first["quats"], other["quats"])


def test_densification_changes_count_and_keeps_tensors_aligned(trained):
    trainer, history, _ = trained
    counts = {h["n"] for h in history}
    assert len(counts) > 1
    model = trainer.pipeline.model
    lengths = {name: param.shape[0] for name, param in model.gauss_params.items()}
    assert set(lengths) >= {"means", "scales", "quats", "features_dc", "features_rest", "opacities", "features"}
    assert len(set(lengths.values())) == 1
    optimizers = trainer.optimizers.optimizers
    for name, param in model.gauss_params.items():
        state = optimizers[name].state[optimizers[name].param_groups[0]["params"][0]]
        assert state["exp_avg"].shape == param.shape


@pytest.mark.parametrize("densify, min_views, grows", [(True, 0, True), (False, 0, False), (True, 1000, False)])
def test_densification_can_be_switched_off_or_limited_to_many_views(tiny_scene, tmp_path, densify, min_views, grows):
    """`densify False`, or fewer training views than `densify_min_views` (the tiny scene has 14), keep the count
    of Gaussians through the first refinement step of the test schedule (step 120), where the default changes it."""
    from sg_nerfstudio.splat.training import train

    config = make_config(tiny_scene / "reference", tmp_path, 125, TeacherConfig(name="offline", input_size=128, cache_dir=tmp_path / "cache"))
    config.pipeline.model.densify, config.pipeline.model.densify_min_views = densify, min_views
    counts = []
    trainer = train(config, lambda step, trainer, losses: counts.append(trainer.pipeline.model.num_points))
    assert trainer.pipeline.model.densifies == grows
    assert (len(set(counts)) > 1) == grows, counts[::20]


def test_checkpoint_round_trip_renders_identically(trained):
    trainer, _, config = trained
    model = trainer.pipeline.model
    model.eval()
    camera = trainer.pipeline.datamanager.eval_dataset.cameras[0:1]
    before = model.get_outputs_for_camera(camera)
    assert set(before) >= {"rgb", "depth", "accumulation", "features", "feature_pca"}
    assert before["features"].shape[-1] == 36 and before["feature_pca"].shape[-1] == 3
    _, pipeline, _, _ = eval_setup(config.get_base_dir() / "config.yml", test_mode="inference")
    after = pipeline.model.get_outputs_for_camera(camera)
    for key in ("rgb", "depth", "accumulation", "features", "feature_pca"):
        assert torch.equal(before[key], after[key]), key


def test_feature_render_size_follows_the_teacher_grid(trained):
    """Features render apart at feature_render_scale x the teacher grid on the long side where that is at most
    half the image's, else jointly with the colour (always at scale 0)."""
    model = trained[0].pipeline.model
    assert model.teacher_grid_size == 16 and model.config.feature_render_scale == 1.5
    assert model.feature_render_size(48, 36) == (24, 18)
    assert model.feature_render_size(36, 48) == (18, 24)
    assert model.feature_render_size(480, 320) == (24, 16)
    assert model.feature_render_size(47, 36) is None
    model.config.feature_render_scale = 0.0
    try:
        assert model.feature_render_size(480, 320) is None
    finally:
        model.config.feature_render_scale = 1.5


def test_small_feature_render_matches_the_full_resolution_one_shrunk(trained):
    """The separate feature render (intrinsics scaled to its size) sees what the joint full-size render sees:
    both on the teacher grid agree; the same render with its principal point left unscaled does not."""
    from sg_nerfstudio.features.base import resize_bilinear
    from sg_nerfstudio.geometry.frames import viewmats_from_camera_to_worlds
    from sg_nerfstudio.render import resolve_backend

    trainer = trained[0]
    model = trainer.pipeline.model
    camera = trainer.pipeline.datamanager.train_dataset.cameras[3:4]
    model.train()
    try:
        small = model.get_outputs(camera)["feature_render"].detach()
        model.config.feature_render_scale = 0.0
        full = model.get_outputs(camera)["feature_render"].detach()
    finally:
        model.config.feature_render_scale = 1.5
        model.eval()
    assert tuple(small.shape[:2]) == (18, 24) and tuple(full.shape[:2]) == (36, 48)

    def on_grid(render):
        return resize_bilinear(render.permute(2, 0, 1)[None], (12, 16))[0]

    scale = on_grid(full).abs().mean()
    error = (on_grid(small) - on_grid(full)).abs().mean() / scale
    assert error < 0.25, float(error)  # 0.12 here: the two sample the Gaussians at different pixel centres
    unscaled = camera.get_intrinsics_matrices().clone()
    unscaled[:, 0, 0] *= 24 / 48
    unscaled[:, 1, 1] *= 18 / 36
    params = dict(model.gauss_params.items())
    viewmat = viewmats_from_camera_to_worlds(camera.camera_to_worlds)
    with torch.no_grad():
        wrong, _, _ = model._rasterize(params, params["features"], viewmat, unscaled, (24, 18), resolve_backend("auto", model.device), render_mode="RGB")
    assert (on_grid(wrong[0]) - on_grid(full)).abs().mean() / scale > 3 * error  # 1.05 here


def test_feature_pca_is_fixed_per_model(trained):
    trainer, _, _ = trained
    model = trainer.pipeline.model
    model.eval()
    cameras = trainer.pipeline.datamanager.train_dataset.cameras
    basis = model.pca_components.clone()
    for index in (0, 5):
        model.get_outputs_for_camera(cameras[index : index + 1])
    assert torch.equal(basis, model.pca_components)
    assert not torch.allclose(basis, torch.eye(basis.shape[0], 3))  # computed from teacher features
    # a colour depends only on the feature vector, not on the view it appears in (no per-frame normalisation)
    vector = torch.randn(model.teacher_feature_dim)
    first, second = torch.randn(4, 5, model.teacher_feature_dim), 3.0 * torch.randn(4, 5, model.teacher_feature_dim) + 1.0
    first[1, 2], second[3, 0] = vector, vector
    torch.testing.assert_close(model.feature_pca(first)[1, 2], model.feature_pca(second)[3, 0], rtol=0, atol=1e-6)


def test_missing_images_and_unloadable_teacher_fail_early(tiny_scene, tmp_path, monkeypatch):
    broken = tmp_path / "reference"
    shutil.copytree(tiny_scene / "reference", broken)
    (broken / "images" / "ring_003.png").unlink()
    config = make_config(broken, tmp_path / "out", 1, TeacherConfig(name="offline", input_size=64, cache_dir=tmp_path / "cache"))
    with pytest.raises(DatasetInputError, match=r"1 of the \d+ images the COLMAP model .* lists are missing .*ring_003.png"):
        config.pipeline.setup(device="cpu", test_mode="val")

    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    monkeypatch.setenv("HF_HOME", str(tmp_path / "hf"))
    config = make_config(tiny_scene / "reference", tmp_path / "out", 1, TeacherConfig(name="dinov2", input_size=112))
    with pytest.raises(TeacherInputError, match="No DINOv2 ViT-S/14 weights found"):
        config.pipeline.setup(device="cpu", test_mode="val")
    config = make_config(tiny_scene / "reference", tmp_path / "out", 1, TeacherConfig(name="offline", input_size=100))
    with pytest.raises(TeacherInputError, match="not a positive multiple"):
        config.pipeline.setup(device="cpu", test_mode="val")


def test_nerfstudio_render_and_export_work_on_the_checkpoint(trained, tmp_path):
    from nerfstudio.scripts.exporter import ExportGaussianSplat
    from nerfstudio.scripts.render import DatasetRender

    _, _, config = trained
    config_path = config.get_base_dir() / "config.yml"
    ExportGaussianSplat(load_config=config_path, output_dir=tmp_path / "export").main()
    ply = (tmp_path / "export" / "splat.ply").read_bytes()
    assert ply.startswith(b"ply") and b"element vertex" in ply
    DatasetRender(load_config=config_path, output_path=tmp_path / "renders", split="test", rendered_output_names=["rgb", "feature_pca"]).main()
    for name in ("rgb", "feature_pca"):
        assert len(list((tmp_path / "renders" / "test" / name).glob("*.jpg"))) >= 1
