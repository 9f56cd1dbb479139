"""Level of detail of the frozen reference: moment matching, what merges, and that the render barely changes."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

import pytest
import torch

from sg_nerfstudio.registration.level_of_detail import coarsen, distinct_row_ids, footprint_cells, merge, plan_merge
from sg_nerfstudio.geometry.frames import viewmat
from sg_nerfstudio.geometry.sim3 import Sim3
from sg_nerfstudio.registration.reference import ReferenceModel
from sg_nerfstudio.registration.visibility import MAX_ROTATION_DEG, MAX_VOXEL_DOUBLINGS, CullingCamera, VisibleSubset
from sg_nerfstudio.render import rasterize
from sg_nerfstudio.render.projection import cull_gaussians


def model_of(means, covars, opacities, colors) -> ReferenceModel:
    """A ReferenceModel holding just these Gaussians (RGB colours, 2 features each)."""
    return ReferenceModel(
        config_path=Path("none"), checkpoint_path=Path("none"), model=None, world_to_dataparser=None, teacher=None,
        means=means, covars=covars, opacities=opacities, gaussian_features=colors[:, :2].clone(), feature_bias=torch.zeros(0),
        colors=colors, sh_degree=0, background=torch.zeros(3),
    )


def textured_plane(count: int, seed: int) -> ReferenceModel:
    """`count` tiny flat Gaussians about the plane z = 3 (x, y in [-1, 1], z within a few thousandths, as a
    trained surface is) coloured by a smooth pattern."""
    generator = torch.Generator().manual_seed(seed)
    xy = torch.rand(count, 2, generator=generator) * 2 - 1
    means = torch.cat([xy, 3.0 + 0.003 * torch.randn(count, 1, generator=generator)], dim=1)
    covars = torch.diag_embed(torch.tensor([0.012, 0.012, 0.001]) ** 2).expand(count, 3, 3).clone()
    colors = torch.stack([0.5 + 0.4 * torch.sin(3 * xy[:, 0]), 0.5 + 0.4 * torch.cos(2 * xy[:, 1]), 0.5 + 0.3 * xy[:, 0] * xy[:, 1]], dim=1)
    return model_of(means, covars, torch.full((count,), 0.9), colors)


def camera(width=64, height=48, focal=50.0):
    K = torch.tensor([[[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]]])
    return torch.eye(4)[None], K, width, height


def render(model: ReferenceModel, viewmats, Ks, width, height):
    rgb, alpha, _ = rasterize(model.means, None, None, model.opacities, model.colors, viewmats, Ks, width, height, covars=model.covars)
    return rgb, alpha


def cells_for(model: ReferenceModel, viewmats, Ks, width, height, pixels=1.0):
    depths, seen = cull_gaussians(model.means, model.covars, viewmats, Ks, width, height)
    return footprint_cells(depths, Ks[:, 0, 0], seen, pixels)


def test_two_gaussians_merge_by_opacity_weighted_moments():
    covars = torch.diag_embed(torch.tensor([[1.0, 4.0, 0.25], [4.0, 1.0, 1.0]], dtype=torch.float64) * 1e-4)
    model = model_of(torch.tensor([[0.0, 0.0, 1.0], [0.02, 0.0, 1.0]], dtype=torch.float64), covars,
                     torch.tensor([0.5, 0.8], dtype=torch.float64), torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], dtype=torch.float64))
    merged = merge(model, plan_merge(model.means, model.covars, torch.full((2,), 0.1, dtype=torch.float64)))
    assert merged.count == 1
    area = torch.tensor([2e-4, 2e-4], dtype=torch.float64)  # product of the two largest standard deviations
    weights = model.opacities * area
    mean = (weights[:, None] * model.means).sum(0) / weights.sum()
    torch.testing.assert_close(merged.means[0], mean)
    offsets = model.means - mean
    covariance = (weights[:, None, None] * (covars + offsets[:, :, None] * offsets[:, None, :])).sum(0) / weights.sum()
    torch.testing.assert_close(merged.covars[0], covariance)
    torch.testing.assert_close(merged.colors[0], (weights[:, None] * model.colors).sum(0) / weights.sum())
    largest = torch.linalg.eigvalsh(covariance)[1:].prod().sqrt()
    torch.testing.assert_close(merged.opacities[0], (weights.sum() / largest).clamp(max=1.0))


def test_gaussians_larger_than_their_cell_and_lone_ones_are_unchanged():
    model = textured_plane(200, seed=1)
    big = merge(model, plan_merge(model.means, model.covars, torch.full((200,), 0.01)))  # cells below every extent
    assert big.count == 200 and torch.equal(big.means, model.means)
    far_apart = model.means * torch.tensor([100.0, 100.0, 1.0])  # one Gaussian per cell
    alone = plan_merge(far_apart, model.covars, torch.full((200,), 0.05))
    assert alone.count == 200
    kept = merge(model_of(far_apart, model.covars, model.opacities, model.colors), alone)
    torch.testing.assert_close(kept.opacities.sort().values, model.opacities.sort().values)


def test_coarsened_plane_renders_the_same_image_with_far_fewer_gaussians():
    model = textured_plane(30_000, seed=0)
    viewmats, Ks, width, height = camera()
    coarse = coarsen(model, cells_for(model, viewmats, Ks, width, height))
    assert coarse.count < model.count / 5
    full_rgb, full_alpha = render(model, viewmats, Ks, width, height)
    lod_rgb, lod_alpha = render(coarse, viewmats, Ks, width, height)
    # Two random draws of the same plane differ by 0.004 / 0.001; clamping the merged opacity at 1 without growing
    # the merged Gaussians (holes between them) gave 0.045 / 0.035.
    assert (full_rgb - lod_rgb).abs().mean() < 0.02
    assert (full_alpha - lod_alpha).abs().mean() < 0.025
    # A camera four times closer resolves finer detail: cells shrink with depth, fewer Gaussians merge.
    closer = torch.eye(4)[None].clone()
    closer[0, 2, 3] = -2.25  # the plane at depth 0.75
    nearer = coarsen(model, cells_for(model, closer, Ks, width, height))
    assert nearer.count > coarse.count


def test_cells_follow_the_nearest_camera_that_sees_the_gaussian():
    depths = torch.tensor([[2.0, 4.0, 8.0], [4.0, 1.0, 8.0]])
    seen = torch.tensor([[True, True, False], [True, False, False]])
    cells = footprint_cells(depths, torch.tensor([100.0, 50.0]), seen, pixels=2.0)
    torch.testing.assert_close(cells[:2], torch.tensor([0.04, 0.08]))
    assert torch.isinf(cells[2])


def test_a_render_budget_coarsens_only_models_that_exceed_it():
    model = textured_plane(30_000, seed=0)
    viewmats, Ks, width, height = camera()
    cameras = [CullingCamera(viewmats[0, :3].double(), Ks[0], width, height)]
    one_pixel = VisibleSubset(model, cameras, level_of_detail=1.0).for_pose(Sim3.identity())
    within = VisibleSubset(model, cameras, level_of_detail=1.0, render_budget=one_pixel.count)
    assert within.for_pose(Sim3.identity()).count == one_pixel.count and within.voxel_pixels == 1.0
    over = VisibleSubset(model, cameras, level_of_detail=1.0, render_budget=one_pixel.count // 2)
    coarser = over.for_pose(Sim3.identity())
    assert over.voxel_pixels in (2.0, 4.0) and coarser.count <= one_pixel.count // 2
    # The budget only chooses the voxel: the model is the one merged at that voxel directly.
    direct = VisibleSubset(model, cameras, level_of_detail=over.voxel_pixels).for_pose(Sim3.identity())
    for name in ("means", "covars", "opacities", "colors", "gaussian_features"):
        assert torch.equal(getattr(direct, name), getattr(coarser, name)), name
    # A budget no voxel can meet stops at the largest voxel allowed rather than merging the model away.
    tiny = VisibleSubset(model, cameras, level_of_detail=1.0, render_budget=1)
    assert tiny.for_pose(Sim3.identity()).count > 1 and tiny.voxel_pixels == 2.0**MAX_VOXEL_DOUBLINGS


def turned_about_y(degrees: float) -> Sim3:
    angle = math.radians(degrees)
    rotation = [[math.cos(angle), 0.0, math.sin(angle)], [0.0, 1.0, 0.0], [-math.sin(angle), 0.0, math.cos(angle)]]
    return Sim3.from_parts(1.0, rotation, [0.0, 0.0, 0.0])


def test_a_held_cull_serves_every_pose_until_released():
    model = textured_plane(2000, seed=1)
    viewmats, Ks, width, height = camera()
    visible = VisibleSubset(model, [CullingCamera(viewmats[0, :3].double(), Ks[0], width, height)], level_of_detail=1.0)
    visible.for_pose(Sim3.identity())
    near, far = turned_about_y(1.0), turned_about_y(3.0 * MAX_ROTATION_DEG)
    with visible.held_at(near):  # culled again at exactly the held pose, though within the bounds of the last cull
        assert visible.culls == 2 and np.array_equal(visible.pose.matrix, near.matrix)
        held = visible.subset
        assert visible.for_pose(far) is held and visible.culls == 2  # a pose beyond the bounds: the held model
    assert visible.for_pose(far) is not held and visible.culls == 3  # released: the pose is culled for again
    with visible.held_at(far):  # already culled there
        assert visible.culls == 3


@pytest.mark.parametrize("spread", [3000, 2**40])  # packed into one int64; ranges beyond 63 bits: unique over rows
def test_distinct_row_ids_number_rows_as_unique_over_rows_does(spread):
    generator = torch.Generator().manual_seed(0)
    keys = torch.cat([torch.randint(-1, 4, (2000, 1), generator=generator), torch.randint(-spread, spread, (2000, 3), generator=generator)], 1)
    keys = torch.cat([keys, keys[:500]])  # repeated rows share an id
    assert torch.equal(distinct_row_ids(keys), torch.unique(keys, dim=0, return_inverse=True)[1])
    assert distinct_row_ids(keys[:0]).shape == (0,)


def test_a_held_cull_renders_probes_at_the_hold_bound_as_the_whole_model():
    """`optimize.held_for_probes`' premise: the model culled at a pose renders the camera turned by the re-cull rotation,
    or moved sideways by that angle times the depth, exactly as the whole model does (a plane reaching past the view)."""
    wide = textured_plane(20_000, seed=2)
    wide = model_of(wide.means * torch.tensor([6.0, 6.0, 1.0]), wide.covars, wide.opacities, wide.colors)  # x, y in [-6, 6]
    viewmats, Ks, width, height = camera()
    eye = CullingCamera(viewmats[0, :3].double(), Ks[0], width, height)
    visible = VisibleSubset(wide, [eye])
    with visible.held_at(Sim3.identity()):
        held = visible.for_pose(Sim3.identity())
    assert held.count < wide.count / 2  # the view holds less than half of the plane
    sideways = 3.0 * math.tan(math.radians(MAX_ROTATION_DEG))  # the plane is at depth 3
    probes = [turned_about_y(MAX_ROTATION_DEG), turned_about_y(-MAX_ROTATION_DEG),
              Sim3.from_parts(1.0, np.eye(3), [sideways, 0.0, 0.0]), Sim3.from_parts(1.0, np.eye(3), [0.0, -sideways, 0.0])]
    for probe in probes:
        view = viewmat(probe.to_torch().move_camera(eye.cam_from_meta)).float()[None]
        for ours, whole in zip(render(held, view, Ks, width, height), render(wide, view, Ks, width, height)):
            torch.testing.assert_close(ours, whole)
