"""Teacher features: DINOv2 architecture and weight loading, the offline and dense SIFT descriptors, the disk cache."""

from __future__ import annotations

import math
import re

import pytest
import torch

from sg_nerfstudio.features import FeatureCache, TeacherConfig, TeacherInputError, build_teacher, extract_all
from sg_nerfstudio.features.dinov2 import Dinov2Teacher, load_vits14, vits14_architecture


@pytest.fixture(scope="module")
def random_vits14():
    torch.manual_seed(0)
    return vits14_architecture()


def smooth_image(seed: int, height: int = 60, width: int = 80) -> torch.Tensor:
    """A structured test image in [0.1, 0.8]: blurred noise with edges (no saturation)."""
    gen = torch.Generator().manual_seed(seed)
    coarse = torch.rand(3, height // 10, width // 10, generator=gen)
    image = torch.nn.functional.interpolate(coarse[None], size=(height, width), mode="nearest")[0]
    image = image + 0.1 * torch.rand(3, height, width, generator=gen)
    return (0.1 + 0.6 * image / image.max()).permute(1, 2, 0).contiguous()


def test_dinov2_random_weights_shapes_grid_and_normalisation(random_vits14):
    teacher = Dinov2Teacher(TeacherConfig(input_size=112, device="cpu"), model=random_vits14)
    assert teacher.grid_size == 8 and teacher.feature_dim == 384
    features = teacher.extract(smooth_image(0))
    # 80x60 image -> 112x84 input (aspect kept) -> 8 x 6 patches
    assert features.shape == (6, 8, 384) and features.dtype == torch.float32
    assert teacher.grid_shape(60, 80) == (6, 8) and teacher.grid_shape(80, 60) == (8, 6)
    assert teacher.extract(smooth_image(0, height=80, width=60)).shape == (8, 6, 384)
    # final LayerNorm (weight 1, bias 0 at init): every patch token has zero mean and unit variance
    torch.testing.assert_close(features.mean(-1), torch.zeros(6, 8), atol=1e-4, rtol=0)
    torch.testing.assert_close(features.var(-1, unbiased=False), torch.ones(6, 8), atol=1e-3, rtol=0)
    # ImageNet normalisation happens inside: a different image gives different tokens
    assert not torch.allclose(features, teacher.extract(smooth_image(1)))


def torch_hub_state_dict(model) -> dict:
    """The facebookresearch/dinov2 (torch hub) key layout of a transformers Dinov2Model, built by hand."""
    state = model.state_dict()
    out = {
        "cls_token": state["embeddings.cls_token"],
        "mask_token": state["embeddings.mask_token"],
        "pos_embed": state["embeddings.position_embeddings"],
        "patch_embed.proj.weight": state["embeddings.patch_embeddings.projection.weight"],
        "patch_embed.proj.bias": state["embeddings.patch_embeddings.projection.bias"],
        "norm.weight": state["layernorm.weight"],
        "norm.bias": state["layernorm.bias"],
    }
    for i in range(12):
        p = f"encoder.layer.{i}."
        for kind in ("weight", "bias"):
            out[f"blocks.{i}.attn.qkv.{kind}"] = torch.cat([state[p + f"attention.{n}_proj.{kind}"] for n in "qkv"])
            out[f"blocks.{i}.attn.proj.{kind}"] = state[p + f"attention.o_proj.{kind}"]
            for name in ("norm1", "norm2", "mlp.fc1", "mlp.fc2"):
                out[f"blocks.{i}.{name}.{kind}"] = state[p + f"{name}.{kind}"]
        out[f"blocks.{i}.ls1.gamma"] = state[p + "layer_scale1.lambda1"]
        out[f"blocks.{i}.ls2.gamma"] = state[p + "layer_scale2.lambda1"]
    return out


def test_dinov2_loads_torch_hub_checkpoint_from_explicit_path_and_cache(tmp_path, monkeypatch, random_vits14):
    with torch.no_grad():
        for param in random_vits14.parameters():
            param.add_(torch.randn_like(param) * 0.01)  # non-default layer norms and scales
    checkpoint = tmp_path / "dinov2_vits14_pretrain.pth"
    torch.save(torch_hub_state_dict(random_vits14), checkpoint)
    image = smooth_image(2)
    expected = Dinov2Teacher(TeacherConfig(input_size=56, device="cpu"), model=random_vits14).extract(image)

    explicit = Dinov2Teacher(TeacherConfig(input_size=56, device="cpu", weights=checkpoint))
    torch.testing.assert_close(explicit.extract(image), expected, atol=1e-5, rtol=1e-5)

    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    (tmp_path / "torch" / "hub" / "checkpoints").mkdir(parents=True)
    checkpoint.rename(tmp_path / "torch" / "hub" / "checkpoints" / checkpoint.name)
    from_cache = Dinov2Teacher(TeacherConfig(input_size=56, device="cpu"))
    torch.testing.assert_close(from_cache.extract(image), expected, atol=1e-5, rtol=1e-5)


def test_dinov2_missing_weights_error_lists_every_place(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    monkeypatch.setenv("HF_HOME", str(tmp_path / "hf"))
    monkeypatch.delenv("HF_HUB_CACHE", raising=False)
    with pytest.raises(TeacherInputError) as error:
        load_vits14(None)
    message = str(error.value)
    assert str(tmp_path / "torch" / "hub" / "checkpoints" / "dinov2_vits14_pretrain.pth") in message
    assert str(tmp_path / "hf" / "hub" / "models--facebook--dinov2-small") in message
    assert "teacher.name offline" in message and message.count("\n") == 0
    with pytest.raises(TeacherInputError, match="does not exist"):
        load_vits14(tmp_path / "nowhere.pth")
    garbage = tmp_path / "garbage.pth"
    garbage.write_bytes(b"not a checkpoint")
    with pytest.raises(TeacherInputError, match="Could not read DINOv2"):
        load_vits14(garbage)


@pytest.mark.parametrize("name,size,step", [("dinov2", 1000, 14), ("offline", 250, 8), ("dense-sift", 250, 8), ("hog-layout", 250, 8)])
def test_grid_size_must_be_a_multiple_of_the_patch(name, size, step):
    with pytest.raises(TeacherInputError, match=rf"not a positive multiple of .* \({step} pixels\)"):
        build_teacher(TeacherConfig(name=name, input_size=size, weights=None))


@pytest.mark.parametrize("name,dim", [("offline", 36), ("dense-sift", 128), ("hog-layout", 324)])
def test_weight_free_descriptor_shape_and_appearance_invariance(name, dim):
    teacher = build_teacher(TeacherConfig(name=name, input_size=64))
    image = smooth_image(3)
    features = teacher.extract(image)
    assert features.shape == (6, 8, dim) and teacher.feature_dim == dim  # 80x60 -> 64x48 input (aspect kept) -> 8 x 6 cells
    portrait = smooth_image(3, height=80, width=60)
    assert teacher.extract(portrait).shape == (8, 6, dim) == (*teacher.grid_shape(80, 60), dim)
    # photos of any size with the same aspect ratio get the same grid (no stretch differs between them)
    assert teacher.grid_shape(120, 160) == teacher.grid_shape(60, 80) == (6, 8)
    changed_image = (image * 1.5 * torch.tensor([1.15, 1.0, 0.8])).clamp(0, 1) ** 0.8  # exposure, white balance, gamma
    feature_change = ((teacher.extract(changed_image) - features).norm() / features.norm()).item()
    rgb_change = ((changed_image - image).norm() / image.norm()).item()
    assert rgb_change > 0.3
    assert feature_change < 0.1 * rgb_change
    other = teacher.extract(smooth_image(4))  # but a different scene does move it
    assert ((other - features).norm() / features.norm()).item() > 5 * feature_change


def test_dense_sift_map_follows_the_image_one_cell_per_cell():
    """Output (i, j) describes the neighbourhood of cell (i, j): moving the image by one cell (8 px) moves the
    map by one cell, and a structure's descriptor sits at the cell the structure is in."""
    from sg_nerfstudio.features.dense_sift import CELL

    teacher = build_teacher(TeacherConfig(name="dense-sift", input_size=96))
    image = smooth_image(5, height=72, width=96)  # exactly the input size: 9 x 12 cells, no resize
    features = teacher.extract(image)
    moved = teacher.extract(torch.roll(image, shifts=(CELL, 2 * CELL), dims=(0, 1)))
    torch.testing.assert_close(moved[3:-1, 4:-1], features[2:-2, 2:-3], rtol=0, atol=1e-5)
    flat = torch.full((72, 96, 3), 0.4)
    flat[36:44, 48:56] = 0.8  # a bright square centred 4.5 cells down and 6 across (cell centres at 0, 1, ...)
    sees_square = teacher.extract(flat).norm(dim=-1) > 0.5  # RootSIFT: unit length where there is structure, ~0 where flat
    rows, columns = torch.nonzero(sees_square, as_tuple=True)
    assert 0 < len(rows) < sees_square.numel() / 4
    assert (rows.float().mean().item(), columns.float().mean().item()) == (4.5, 6.0)  # the cells that see it surround it


def test_dense_sift_sampled_pooling_is_kornias_dense_sift():
    """The descriptors pooled only where kornia samples its pooled maps are kornia's, values and gradients."""
    teacher = build_teacher(TeacherConfig(name="dense-sift", input_size=64))
    torch.manual_seed(0)
    for height, width in ((48, 64), (64, 40), (8, 16)):
        image = torch.rand(2, 1, height, width, dtype=torch.float64)
        image[0, :, : height // 2] = 0.3  # flat: zero descriptors, zero gradients
        ours, theirs = image.clone().requires_grad_(True), image.clone().requires_grad_(True)
        weights = torch.rand(2, 128, height // 8, width // 8, dtype=torch.float64)
        (teacher.sampled_descriptors(ours) * weights).sum().backward()
        reference = teacher.descriptor.double()(theirs)
        (reference * weights).sum().backward()
        torch.testing.assert_close(teacher.sampled_descriptors(image), reference.detach(), rtol=0, atol=1e-12)
        torch.testing.assert_close(ours.grad, theirs.grad, rtol=1e-9, atol=1e-12)
        teacher.descriptor.float()


def test_offline_sobel_matches_the_convolution_it_replaces():
    from sg_nerfstudio.features.offline import _sobel

    channels = torch.rand(3, 17, 23, generator=torch.Generator().manual_seed(0))
    kernel = torch.tensor([[-1.0, 0.0, 1.0], [-2.0, 0.0, 2.0], [-1.0, 0.0, 1.0]]) / 8.0
    kernels = torch.stack([kernel, kernel.T])[:, None]  # [2, 1, 3, 3]: d/dx, d/dy
    expected = torch.nn.functional.conv2d(torch.nn.functional.pad(channels[:, None], (1, 1, 1, 1), mode="replicate"), kernels)
    gx, gy = _sobel(channels)
    assert torch.allclose(gx, expected[:, 0], atol=1e-6) and torch.allclose(gy, expected[:, 1], atol=1e-6)
    ramp = torch.arange(5.0)[None, None].expand(1, 4, 5)  # brightness rising to the right
    assert torch.allclose(_sobel(ramp)[0][:, :, 1:-1], torch.ones(1, 4, 3))  # kernel / 8: the slope itself


def test_offline_cell_histograms_match_per_pixel_histograms_pooled():
    """The fused cell histogram equals the definition: per-pixel soft-binned votes, summed over channels,
    averaged over each cell (values and gradients)."""
    import math

    from sg_nerfstudio.features.offline import ORIENTATIONS, _cell_orientation_histograms

    generator = torch.Generator().manual_seed(1)
    gx = torch.randn(3, 16, 24, generator=generator, requires_grad=True)
    gy = torch.randn(3, 16, 24, generator=generator, requires_grad=True)
    magnitude = torch.sqrt(gx**2 + gy**2)
    position = (torch.atan2(gy, gx) % (2 * math.pi)) / (2 * math.pi) * ORIENTATIONS
    lower = torch.floor(position.detach())
    lower_bin = torch.nn.functional.one_hot(lower.long() % ORIENTATIONS, ORIENTATIONS).permute(0, 3, 1, 2)
    upper_bin = torch.nn.functional.one_hot((lower.long() + 1) % ORIENTATIONS, ORIENTATIONS).permute(0, 3, 1, 2)
    weight = (position - lower)[:, None]
    per_pixel = (magnitude[:, None] * ((1 - weight) * lower_bin + weight * upper_bin)).sum(0)  # [B, H, W]
    expected = torch.nn.functional.avg_pool2d(per_pixel[None], 8)[0]
    fused = _cell_orientation_histograms(gx, gy, 8)
    assert fused.shape == (ORIENTATIONS, 2, 3)
    torch.testing.assert_close(fused, expected, rtol=1e-5, atol=1e-6)
    probe = torch.randn(fused.shape, generator=generator)
    grads = torch.autograd.grad((fused * probe).sum(), (gx, gy))
    expected_grads = torch.autograd.grad((expected * probe).sum(), (gx, gy))
    for grad, expected_grad in zip(grads, expected_grads):
        torch.testing.assert_close(grad, expected_grad, rtol=1e-4, atol=1e-5)


class CountingTeacher:
    """Wraps a teacher and counts extractions."""

    def __init__(self, inner, extra_setting=0):
        self.inner, self.calls, self.extra = inner, 0, extra_setting
        self.feature_dim, self.grid_size = inner.feature_dim, inner.grid_size

    def settings(self):
        return {**self.inner.settings(), "extra": self.extra}

    def extract(self, image):
        self.calls += 1
        return self.inner.extract(image)


def test_rendered_maps_reach_the_teacher_grid_by_averaging_their_footprint():
    """Shrinking to the grid averages each cell's footprint (every rendered pixel gets a gradient);
    same-size and enlarging resizes are plain bilinear."""
    from sg_nerfstudio.features.base import resize_bilinear

    generator = torch.Generator().manual_seed(0)
    maps = torch.rand(1, 3, 120, 160, generator=generator, requires_grad=True)
    on_grid = resize_bilinear(maps, (24, 32))
    on_grid.sum().backward()
    assert on_grid.shape == (1, 3, 24, 32) and bool((maps.grad > 0).all())
    blocks = maps.detach().reshape(1, 3, 24, 5, 32, 5).mean(dim=(3, 5))  # 5 x 5 footprint per cell
    assert float((on_grid.detach() - blocks).abs().mean()) < 0.05 < float((maps.detach()[..., 2::5, 2::5] - blocks).abs().mean())

    small = torch.rand(1, 3, 6, 8, generator=generator)
    assert resize_bilinear(small, (6, 8)) is small
    enlarged = torch.nn.functional.interpolate(small, size=(12, 16), mode="bilinear", align_corners=False)
    assert torch.equal(resize_bilinear(small, (12, 16)), enlarged)


def test_cache_hits_misses_and_corruption(tmp_path, capsys):
    cache = FeatureCache(tmp_path / "cache")
    teacher = CountingTeacher(build_teacher(TeacherConfig(name="offline", input_size=32)))
    images = [(smooth_image(i) * 255).to(torch.uint8) for i in range(3)]
    first = extract_all(images, 3, teacher, cache, "test")
    assert teacher.calls == 3 and len(list((tmp_path / "cache").glob("*.pt"))) == 3
    again = extract_all(images, 3, teacher, cache, "test")
    assert teacher.calls == 3
    for a, b in zip(first, again):
        assert torch.equal(a, b)

    images[1] = images[1].clone()
    images[1][0, 0, 0] ^= 1  # one changed pixel
    extract_all(images, 3, teacher, cache, "test")
    assert teacher.calls == 4
    other_settings = CountingTeacher(teacher.inner, extra_setting=1)
    extract_all(images, 3, other_settings, cache, "test")
    assert other_settings.calls == 3

    victim = sorted((tmp_path / "cache").glob("*.pt"))[0]
    victim.write_bytes(b"\x00garbage")
    capsys.readouterr()
    teacher.calls = other_settings.calls = 0
    extract_all(images, 3, teacher, cache, "test")
    extract_all(images, 3, other_settings, cache, "test")
    assert teacher.calls + other_settings.calls == 1
    assert re.search(r"Ignoring corrupt feature cache file", capsys.readouterr().out)


@pytest.mark.parametrize("name", ["offline", "dense-sift", "hog-layout", "dinov2"])
def test_describe_is_extract_with_gradients_and_a_forced_grid(name, random_vits14):
    """Registration's teacher-on-render objective differentiates the teacher through the rendered image."""
    torch.manual_seed(0)
    if name != "dinov2":
        teacher = build_teacher(TeacherConfig(name=name, input_size=64, device="cpu"))
    else:
        teacher = Dinov2Teacher(TeacherConfig(name="dinov2", input_size=56, device="cpu"), model=random_vits14)
    image = torch.rand(30, 40, 3)
    image[:, :12] = 0.5  # a flat region: where sqrt and atan2 have no derivative at zero gradient
    torch.testing.assert_close(teacher.describe(image.clone()).detach(), teacher.extract(image), rtol=0, atol=1e-6)
    pixels = image.clone().requires_grad_(True)
    forced = teacher.describe(pixels, (5, 7))
    assert forced.shape == (5, 7, teacher.feature_dim)
    forced.square().sum().backward()
    assert torch.isfinite(pixels.grad).all() and pixels.grad.abs().sum() > 0


def test_hog_layout_sees_a_blurred_hazy_render_as_its_photo_and_keeps_where_structure_is():
    """What a render of a reference model does to a photo (blur, haze: contrast pulled towards a grey) moves the
    hog-layout map far less than another scene does, and less than it moves dense SIFT's; and the layout part tells
    apart two images whose cells hold the same orientations in another arrangement."""
    import kornia

    image = smooth_image(7, height=96, width=128)
    blurred = kornia.filters.gaussian_blur2d(image.permute(2, 0, 1)[None], (5, 5), (0.7, 0.7))[0].permute(1, 2, 0)
    rendered_look = 0.6 * blurred + 0.4 * torch.tensor([0.55, 0.6, 0.7])  # blur, then haze towards a bluish grey
    other_scene = smooth_image(8, height=96, width=128)

    def look_over_scene_change(name: str) -> float:
        teacher = build_teacher(TeacherConfig(name=name, input_size=128))
        features = teacher.extract(image)
        change = [(teacher.extract(other) - features).abs().sum(-1).mean().item() for other in (rendered_look, other_scene)]
        return change[0] / change[1]

    layout_ratio = look_over_scene_change("hog-layout")
    assert layout_ratio < 0.5 and layout_ratio < 0.75 * look_over_scene_change("dense-sift")
    bar = torch.full((64, 64, 3), 0.1)
    bar[:, 24:40] = 0.9  # a vertical bar...
    edges = torch.full((64, 64, 3), 0.1)
    edges[:, :16], edges[:, 48:] = 0.9, 0.9  # ...and bars at the sides instead: the same edges, elsewhere
    teacher = build_teacher(TeacherConfig(name="hog-layout", input_size=64))
    centre = (slice(3, 5), slice(3, 5))
    assert (teacher.extract(bar)[centre] - teacher.extract(edges)[centre]).abs().sum(-1).mean() > 0.1


def test_a_feature_splat_trains_on_the_hog_layout_teacher(tiny_scene, tmp_path):
    """The new teacher as a reference's teacher: ns-train's datamanager caches its maps and the model distils all 324
    channels (a few steps: the run works end to end; accuracy is the benchmarks' business)."""
    from conftest import make_config

    from sg_nerfstudio.splat.training import train

    config = make_config(tiny_scene / "reference", tmp_path, 12, TeacherConfig(name="hog-layout", input_size=128, cache_dir=tmp_path / "cache"))
    losses = []
    trainer = train(config, lambda step, trainer, step_losses: losses.append({k: float(v.detach()) for k, v in step_losses.items()}))
    assert trainer.pipeline.model.teacher_feature_dim == 324
    assert len(losses) == 12 and all(math.isfinite(value) for step in losses for value in step.values())
    assert any("feature" in name for name in losses[0]) and len(list((tmp_path / "cache").glob("*.pt"))) > 0
